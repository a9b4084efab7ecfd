"""Rain and fog physics used by the mapping: pure functions of scalars, each with its unit and source.

R or P is the rain rate (mm/h), D a drop diameter (mm), V a visibility (m), β an extinction
coefficient (1/m). Sections refer to the research note ``../shared/research/meteorology.md``.
"""

from __future__ import annotations

import math

MP_N0_PER_M3_PER_MM = 8000.0
"""Marshall–Palmer intercept N0 = 0.08 cm⁻⁴ = 8000 m⁻³ mm⁻¹ (Marshall & Palmer 1948, J. Meteor. 5:165)."""

LN20 = math.log(20.0)
"""ln(1/0.05) = 2.996: the WMO meteorological optical range uses a 5 % contrast threshold (WMO-No. 8 Ch. 9)."""


def mp_lambda_per_mm(rate_mm_per_h: float) -> float:
    """Marshall–Palmer slope Λ = 4.1·R^−0.21 (1/mm); +inf for R = 0 (Marshall & Palmer 1948, §2.1)."""
    if rate_mm_per_h <= 0:
        return math.inf
    return 4.1 * rate_mm_per_h**-0.21


def mp_number_density_per_m3(rate_mm_per_h: float, d_min_mm: float = 0.5, d_max_mm: float = 6.0) -> float:
    """Drops per m³ with d_min ≤ D ≤ d_max: (N0/Λ)(e^−Λ·d_min − e^−Λ·d_max) (§2.1, §8.1.2; ≈ 269·R^0.50 for rain)."""
    lam = mp_lambda_per_mm(rate_mm_per_h)
    if math.isinf(lam):
        return 0.0
    return MP_N0_PER_M3_PER_MM / lam * (math.exp(-lam * d_min_mm) - math.exp(-lam * d_max_mm))


def mp_mean_diameter_mm(rate_mm_per_h: float, d_min_mm: float = 0.5, d_max_mm: float = 6.0) -> float:
    """Number-mean diameter (mm) of the Marshall–Palmer distribution truncated to [d_min, d_max]; d_min for R = 0 [D]."""
    lam = mp_lambda_per_mm(rate_mm_per_h)
    width = d_max_mm - d_min_mm
    if math.isinf(lam) or lam * width > 700:
        return d_min_mm + (0.0 if math.isinf(lam) else 1.0 / lam)
    tail = math.exp(-lam * width)
    return d_min_mm + 1.0 / lam - width * tail / (1.0 - tail)


def mp_median_volume_diameter_mm(rate_mm_per_h: float) -> float:
    """Median volume diameter D0 = 3.67/Λ (mm) of the untruncated distribution; 0 for R = 0 (§2.1)."""
    lam = mp_lambda_per_mm(rate_mm_per_h)
    return 0.0 if math.isinf(lam) else 3.67 / lam


def mp_sample_diameter_mm(u: float, rate_mm_per_h: float, d_min_mm: float = 0.5, d_max_mm: float = 6.0) -> float:
    """Inverse CDF of the truncated exponential: a diameter (mm) for a uniform u in [0, 1) (§2.1)."""
    lam = mp_lambda_per_mm(rate_mm_per_h)
    if math.isinf(lam):
        return d_min_mm
    return d_min_mm - math.log(1.0 - u * (1.0 - math.exp(-lam * (d_max_mm - d_min_mm)))) / lam


def fall_speed_m_per_s(diameter_mm: float, air_density_ratio: float = 1.0) -> float:
    """Terminal fall speed v_t = 9.65 − 10.3·e^−0.6·D (m/s) (Atlas, Srivastava & Sekhon 1973, Eq. 24).

    Fits Gunn & Kinzer (1949) within 2 % for 0.6-5.8 mm; clamped to ≥ 0.01 m/s (the fit is negative below
    0.11 mm). ``air_density_ratio`` = ρ0/ρ applies Beard's (1985) altitude factor (ρ0/ρ)^(0.375 + 0.025·D).
    """
    v = 9.65 - 10.3 * math.exp(-0.6 * diameter_mm)
    v = max(v, 0.01)
    if air_density_ratio != 1.0:
        v *= air_density_ratio ** (0.375 + 0.025 * diameter_mm)
    return v


