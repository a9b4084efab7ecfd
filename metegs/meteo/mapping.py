"""The weather mapping θ(P, visibility, wind, camera) → θ_rain, θ_fog, θ_drops (research note §8).

Physical mapping (default): Marshall–Palmer drop numbers and sizes, Atlas fall speeds, exposure-set
streak opacity with coverage-preserving subsampling to ``n_max``, rain extinction (Weber 2015), fog
extinction from visibility by the 5 % contrast rule without counting the rain twice, lens drops from
the kinematic arrival rate. The paper's form ``N = clamp(base + k·P^γ, 0, N_max)`` is available as
``PaperMapping``; ``PaperMapping.fit`` derives base, k and γ from the physics (γ ≈ 0.5).

Every mapped quantity is monotone in P and in 1/V (non-decreasing unless its docstring says
"decreasing"), bounded and finite for every non-negative input.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from datetime import datetime, timezone
from typing import Any, Literal

from metegs.errors import ConfigError
from metegs.meteo import physics
from metegs.meteo.aggregate import FOG_LIMIT_M, MIST_LIMIT_M, WeatherConditions, intensity_class, wmo_score

RGB_WAVELENGTHS_NM = (610.0, 550.0, 465.0)
"""Representative wavelengths of the R, G, B channels for the spectral fog exponent (§3.4)."""


@dataclass(frozen=True)
class CameraSpec:
    """The camera settings the rain appearance depends on (the dataset's intrinsics and exposure)."""

    exposure_s: float = 1.0 / 60.0
    """Exposure time T, s (the photos' EXIF ``ExposureTime``, as given): sets streak length and opacity (Garg & Nayar, §2.4)."""
    focal_px: float = 1000.0
    """Focal length in pixels f_px (sets the depth at which a drop becomes sub-pixel, §2.4)."""
    fov_x_deg: float = 60.0
    """Horizontal field of view, degrees."""
    fov_y_deg: float = 40.0
    """Vertical field of view, degrees."""
    near_m: float = 0.5
    """Nearest depth of rain streaks, m (closer drops are out of focus and not modelled, §8.1.3)."""
    far_max_m: float = 10.0
    """Largest depth of rain streaks, m (a cap from the scene size; farther rain acts through β_rain)."""
    far_m: float | None = None
    """A fixed far depth of streaks, m; None: the depth where a streak falls below the visible contrast (§8.1.3)."""
    speed_m_per_s: float = 0.0
    """Camera speed along its viewing direction, m/s (vehicle; adds to lens-drop arrivals)."""
    facing_wind_cos: float | None = None
    """Cosine between the viewing direction and the direction the wind comes from; None: averaged over azimuth (1/π)."""

    @classmethod
    def from_intrinsics(
        cls, fx: float, width: int, height: int, fy: float | None = None, exposure_s: float = 1.0 / 60.0, **kwargs: Any
    ) -> CameraSpec:
        """From pinhole intrinsics (pixels) and the image size."""
        fy = fx if fy is None else fy
        return cls(
            exposure_s=exposure_s,
            focal_px=fx,
            fov_x_deg=math.degrees(2 * math.atan(width / (2 * fx))),
            fov_y_deg=math.degrees(2 * math.atan(height / (2 * fy))),
            **kwargs,
        )


@dataclass(frozen=True)
class PaperMapping:
    """The paper's drop count N = clamp(base + k·x^γ, 0, N_max) with x = P (mm/h) or the normalised s_t."""

    base: float = 0.0
    """Drops at x = 0 (physically 0)."""
    k: float = 70_000.0
    """Drops at x = 1: n(1 mm/h)·V_f = 251 m⁻³ × 280 m³ for a 60°×40° frustum from 0.5 to 10 m (§8.1.4)."""
    gamma: float = 0.5
    """Exponent γ: 0.50 from Marshall–Palmer for D ≥ 0.5 mm (0.21 all sizes, 0.79 for D ≥ 1 mm; §2.1)."""
    n_max: int = 100_000
    """Upper clamp N_max."""
    use_normalised: bool = False
    """True: x is the paper's normalised s_t in [0, 1] (then k is the count at Pmax), else the rate in mm/h."""

    def count(self, x: float) -> float:
        """The clamped count for x ≥ 0."""
        return min(float(self.n_max), max(0.0, self.base + self.k * max(x, 0.0) ** self.gamma))

    @classmethod
    def fit(
        cls,
        camera: CameraSpec | None = None,
        config: MappingConfig | None = None,
        p_range: tuple[float, float] = (1.0, 50.0),
    ) -> PaperMapping:
        """base = 0, and k, γ fitted (least squares in log-log) to the physical expected count over ``p_range`` mm/h."""
        camera = camera or CameraSpec()
        config = config or MappingConfig()
        if camera.far_m is None:
            camera = dataclasses.replace(camera, far_m=camera.far_max_m)
        volume = physics.frustum_volume_m3(camera.fov_x_deg, camera.fov_y_deg, camera.near_m, camera.far_m)
        ps = [p_range[0] * (p_range[1] / p_range[0]) ** (i / 31) for i in range(32)]
        xs = [math.log(p) for p in ps]
        ys = [math.log(physics.mp_number_density_per_m3(p, config.d_min_mm, config.d_max_mm) * volume) for p in ps]
        mx, my = sum(xs) / len(xs), sum(ys) / len(ys)
        gamma = sum((x - mx) * (y - my) for x, y in zip(xs, ys)) / sum((x - mx) ** 2 for x in xs)
        return cls(base=0.0, k=math.exp(my - gamma * mx), gamma=gamma, n_max=config.n_max)


@dataclass(frozen=True)
class MappingConfig:
    """Constants of the mapping, each with its source (defaults follow the research note §8)."""

    mapping: Literal["physical", "paper"] = "physical"
    """``physical`` (Marshall–Palmer count in the frustum) or ``paper`` (``paper`` decides the count)."""
    paper: PaperMapping = field(default_factory=PaperMapping)
    """Parameters of the paper's count formula, used when ``mapping="paper"``."""
    d_min_mm: float = 0.5
    """Smallest rain drop rendered, mm (AMS: rain drops are > 0.5 mm)."""
    d_max_mm: float = 6.0
    """Largest rain drop, mm (larger drops break up, §2.1)."""
    drizzle_d_min_mm: float = 0.2
    """Smallest drizzle drop, mm (AMS/§1.3)."""
    drizzle_d_max_mm: float = 0.5
    """Largest drizzle drop, mm (AMS: drizzle drops < 0.5 mm)."""
    n_max: int = 100_000
    """Most rain Gaussians per camera; beyond it drops are subsampled and their opacity raised (coverage kept)."""
    opacity_cap: float = 0.99
    """Largest opacity of a Gaussian."""
    relative_contrast: float = 3.0
    """|E_drop − E_background|/E_background of a streak: drops refract the bright sky (Garg & Nayar 2004) [assumption]."""
    min_visible_step: float = 2.0 / 255.0
    """Smallest visible intensity change (two 8-bit levels); with the contrast it sets the streak far limit (§8.1.3)."""
    rain_extinction: Literal["weber", "marshall-palmer"] = "weber"
    """β_rain model: Weber et al. 2015 (0.312·P^0.67 km⁻¹) or geometric optics over Marshall–Palmer (0.365·P^0.63)."""
    contrast_threshold: float = 0.05
    """ε of V = ln(1/ε)/β: 0.05 (WMO MOR, 2.996/V), 0.02 for Koschmieder (3.912/V) (§3.1)."""
    clear_visibility_m: float = 25_000.0
    """Visibility of clear air for the background extinction β_bg when none is measured (20-30 km, §3.6)."""
    fog_visibility_m: float = 500.0
    """Visibility assumed for reported fog (FG) without a number, m (§8.2)."""
    mist_visibility_m: float = 3000.0
    """Visibility assumed for mist (BR) or haze (HZ) without a number, m (§8.2)."""
    drop_height_m: float = 2.0
    """Height of the rain seen by the camera, for the log-law wind reduction, m (§4)."""
    roughness_m: float = 0.03
    """Aerodynamic roughness length z0, m: 0.03 open terrain, 0.5-1 urban (§4)."""
    altitude_m: float = 0.0
    """Site altitude, m: faster fall in thinner air (Beard 1985; +8 % at 2 km)."""
    env_weight: float = 0.94
    """Drop colour = env_weight·(mean sky/environment radiance) + ambient_weight·(ambient), linear RGB (Halder et al. 2019)."""
    ambient_weight: float = 0.06
    """See ``env_weight``."""
    fog_phase_g: float = 0.9
    """Henyey–Greenstein asymmetry of fog droplets (forward scattering) [R]."""
    fog_lattice_spacing_m: float = 1.0
    """Largest spacing h of world-space fog Gaussians, m; denser fog gets a finer lattice (§8.2.5b)."""
    fog_max_lattice_opacity: float = 0.002
    """Cap on the opacity of one fog Gaussian, which sets the lattice spacing in dense fog: a ray's optical depth errs by
    up to ≈ 3·o at its ends, so 0.002 keeps random rays within 1 % of e^{−βd}. Rays parallel to a lattice axis see
    whole lattice planes (error up to β·h): rotate or jitter the lattice. Such faint Gaussians need a rasterizer
    without the 1/255 alpha cutoff."""
    fog_sigma_ratio: float = 1.0
    """σ/h of fog Gaussians; ≥ 0.7 keeps the lattice smooth (§8.2.5b)."""
    lens_window_area_m2: float = 9e-4
    """Area of the lens or protective window that collects drops, m² (3 cm × 3 cm, §5)."""
    lens_drop_lifetime_s: float = 10.0
    """How long a lens drop stays before it slides or is wiped off, s [assumption]."""
    lens_max_drops: int = 40
    """Most drops on the lens at once."""
    lens_radius_mm: tuple[float, float] = (1.5, 6.0)
    """Range of drop footprint radii on the glass, mm (§5)."""
    lens_contact_angle_deg: tuple[float, float] = (20.0, 90.0)
    """Range of contact angles, degrees (hydrophobic coatings are larger, §8.3)."""


@dataclass(frozen=True)
class ThetaRain:
    """Rain streaks as world-space Gaussians, one set per camera (§8.1)."""

    active: bool
    """Render rain at all (gated by present weather)."""
    kind: str
    """``rain``, ``drizzle`` or ``none``."""
    precip_mm_per_h: float
    """Rate P the parameters follow, mm/h."""
    intensity_class: str
    """WMO class of P (``none``, ``light``, ``moderate``, ``heavy``, ``violent``)."""
    wmo_score: float
    """WMO-anchored score of P in [0, 1]."""
    lambda_per_mm: float
    """Marshall–Palmer slope Λ = 4.1·P^−0.21, 1/mm (decreasing in P; capped at 1e6 for P = 0)."""
    diameter_min_mm: float
    """Smallest drop rendered, mm."""
    diameter_max_mm: float
    """Largest drop rendered, mm."""
    diameter_mean_mm: float
    """Number-mean diameter of the truncated Marshall–Palmer distribution, mm."""
    diameter_median_volume_mm: float
    """Median volume diameter D0 = 3.67/Λ, mm (Marshall & Palmer)."""
    number_density_per_m3: float
    """Drops per m³ with D in range: (N0/Λ)(e^−Λ·Dmin − e^−Λ·Dmax), N0 = 8000 m⁻³ mm⁻¹ (≈ 269·P^0.5)."""
    fall_speed_m_per_s: float
    """Terminal speed of the mean drop, m/s (Atlas et al. 1973, altitude-corrected)."""
    wind_at_drop_height_m_per_s: float
    """Horizontal wind at ``drop_height_m`` by the log law, m/s."""
    wind_dir_to_deg: float | None
    """Direction the drops drift towards (wind from + 180°), degrees true; None when unknown or calm."""
    velocity_enu_m_per_s: tuple[float, float, float] | None
    """Drop velocity (east, north, up), m/s; None when the wind direction is unknown (tilt still known)."""
    tilt_deg: float
    """Streak angle from vertical atan(U_h/v_t), degrees (decreasing in P: bigger drops fall faster)."""
    exposure_s: float
    """Exposure time T, s."""
    streak_length_m: float
    """World length of a streak L = |w|·T, m."""
    sigma_parallel_m: float
    """Gaussian std along the streak √(L²/12 + D²/16), m."""
    sigma_perp_m: float
    """Gaussian std across the streak D/4, m."""
    opacity: float
    """Coverage-preserving opacity of one streak D²/(8σ∥σ⊥) ≈ 1.73·D/L: set by the exposure, nearly independent of P."""
    mean_coverage: float
    """Time-averaged coverage of a streak pixel (π/4)·D/(|w|·T) (Garg & Nayar's τ/T)."""
    near_m: float
    """Nearest streak depth, m."""
    far_m: float
    """Farthest streak depth, m: where a sub-pixel streak's contrast falls below the visible step, ≤ visibility (§8.1.3)."""
    frustum_volume_m3: float
    """Volume of the camera frustum between near and far, m³."""
    expected_count: float
    """Physical expected number of drops n·V_f in one frustum."""
    n_max: int
    """Upper limit of Gaussians per camera."""
    count: int
    """Gaussians to create per camera (min(n_max, expected) or the paper's formula)."""
    subsample_ratio: float
    """count / expected_count (1 when nothing is dropped; decreasing in P once capped)."""
    opacity_effective: float
    """Opacity per Gaussian after subsampling, opacity / subsample_ratio (capped): keeps the mean coverage."""
    coverage_preserved: bool
    """False when the cap stopped ``opacity_effective`` from fully compensating the subsampling."""
    beta_rain_per_m: float
    """Extinction of the rain veil beyond the streaks, 1/m (Weber et al. 2015 or Marshall–Palmer optics)."""
    colour_env_weight: float
    """Weight of the mean environment (sky) radiance in the drop colour (Halder et al. 2019)."""
    colour_ambient_weight: float
    """Weight of the ambient radiance in the drop colour."""
    mapping: str
    """``physical`` or ``paper``: where ``count`` came from."""


@dataclass(frozen=True)
class ThetaFog:
    """Fog, mist or haze as extinction β and airlight, for analytic fog or world-space fog Gaussians (§8.2)."""

    active: bool
    """Render a fog/mist/haze effect (gated by present weather, or by visibility below 5 km beyond the rain's share)."""
    kind: str | None
    """``fog``, ``mist``, ``haze`` or None."""
    visibility_m: float | None
    """Visibility the extinction comes from, m (None: from rain and clear air only)."""
    visibility_source: str
    """``measured``, ``present_weather`` (FG/BR/HZ without a number), ``at_least`` (no fog) or ``none``."""
    contrast_threshold: float
    """ε of V = ln(1/ε)/β (0.05: WMO MOR)."""
    beta_total_per_m: float
    """Total extinction ln(1/ε)/V if measured, else β_rain + β_bg, 1/m."""
    beta_rain_per_m: float
    """Part of the total due to rain, 1/m (a measured visibility already contains it)."""
    beta_background_per_m: float
    """Clear-air extinction ln(1/ε)/V_clear, 1/m."""
    beta_fog_per_m: float
    """Extinction beyond the rain's: max(0, β_total − β_rain) with a visibility, else β_bg, 1/m (decreasing in P).

    It is kept when fog is gated off (rain without fog): the measured visibility is honoured through
    ``beta_veil_per_m``; ``active`` only says whether a separate fog effect is called for."""
    beta_veil_per_m: float
    """Extinction to apply along every ray: β_fog + β_rain, 1/m."""
    beta_rgb_per_m: tuple[float, float, float]
    """β_fog per R, G, B: β_fog·(λ/550 nm)^−q (Kim et al. 2001; grey in fog), 1/m."""
    kim_q: float
    """Spectral exponent q of Kim et al. (2001) for the visibility."""
    airlight_rgb: tuple[float, float, float] | None
    """Airlight A in linear RGB; None: estimate it from the training images (sky median or dark channel, §3.6)."""
    phase_g: float
    """Henyey–Greenstein asymmetry for a forward lobe around the sun."""
    lattice_spacing_m: float
    """Spacing h of world-space fog Gaussians, m."""
    lattice_sigma_m: float
    """Std σ of each fog Gaussian, m."""
    lattice_opacity: float
    """Opacity o of each fog Gaussian so rays see e^{−β_fog·d} (exact rule, ``physics.fog_lattice_opacity``; ≤ 0.002 by default)."""


@dataclass(frozen=True)
class ThetaDrops:
    """Drops on the lens or its protective window (image-space effect attached to the camera, §8.3)."""

    active: bool
    """Render lens drops (rain with wind into the lens or camera motion)."""
    arrival_rate_per_s: float
    """Drops hitting the window per second n·U_normal·A."""
    count: int
    """Drops on the lens at a time: min(max, rate × lifetime)."""
    lifetime_s: float
    """Seconds a drop stays."""
    radius_mm: tuple[float, float]
    """Range of footprint radii on the glass, mm."""
    contact_angle_deg: tuple[float, float]
    """Range of contact angles, degrees."""
    refractive_index: float
    """Refractive index of water (1.33)."""
    window_area_m2: float
    """Collecting area, m²."""


@dataclass(frozen=True)
class Theta:
    """θ = {θ_rain, θ_fog, θ_drops} for one capture time and camera, with what it came from."""

    rain: ThetaRain
    """θ_rain: rain streak Gaussians per camera."""
    fog: ThetaFog
    """θ_fog: extinction and airlight."""
    drops: ThetaDrops
    """θ_drops: drops on the lens."""
    conditions: WeatherConditions
    """The aggregated conditions θ was mapped from."""
    camera: CameraSpec
    """The camera settings used."""

    def to_dict(self) -> dict[str, Any]:
        """Plain data (JSON/YAML safe)."""
        return _plain(self)


def _plain(obj: Any) -> Any:
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: _plain(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, datetime):
        return obj.isoformat()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def _ratio_speed(d_mm: float, u_h: float, density_ratio: float) -> float:
    v = physics.fall_speed_m_per_s(d_mm, density_ratio)
    return d_mm / math.hypot(u_h, v)


def _representative_drop_mm(mean_d: float, d_min: float, d_max: float, u_h: float, density_ratio: float) -> float:
    """The drop that sets streak opacity: max(mean D, D*), with D* the minimum of D/|w(D)| over [d_min, d_max].

    Opacity ∝ D/|w|. For rain, D/v_t(D) has a shallow minimum near 0.7 mm (2 % deep in Gunn–Kinzer's
    data and in the Atlas fit) and grows beyond it, so max(mean, D*) keeps the opacity non-decreasing in P
    at a cost below 2 %. For drizzle in still air D/v_t falls over all of [0.2, 0.5] mm, so the rule
    holds its opacity at the 0.5 mm value (up to 15 % fainter than its mean drop would give).
    """
    lo, hi = d_min, d_max
    golden = (math.sqrt(5.0) - 1.0) / 2.0
    for _ in range(60):  # golden-section search of the unimodal D/|w(D)|
        a = hi - golden * (hi - lo)
        b = lo + golden * (hi - lo)
        if _ratio_speed(a, u_h, density_ratio) <= _ratio_speed(b, u_h, density_ratio):
            hi = b
        else:
            lo = a
    return max(mean_d, 0.5 * (lo + hi))


def map_rain(conditions: WeatherConditions, camera: CameraSpec, config: MappingConfig) -> ThetaRain:
    """θ_rain from the conditions (P, wind, visibility) and the camera (§8.1)."""
    p = conditions.precip_mm_per_h or 0.0
    active = conditions.rain_active and p > 0
    kind = conditions.precip_kind if conditions.precip_kind in ("rain", "drizzle") else "rain"
    p_eff = p if active else 0.0
    d_min, d_max = (
        (config.drizzle_d_min_mm, config.drizzle_d_max_mm) if kind == "drizzle" else (config.d_min_mm, config.d_max_mm)
    )
    lam = physics.mp_lambda_per_mm(p_eff)
    density = physics.mp_number_density_per_m3(p_eff, d_min, d_max)
    mean_d = physics.mp_mean_diameter_mm(p_eff, d_min, d_max)
    density_ratio = physics.air_density_ratio(config.altitude_m)
    v_t = physics.fall_speed_m_per_s(mean_d, density_ratio)
    u_h = physics.wind_at_height_m_per_s(conditions.wind_speed_m_per_s, config.drop_height_m, config.roughness_m)
    dir_to = (
        None if conditions.wind_dir_deg_from is None or u_h <= 0 else (conditions.wind_dir_deg_from + 180.0) % 360.0
    )
    velocity = None
    if dir_to is not None:
        a = math.radians(dir_to)
        velocity = (u_h * math.sin(a), u_h * math.cos(a), -v_t)
    elif u_h <= 0:
        velocity = (0.0, 0.0, -v_t)
    speed = math.hypot(u_h, v_t)
    d_rep = _representative_drop_mm(mean_d, d_min, d_max, u_h, density_ratio)
    speed_rep = math.hypot(u_h, physics.fall_speed_m_per_s(d_rep, density_ratio))
    T = camera.exposure_s
    s_par, s_perp = physics.streak_sigmas_m(mean_d, speed, T)
    opacity = physics.streak_opacity(d_rep, speed_rep, T, config.opacity_cap)
    coverage = physics.mean_streak_coverage(d_rep, speed_rep, T)
    if camera.far_m is not None:
        far = max(camera.near_m, camera.far_m)
    else:
        alpha_min = config.min_visible_step / config.relative_contrast
        far = camera.focal_px * mean_d * 1e-3 * coverage / alpha_min
        far = min(max(far, camera.near_m), camera.far_max_m)
    if conditions.visibility_m is not None and not conditions.visibility_at_least:
        far = max(camera.near_m, min(far, conditions.visibility_m))
    volume = physics.frustum_volume_m3(camera.fov_x_deg, camera.fov_y_deg, camera.near_m, far)
    expected = density * volume
    if config.mapping == "paper":
        x = conditions.normalised if config.paper.use_normalised else p_eff
        count_f = config.paper.count(x or 0.0) if active else 0.0
        n_max = config.paper.n_max
    elif config.mapping == "physical":
        count_f = min(float(config.n_max), expected)
        n_max = config.n_max
    else:
        raise ConfigError(f"unknown mapping {config.mapping!r}; use physical or paper")
    count = int(math.floor(count_f + 0.5))
    ratio = count_f / expected if expected > 0 and count_f > 0 else 1.0
    raw_effective = opacity / ratio
    effective = min(config.opacity_cap, raw_effective)
    return ThetaRain(
        active=active,
        kind=kind if active else "none",
        precip_mm_per_h=p_eff,
        intensity_class=intensity_class(p_eff, kind),
        wmo_score=wmo_score(p_eff),
        lambda_per_mm=min(lam, 1e6),
        diameter_min_mm=d_min,
        diameter_max_mm=d_max,
        diameter_mean_mm=mean_d,
        diameter_median_volume_mm=physics.mp_median_volume_diameter_mm(p_eff),
        number_density_per_m3=density,
        fall_speed_m_per_s=v_t,
        wind_at_drop_height_m_per_s=u_h,
        wind_dir_to_deg=dir_to,
        velocity_enu_m_per_s=velocity,
        tilt_deg=math.degrees(math.atan2(u_h, v_t)),
        exposure_s=T,
        streak_length_m=speed * T,
        sigma_parallel_m=s_par,
        sigma_perp_m=s_perp,
        opacity=opacity,
        mean_coverage=coverage,
        near_m=camera.near_m,
        far_m=far,
        frustum_volume_m3=volume,
        expected_count=expected,
        n_max=n_max,
        count=count,
        subsample_ratio=ratio,
        opacity_effective=effective,
        coverage_preserved=raw_effective <= config.opacity_cap + 1e-12,
        beta_rain_per_m=physics.beta_rain_per_m(p_eff, config.rain_extinction),
        colour_env_weight=config.env_weight,
        colour_ambient_weight=config.ambient_weight,
        mapping=config.mapping,
    )


def map_fog(conditions: WeatherConditions, beta_rain: float, config: MappingConfig) -> ThetaFog:
    """θ_fog: β from visibility (5 % rule) minus the rain's share, airlight hints, gating flag (§8.2)."""
    eps = config.contrast_threshold
    beta_bg = physics.beta_from_visibility_per_m(config.clear_visibility_m, eps)
    vis = conditions.visibility_m
    if vis is not None and not conditions.visibility_at_least:
        source = "measured"
        vis = max(vis, 1e-3)
    elif conditions.fog_active and conditions.fog_kind is not None:
        source = "present_weather"
        vis = config.fog_visibility_m if conditions.fog_kind == "fog" else config.mist_visibility_m
    elif vis is not None:
        source = "at_least"
        vis = None
    else:
        source = "none"
    if vis is not None:  # a measured visibility already contains the rain and the background
        beta_total = physics.beta_from_visibility_per_m(vis, eps)
        beta_fog = max(0.0, beta_total - beta_rain)
    else:
        beta_fog = beta_bg
        beta_total = beta_rain + beta_bg
    q = physics.kim_exponent(vis if vis is not None else config.clear_visibility_m)
    rgb = tuple(beta_fog * (lam / 550.0) ** -q for lam in RGB_WAVELENGTHS_NM)
    sigma_ratio = config.fog_sigma_ratio
    spacing = physics.fog_lattice_spacing_m(
        beta_fog, config.fog_max_lattice_opacity, sigma_ratio, config.fog_lattice_spacing_m
    )
    lattice_opacity = physics.fog_lattice_opacity(beta_fog, spacing, sigma_ratio * spacing)
    kind = conditions.fog_kind if conditions.fog_active else None
    if conditions.fog_active and kind is None and vis is not None:
        kind = "fog" if vis < FOG_LIMIT_M else "mist" if vis <= MIST_LIMIT_M else "haze"
    return ThetaFog(
        active=conditions.fog_active,
        kind=kind,
        visibility_m=vis,
        visibility_source=source,
        contrast_threshold=eps,
        beta_total_per_m=beta_total,
        beta_rain_per_m=beta_rain,
        beta_background_per_m=beta_bg,
        beta_fog_per_m=beta_fog,
        beta_veil_per_m=beta_fog + beta_rain,
        beta_rgb_per_m=rgb,  # type: ignore[arg-type]
        kim_q=q,
        airlight_rgb=None,
        phase_g=config.fog_phase_g,
        lattice_spacing_m=spacing,
        lattice_sigma_m=sigma_ratio * spacing,
        lattice_opacity=lattice_opacity,
    )


def map_drops(rain: ThetaRain, camera: CameraSpec, config: MappingConfig) -> ThetaDrops:
    """θ_drops: lens drops arrive at n·(U_h·cos(facing) + camera speed)·A per second (§5, §8.3)."""
    facing = (1.0 / math.pi) if camera.facing_wind_cos is None else max(0.0, camera.facing_wind_cos)
    normal_speed = rain.wind_at_drop_height_m_per_s * facing + max(0.0, camera.speed_m_per_s)
    rate = (
        physics.lens_drop_arrival_rate_per_s(rain.number_density_per_m3, normal_speed, config.lens_window_area_m2)
        if rain.active
        else 0.0
    )
    count = int(min(config.lens_max_drops, math.floor(rate * config.lens_drop_lifetime_s + 0.5)))
    return ThetaDrops(
        active=rain.active and count > 0,
        arrival_rate_per_s=rate,
        count=count,
        lifetime_s=config.lens_drop_lifetime_s,
        radius_mm=config.lens_radius_mm,
        contact_angle_deg=config.lens_contact_angle_deg,
        refractive_index=1.33,
        window_area_m2=config.lens_window_area_m2,
    )


def map_conditions(
    conditions: WeatherConditions, camera: CameraSpec | None = None, config: MappingConfig | None = None
) -> Theta:
    """θ for aggregated conditions and one camera."""
    camera = camera or CameraSpec()
    config = config or MappingConfig()
    _check_camera(camera)
    rain = map_rain(conditions, camera, config)
    fog = map_fog(conditions, rain.beta_rain_per_m, config)
    drops = map_drops(rain, camera, config)
    return Theta(rain=rain, fog=fog, drops=drops, conditions=conditions, camera=camera)


def theta_from_values(
    precip_mm_per_h: float = 0.0,
    visibility_m: float | None = None,
    wind_speed_m_per_s: float = 0.0,
    wind_dir_deg_from: float | None = None,
    *,
    kind: Literal["rain", "drizzle"] = "rain",
    fog_kind: str | None = None,
    camera: CameraSpec | None = None,
    config: MappingConfig | None = None,
) -> Theta:
    """θ straight from numbers (no record): rain if P > 0; fog if ``fog_kind`` is given or the visibility,
    after removing the rain's extinction, is below 5 km."""
    for name, value in (("precip_mm_per_h", precip_mm_per_h), ("wind_speed_m_per_s", wind_speed_m_per_s)):
        if not math.isfinite(value) or value < 0:
            raise ConfigError(f"{name} must be a finite, non-negative number, got {value}")
    if visibility_m is not None and (not math.isfinite(visibility_m) or visibility_m <= 0):
        raise ConfigError(f"visibility_m must be a positive number, got {visibility_m}")
    if wind_dir_deg_from is not None and not math.isfinite(wind_dir_deg_from):
        raise ConfigError(f"wind_dir_deg_from must be a finite number of degrees, got {wind_dir_deg_from}")
    config = config or MappingConfig()
    fog_active = fog_kind is not None
    if not fog_active and visibility_m is not None and visibility_m < MIST_LIMIT_M:
        excess = physics.beta_from_visibility_per_m(visibility_m, config.contrast_threshold) - physics.beta_rain_per_m(
            precip_mm_per_h, config.rain_extinction
        )
        fog_active = excess > physics.beta_from_visibility_per_m(MIST_LIMIT_M, config.contrast_threshold)
        if fog_active:
            fog_kind = "fog" if visibility_m < FOG_LIMIT_M else "mist"
    conditions = WeatherConditions(
        time_utc=datetime(1970, 1, 1, tzinfo=timezone.utc),
        window_s=0.0,
        agg="max",
        precip_mm_per_h=precip_mm_per_h,
        precip_source="given",
        precip_coverage=1.0,
        precip_kind=kind,
        intensity_class=intensity_class(precip_mm_per_h, kind),
        wmo_score=wmo_score(precip_mm_per_h),
        visibility_m=visibility_m,
        wind_speed_m_per_s=wind_speed_m_per_s,
        wind_dir_deg_from=wind_dir_deg_from,
        rain_active=precip_mm_per_h > 0,
        fog_active=fog_active,
        fog_kind=fog_kind,
    )
    return map_conditions(conditions, camera, config)


def _check_camera(camera: CameraSpec) -> None:
    checks = (
        ("exposure_s", camera.exposure_s > 0),
        ("focal_px", camera.focal_px > 0),
        ("fov_x_deg", 0 < camera.fov_x_deg < 180),
        ("fov_y_deg", 0 < camera.fov_y_deg < 180),
        ("near_m", camera.near_m > 0),
        ("far_max_m", camera.far_max_m >= camera.near_m),
    )
    for name, ok in checks:
        if not ok:
            raise ConfigError(f"camera {name}={getattr(camera, name)!r} is out of range")
