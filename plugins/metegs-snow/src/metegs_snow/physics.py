"""Snowfall physics: pure functions of scalars, each with its unit and source.

R is the snowfall rate in mm/h of *water equivalent* (what a heated gauge or a station's precipitation
amount measures), D_m the diameter of the water drop a snowflake melts into (mm) and D the flake's own
largest dimension (mm).

Size distribution — Gunn, K. L. S. and Marshall, J. S. (1958), "The distribution with size of aggregate
snowflakes", J. Meteor. 15, 452–461:

    N(D_m) = N0 · exp(−Λ·D_m),   N0 = 3.8·10³ · R^−0.87  m⁻³ mm⁻¹,   Λ = 25.5 · R^−0.48 cm⁻¹ = 2.55 · R^−0.48 mm⁻¹.

D_m is the *melted* diameter. The numbers check: the water flux the distribution carries at a fall speed
v is (π/6)·∫D_m³·N·v dD_m = π·N0·v/Λ⁴; with v = 1 m/s this is 1.0165·R^1.05 mm/h (π·3800/2.55⁴ mm³ m⁻³
× 1 m/s × 3600 s/h / 10⁶ mm² m⁻²), i.e. R within −10 %/+13 % over 0.1–10 mm/h (the exponents give
N0/Λ⁴ ∝ R^1.05). Read as flake diameters with the Locatelli–Hobbs mass below, the same distribution would
carry 0.073·N0·Γ(2.4)/Λ^2.4 ≈ 0.13 mm/h at R = 1 mm/h: an eighth of the rate.

Fall speed and mass — Locatelli, J. D. and Hobbs, P. V. (1974), "Fall speeds and masses of solid
precipitation particles", J. Geophys. Res. 79(15), 2185–2197, for aggregates of unrimed radiating
assemblages of dendrites (the common large snowflake):

    v = 0.8 · D^0.16  m/s,    m = 0.073 · D^1.4  mg     (D in mm, the flake's maximum dimension)

so a flake of melted diameter D_m has D = ((π/6)·ρ_w·D_m³ / 0.073)^(1/1.4) with ρ_w = 1 mg/mm³
(D_m = 1 mm → D = 4.1 mm, density 0.02 g/cm³, v = 1.0 m/s), never less than D_m itself.

Consequence of the two fits: N0/Λ falls with R while Λ falls faster, so heavier snow is made of bigger,
not more, flakes. The number of flakes above a size cut-off peaks near 2 mm/h and then slowly declines;
their projected area per volume (what the camera sees) keeps rising up to about 12 mm/h with the default
size range, so the model clamps R at ``MAX_RATE_MM_H`` = 10 mm/h (beyond the heaviest snowfalls on
record, ~ 10 cm of fresh snow an hour): every rendered quantity is then non-decreasing in R except the
flake count, whose docstring says so.

Caveat: the geometric-optics extinction of these flakes, 2 × their projected area per volume, is 0.022 m⁻¹
at 1 mm/h (a visibility of about 135 m by the 5 % contrast rule); reports for dry snow are usually several hundred metres at that
rate. Unrimed dendrite aggregates are the fluffiest class (0.02 g/cm³ at 4 mm); a denser mass law (the
``mass_coeff_mg`` / ``mass_exponent`` options) gives smaller flakes for the same water.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np
import torch

GM_N0_COEFF_PER_M3_PER_MM = 3.8e3
"""Gunn–Marshall intercept at R = 1 mm/h, m⁻³ mm⁻¹ (Gunn & Marshall 1958)."""
GM_N0_EXPONENT = -0.87
"""Exponent of R in N0 (Gunn & Marshall 1958)."""
GM_LAMBDA_COEFF_PER_MM = 2.55
"""Gunn–Marshall slope at R = 1 mm/h, mm⁻¹ (25.5 cm⁻¹; Gunn & Marshall 1958)."""
GM_LAMBDA_EXPONENT = -0.48
"""Exponent of R in Λ (Gunn & Marshall 1958)."""
LH_SPEED_COEFF_M_S = 0.8
"""Locatelli–Hobbs fall speed v = 0.8·D^0.16 m/s (D in mm), unrimed dendrite aggregates (1974)."""
LH_SPEED_EXPONENT = 0.16
"""Exponent of D in the fall speed (Locatelli & Hobbs 1974)."""
LH_MASS_COEFF_MG = 0.073
"""Locatelli–Hobbs mass m = 0.073·D^1.4 mg (D in mm), unrimed dendrite aggregates (1974)."""
LH_MASS_EXPONENT = 1.4
"""Exponent of D in the mass (Locatelli & Hobbs 1974)."""
WATER_MG_PER_MM3 = 1.0
"""Density of liquid water, mg/mm³."""
MAX_RATE_MM_H = 10.0
"""Largest snowfall rate used (water equivalent, mm/h); larger rates are clamped to it (see the module docstring)."""


def gm_intercept_per_m3_per_mm(rate_mm_h: float) -> float:
    """N0 = 3.8·10³·R^−0.87 m⁻³ mm⁻¹ (Gunn & Marshall 1958); 0 for R = 0 (no snow)."""
    return 0.0 if rate_mm_h <= 0 else GM_N0_COEFF_PER_M3_PER_MM * rate_mm_h**GM_N0_EXPONENT


def gm_lambda_per_mm(rate_mm_h: float) -> float:
    """Λ = 2.55·R^−0.48 mm⁻¹ (Gunn & Marshall 1958, 25.5 cm⁻¹); +inf for R = 0 (decreasing in R)."""
    return math.inf if rate_mm_h <= 0 else GM_LAMBDA_COEFF_PER_MM * rate_mm_h**GM_LAMBDA_EXPONENT


def gm_number_density_per_m3(rate_mm_h: float, d_min_mm: float = 0.5, d_max_mm: float = 3.0) -> float:
    """Flakes per m³ with melted diameter in [d_min, d_max]: (N0/Λ)(e^−Λ·d_min − e^−Λ·d_max); 0 for R = 0.

    Not monotone: it rises to a maximum near 2 mm/h (d_min = 0.5 mm) and then falls slowly (bigger flakes)."""
    lam = gm_lambda_per_mm(rate_mm_h)
    if math.isinf(lam):
        return 0.0
    n0 = gm_intercept_per_m3_per_mm(rate_mm_h)
    return n0 / lam * (math.exp(-lam * d_min_mm) - math.exp(-lam * d_max_mm))


def gm_water_flux_mm_h(rate_mm_h: float, speed_m_s: float = 1.0) -> float:
    """Water-equivalent flux π·N0·v/Λ⁴ (mm/h) of the untruncated distribution at a constant fall speed v (m/s).

    The consistency check of the fit: ≈ R for v ≈ 1 m/s (1.0165·R^1.05)."""
    lam = gm_lambda_per_mm(rate_mm_h)
    if math.isinf(lam):
        return 0.0
    mm3_per_m3 = math.pi * gm_intercept_per_m3_per_mm(rate_mm_h) / lam**4
    return mm3_per_m3 * speed_m_s * 3600.0 / 1e6


def gm_sample_melted_diameter_mm(
    u: torch.Tensor, rate_mm_h: float, d_min_mm: float = 0.5, d_max_mm: float = 3.0
) -> torch.Tensor:
    """Inverse CDF of the truncated Gunn–Marshall distribution: melted diameters (mm) for uniforms u in [0, 1) -> same shape."""
    lam = gm_lambda_per_mm(rate_mm_h)
    if math.isinf(lam):
        return torch.full_like(u, d_min_mm)
    span = 1.0 - math.exp(-lam * (d_max_mm - d_min_mm))
    return d_min_mm - torch.log1p(-u * span) / lam


def flake_diameter_mm(
    melted_mm: torch.Tensor, mass_coeff_mg: float = LH_MASS_COEFF_MG, mass_exponent: float = LH_MASS_EXPONENT
) -> torch.Tensor:
    """Flake maximum dimension D (mm) holding the water of a drop of D_m (mm): m = 0.073·D^1.4 mg inverted
    (Locatelli & Hobbs 1974), never below D_m (no flake is denser than water). Non-decreasing in D_m; any shape."""
    water_mg = math.pi / 6.0 * WATER_MG_PER_MM3 * melted_mm**3
    return torch.maximum((water_mg / mass_coeff_mg) ** (1.0 / mass_exponent), melted_mm)


def fall_speed_m_s(flake_mm: torch.Tensor | float) -> torch.Tensor | float:
    """Terminal fall speed v = 0.8·D^0.16 m/s of a flake of maximum dimension D mm (Locatelli & Hobbs 1974)."""
    return LH_SPEED_COEFF_M_S * flake_mm**LH_SPEED_EXPONENT


def _integrate(f, a: float, b: float, n: int = 64) -> float:
    """∫_a^b f(x) dx by n-point Gauss–Legendre quadrature (f: float64 tensor -> float64 tensor of the same shape)."""
    nodes, weights = np.polynomial.legendre.leggauss(n)
    half, mid = 0.5 * (b - a), 0.5 * (b + a)
    x = torch.from_numpy(mid + half * nodes)
    return float(half * (torch.from_numpy(weights) * f(x)).sum())


@dataclass(frozen=True)
class SnowParams:
    """What the camera sees of a snowfall: flake numbers, sizes, speeds and the frustum they fill."""

    rate_mm_h: float
    """Snowfall rate used, mm/h water equivalent (clamped to ``MAX_RATE_MM_H``)."""
    active: bool
    """Render snow at all (R > 0)."""
    lambda_per_mm: float
    """Gunn–Marshall slope Λ, 1/mm (decreasing in R; capped at 1e6 for R = 0)."""
    intercept_per_m3_per_mm: float
    """Gunn–Marshall intercept N0, m⁻³ mm⁻¹ (decreasing in R; 0 for R = 0)."""
    melted_min_mm: float
    """Smallest melted diameter drawn, mm."""
    melted_max_mm: float
    """Largest melted diameter drawn, mm."""
    number_density_per_m3: float
    """Flakes per m³ in the melted size range (not monotone in R: see ``gm_number_density_per_m3``)."""
    melted_mean_mm: float
    """Number-mean melted diameter of the truncated distribution, mm."""
    flake_mean_mm: float
    """Number-mean flake diameter (Locatelli–Hobbs mass law), mm."""
    area_density_per_m: float
    """Projected flake area per volume ∫N·πD²/4 dD_m, m²/m³ (what sets the image coverage; non-decreasing)."""
    fall_speed_m_s: float
    """Fall speed of the mean flake, m/s (Locatelli–Hobbs; ≈ 1 m/s)."""
    wind_m_s: float
    """Horizontal wind at flake height, m/s (θ's log-law value); flakes drift with it."""
    wind_dir_to_deg: float | None
    """Direction the flakes drift towards, degrees true; None when unknown or calm."""
    tilt_deg: float
    """Angle of the mean flake's path from vertical atan(U/v), degrees (steep: flakes fall slowly)."""
    exposure_s: float
    """Exposure time, s (sets the motion blur L = |w|·T)."""
    near_m: float
    """Nearest flake depth, m."""
    far_m: float
    """Farthest flake depth, m (the camera's far limit, at most the visibility)."""
    frustum_volume_m3: float
    """Volume of the camera frustum between near and far, m³."""
    expected_count: float
    """Physical number of flakes n·V in one frustum."""


def map_snow(
    rate_mm_h: float,
    wind_m_s: float,
    wind_dir_to_deg: float | None,
    exposure_s: float,
    fov_x_deg: float,
    fov_y_deg: float,
    near_m: float,
    far_m: float,
    melted_min_mm: float = 0.5,
    melted_max_mm: float = 3.0,
    mass_coeff_mg: float = LH_MASS_COEFF_MG,
    mass_exponent: float = LH_MASS_EXPONENT,
) -> SnowParams:
    """Snow parameters for a rate (mm/h water equivalent; above ``MAX_RATE_MM_H`` it is clamped with a warning), the
    wind at flake height (m/s) and the direction it blows to (degrees true), the exposure (s) and a camera frustum
    (fields of view in degrees, near and far depths in m)."""
    if not (math.isfinite(rate_mm_h) and rate_mm_h >= 0):
        raise ValueError(f"snowfall rate must be a finite, non-negative number of mm/h, got {rate_mm_h}")
    if rate_mm_h > MAX_RATE_MM_H:
        warnings.warn(
            f"snowfall rate {rate_mm_h:g} mm/h water equivalent is beyond the heaviest snowfalls; "
            f"the snow model uses {MAX_RATE_MM_H:g} mm/h",
            stacklevel=2,
        )
    rate = min(rate_mm_h, MAX_RATE_MM_H)
    lam = gm_lambda_per_mm(rate)
    n0 = gm_intercept_per_m3_per_mm(rate)
    density = gm_number_density_per_m3(rate, melted_min_mm, melted_max_mm)

    def flake(dm: torch.Tensor) -> torch.Tensor:
        return flake_diameter_mm(dm, mass_coeff_mg, mass_exponent)

    if density > 0:
        pdf = lambda dm: n0 * torch.exp(-lam * dm)  # noqa: E731
        melted_mean = _integrate(lambda dm: dm * pdf(dm), melted_min_mm, melted_max_mm) / density
        flake_mean = _integrate(lambda dm: flake(dm) * pdf(dm), melted_min_mm, melted_max_mm) / density
        area = _integrate(lambda dm: math.pi / 4 * (flake(dm) * 1e-3) ** 2 * pdf(dm), melted_min_mm, melted_max_mm)
    else:
        melted_mean, area = melted_min_mm, 0.0
        flake_mean = float(flake(torch.tensor(melted_min_mm, dtype=torch.float64)))
    v = fall_speed_m_s(flake_mean)
    u = max(wind_m_s, 0.0)
    tx = math.tan(math.radians(fov_x_deg) / 2.0)
    ty = math.tan(math.radians(fov_y_deg) / 2.0)
    far = max(far_m, near_m)
    volume = 4.0 / 3.0 * tx * ty * (far**3 - near_m**3)
    return SnowParams(
        rate_mm_h=rate,
        active=rate > 0 and density > 0,
        lambda_per_mm=min(lam, 1e6),
        intercept_per_m3_per_mm=n0,
        melted_min_mm=melted_min_mm,
        melted_max_mm=melted_max_mm,
        number_density_per_m3=density,
        melted_mean_mm=melted_mean,
        flake_mean_mm=flake_mean,
        area_density_per_m=area,
        fall_speed_m_s=v,
        wind_m_s=u,
        wind_dir_to_deg=wind_dir_to_deg if u > 0 else None,
        tilt_deg=math.degrees(math.atan2(u, v)),
        exposure_s=exposure_s,
        near_m=near_m,
        far_m=far,
        frustum_volume_m3=volume,
        expected_count=density * volume,
    )