def air_density_ratio(altitude_m: float) -> float:
    """ρ0/ρ of the ICAO standard atmosphere below 11 km (1.22 at 2 km); used for fall speeds at altitude."""
    t0, lapse, g, r = 288.15, 0.0065, 9.80665, 287.053
    ratio_t = max(1.0 - lapse * altitude_m / t0, 0.2)
    return ratio_t ** -(g / (r * lapse) - 1.0)


def beta_rain_per_m(rate_mm_per_h: float, model: str = "weber") -> float:
    """Extinction by rain, 1/m: ``weber`` 0.312·R^0.67 km⁻¹ (Weber et al. 2015, used by Tremblay et al. 2021),
    ``marshall-palmer`` 0.365·R^0.63 km⁻¹ (geometric optics over Marshall–Palmer, §2.7)."""
    if rate_mm_per_h <= 0:
        return 0.0
    if model == "weber":
        return 0.312e-3 * rate_mm_per_h**0.67
    if model == "marshall-palmer":
        return 0.365e-3 * rate_mm_per_h**0.63
    raise ValueError(f"unknown rain extinction model {model!r}; use 'weber' or 'marshall-palmer'")


def beta_from_visibility_per_m(visibility_m: float, contrast_threshold: float = 0.05) -> float:
    """β = ln(1/ε)/V (1/m): ε = 0.05 gives the WMO MOR 2.996/V, ε = 0.02 Koschmieder's 3.912/V (§3.1)."""
    if visibility_m <= 0:
        raise ValueError(f"visibility must be positive, got {visibility_m}")
    return math.log(1.0 / contrast_threshold) / visibility_m


def visibility_from_beta_m(beta_per_m: float, contrast_threshold: float = 0.05) -> float:
    """V = ln(1/ε)/β (m); +inf for β = 0 (§3.1)."""
    return math.inf if beta_per_m <= 0 else math.log(1.0 / contrast_threshold) / beta_per_m


def kim_exponent(visibility_m: float) -> float:
    """Ångström-type exponent q of β(λ) ∝ λ^−q from visibility (Kim, McArthur & Korevaar 2001, §3.4): 0 (grey) below 500 m."""
    v_km = visibility_m / 1000.0
    if v_km > 50:
        return 1.6
    if v_km > 6:
        return 1.3
    if v_km > 1:
        return 0.16 * v_km + 0.34
    if v_km > 0.5:
        return v_km - 0.5
    return 0.0


def wind_at_height_m_per_s(u10_m_per_s: float, height_m: float = 2.0, roughness_m: float = 0.03) -> float:
    """Log-law wind U(z) = U10·ln(z/z0)/ln(10/z0) (m/s); 0.72·U10 at 2 m over open terrain (§4)."""
    if u10_m_per_s <= 0:
        return 0.0
    z = max(height_m, roughness_m * 1.0001)
    return u10_m_per_s * math.log(z / roughness_m) / math.log(10.0 / roughness_m)


def streak_sigmas_m(diameter_mm: float, speed_m_per_s: float, exposure_s: float) -> tuple[float, float]:
    """(σ_∥, σ_⊥) in m of a Gaussian standing for a disk of diameter D swept over L = v·T: √(L²/12 + D²/16), D/4 (§8.1.6)."""
    d = diameter_mm * 1e-3
    length = speed_m_per_s * exposure_s
    return math.sqrt(length**2 / 12.0 + d**2 / 16.0), d / 4.0


def streak_opacity(diameter_mm: float, speed_m_per_s: float, exposure_s: float, cap: float = 0.99) -> float:
    """Coverage-preserving opacity o = min(cap, D²/(8·σ_∥·σ_⊥)) ≈ 1.73·D/L: the Gaussian integrates to the swept disk (§8.1.7)."""
    s_par, s_perp = streak_sigmas_m(diameter_mm, speed_m_per_s, exposure_s)
    d = diameter_mm * 1e-3
    return min(cap, d * d / (8.0 * s_par * s_perp))


def mean_streak_coverage(diameter_mm: float, speed_m_per_s: float, exposure_s: float) -> float:
    """Time-averaged pixel coverage of a streak ᾱ = (πD²/4)/(D·L + πD²/4) ≈ (π/4)·D/(v·T) (Garg & Nayar's τ/T, §2.4)."""
    d = diameter_mm * 1e-3
    disk = math.pi * d * d / 4.0
    return disk / (d * speed_m_per_s * exposure_s + disk)


def frustum_volume_m3(fov_x_deg: float, fov_y_deg: float, near_m: float, far_m: float) -> float:
    """Volume of a pyramidal frustum between depths near and far: (4/3)·tan(φx/2)·tan(φy/2)·(far³ − near³) (§8.1.3)."""
    if far_m <= near_m:
        return 0.0
    tx = math.tan(math.radians(fov_x_deg) / 2.0)
    ty = math.tan(math.radians(fov_y_deg) / 2.0)
    return 4.0 / 3.0 * tx * ty * (far_m**3 - near_m**3)


def dilogarithm(x: float) -> float:
    """Li₂(x) = Σ x^k/k² for 0 ≤ x ≤ 1 (Li₂(1) = π²/6), via Li₂(x) = π²/6 − ln x·ln(1−x) − Li₂(1−x) above 1/2."""
    if x < 0 or x > 1:
        raise ValueError(f"dilogarithm here is for 0 <= x <= 1, got {x}")
    if x > 0.5:
        if x == 1.0:
            return math.pi**2 / 6.0
        return math.pi**2 / 6.0 - math.log(x) * math.log(1.0 - x) - dilogarithm(1.0 - x)
    total, term, k = 0.0, x, 1
    while term > 1e-17 * max(total, 1e-300) and k < 200:
        total += term / (k * k)
        k += 1
        term *= x
    return total


def fog_lattice_opacity(beta_per_m: float, spacing_m: float, sigma_m: float) -> float:
    """Opacity o of isotropic Gaussians (std σ) on a cubic lattice of spacing h so that rays see e^{−β·d} (§8.2.5b).

    A 3DGS ray crossing a Gaussian at distance r from its centre loses a fraction o·e^{−r²/2σ²}. Per unit
    length the lattice holds 1/h³ Gaussians per m³, so the mean optical depth per metre is
    (2πσ²/h³)·Li₂(o) (the integral of −ln(1 − o·e^{−r²/2σ²}) over the cross-section); the research note's
    small-o form o = β·h³/(2πσ²) is its first term. Solved exactly here, so the rule holds for dense
    fog too. Needs σ ≳ 0.7·h for a smooth lattice, and β·h³/(2πσ²) < π²/6 (else ValueError: refine
    the lattice). Rasterizers that skip contributions below 1/255 need o well above that.
    """
    if beta_per_m < 0 or spacing_m <= 0 or sigma_m <= 0:
        raise ValueError("fog lattice needs beta >= 0, spacing > 0 and sigma > 0")
    target = beta_per_m * spacing_m**3 / (2.0 * math.pi * sigma_m**2)
    if target == 0:
        return 0.0
    if target >= math.pi**2 / 6.0:
        raise ValueError(
            f"beta={beta_per_m:g}/m cannot be reached with spacing {spacing_m:g} m and sigma {sigma_m:g} m; use a finer lattice"
        )
    lo, hi = 0.0, 1.0
    for _ in range(80):  # bisection: Li2 is increasing on [0, 1]
        mid = 0.5 * (lo + hi)
        if dilogarithm(mid) < target:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def fog_lattice_spacing_m(
    beta_per_m: float, max_opacity: float, sigma_ratio: float = 1.0, max_spacing_m: float = 1.0
) -> float:
    """Lattice spacing h (m) at most ``max_spacing_m`` whose Gaussians (σ = sigma_ratio·h) need opacity ≤ ``max_opacity``.

    The optical depth per metre is (2π·σ²/h³)·Li₂(o) = 2π·ratio²·Li₂(o)/h, so h = 2π·ratio²·Li₂(o_max)/β.
    """
    if not 0 < max_opacity < 1:
        raise ValueError(f"max_opacity must be in (0, 1), got {max_opacity}")
    if beta_per_m <= 0:
        return max_spacing_m
    return min(max_spacing_m, 2.0 * math.pi * sigma_ratio**2 * dilogarithm(max_opacity) / beta_per_m)


def lens_drop_arrival_rate_per_s(
    number_density_per_m3: float, normal_speed_m_per_s: float, window_area_m2: float
) -> float:
    """Drops hitting a window per second: n·max(0, w·n̂)·A (kinematic, §5 and §8.3)."""
    return number_density_per_m3 * max(0.0, normal_speed_m_per_s) * window_area_m2
