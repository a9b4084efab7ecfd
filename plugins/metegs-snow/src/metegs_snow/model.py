"""`snow`: per-view falling snowflakes as flat, bright, motion-blurred Gaussians.

Each photo is its own instant: view v gets its own flakes, drawn from a generator seeded with
(seed, v), uniform in the volume of that camera's frustum between θ's near distance and the camera's
far limit (depth density ∝ z²). Their melted sizes follow the Gunn–Marshall distribution of the snowfall
rate (mm/h water equivalent: θ's precipitation rate), their own sizes and fall speeds the
Locatelli–Hobbs laws (see `metegs_snow.physics`). A flake is an oblate Gaussian (std D/4 across, a·D/4
thick along the vertical: flakes fall broad side down) swept over the exposure along its velocity, the
fall speed plus the horizontal wind at flake height (flakes drift with the air): Σ = Σ_flake + (L²/12)·ŵŵᵀ
with L = |w|·T.

Coverage is preserved on screen: a flake's alpha integrated over the image equals the projected area of
its disk, 2 × the area 2π·sqrt(det Σ₂) of its unblurred Gaussian (exact for a thin disk), whatever the
blur and the rasteriser's ε dilation of sub-pixel footprints, divided by the subsampling ratio when
``max_count`` caps the number of flakes (the kept ones become more opaque, the coverage stays). Flakes whose
opacity would fall below ``min_opacity`` are kept with probability o/min_opacity at opacity min_opacity
(unbiased coverage); 1/255 is added back for the tail the rasteriser cuts (as `rain-streaks` does). A flake
that would need an opacity above 0.99 (close, large flakes, more so under a strong cap) is widened
instead, as if the flakes it stands for were merged into one, so its coverage stays exact (under a strong
cap at high resolution the nearest flakes become wide, soft discs: raise ``max_count`` for renders).

Colour: white, ``albedo`` × the brightness of the view's sky (the brightest channel of the mean of its
brightest tenth of pixels): a white Lambertian flake lit by sun and sky is grey-white whatever the sky's tint.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch
from metegs.gaussians.model import GaussianSet
from metegs.gaussians.sh import rgb_to_sh
from metegs.meteo.mapping import Theta
from metegs.render.base import ALPHA_MIN, RenderSettings
from metegs.weather.base import WeatherModel, WeatherModelConfig, WeatherScene
from metegs.weather.rain_streaks import horizontal_frame

from metegs_snow.physics import (
    LH_MASS_COEFF_MG,
    LH_MASS_EXPONENT,
    SnowParams,
    fall_speed_m_s,
    flake_diameter_mm,
    gm_sample_melted_diameter_mm,
    map_snow,
)

SEED_SALT = 0x534E4F57
"""Mixed into the per-view seed so that snow never draws the same numbers as rain of the same seed."""


@dataclass
class SnowConfig(WeatherModelConfig):
    """Per-view snowflakes from the precipitation rate of θ (read as snowfall, mm/h water equivalent)."""

    _target: type = field(default_factory=lambda: Snow, repr=False)
    max_count: int | None = 2000
    """Cap on flakes per view (None: all of the physical count); the opacity of the kept ones rises to keep coverage."""
    min_opacity: float = 0.02
    """Floor of a flake's opacity; fainter flakes are kept at random with probability o / min_opacity."""
    colour: tuple[float, float, float] | None = None
    """Flake colour in [0, 1]; None: white, ``albedo`` × the brightness of each view's sky."""
    albedo: float = 0.9
    """Reflectance of snow in the visible (fresh snow 0.8–0.95)."""
    margin: float = 0.1
    """Flakes are also drawn this fraction of the image size beyond each edge (their blur reaches in)."""
    melted_min_mm: float = 0.5
    """Smallest melted diameter drawn, mm (a 0.9 mm flake)."""
    melted_max_mm: float = 3.0
    """Largest melted diameter drawn, mm (a 43 mm aggregate)."""
    mass_coeff_mg: float = LH_MASS_COEFF_MG
    """a of the flake mass m = a·D^b mg (D in mm): Locatelli & Hobbs (1974), unrimed dendrite aggregates."""
    mass_exponent: float = LH_MASS_EXPONENT
    """b of the flake mass m = a·D^b mg."""
    aspect_ratio: float = 0.6
    """Thickness / diameter of a flake (oblate; irregular aggregates tumble, so not a thin disk) [assumption]."""
    rate_mm_h: float | None = None
    """Snowfall rate, mm/h water equivalent; None: θ's precipitation rate (the record's or --conditions.precip-mm-h)."""
    only_reported_snow: bool = False
    """Render snow only when the record reports snow (present weather SN, SG…); else any precipitation is snow."""
    far_m: float | None = None
    """Farthest flake depth, m; None: θ's camera far limit (the scene's depth, at most 10 m), at most the visibility."""
    north: tuple[float, float, float] | None = None
    """World direction of geographic north, for the wind direction; None: the mean horizontal viewing direction."""


def quat_wxyz_from_rotmat(R: torch.Tensor) -> torch.Tensor:
    """Rotation matrices [N, 3, 3] -> unit quaternions (w, x, y, z) [N, 4] (largest-component branch per matrix)."""
    m = R.double()
    m00, m01, m02 = m[:, 0, 0], m[:, 0, 1], m[:, 0, 2]
    m10, m11, m12 = m[:, 1, 0], m[:, 1, 1], m[:, 1, 2]
    m20, m21, m22 = m[:, 2, 0], m[:, 2, 1], m[:, 2, 2]
    trace = m00 + m11 + m22
    branches = []
    s = 2.0 * torch.sqrt((1.0 + trace).clamp_min(1e-12))
    branches.append(torch.stack([0.25 * s, (m21 - m12) / s, (m02 - m20) / s, (m10 - m01) / s], 1))
    s = 2.0 * torch.sqrt((1.0 + m00 - m11 - m22).clamp_min(1e-12))
    branches.append(torch.stack([(m21 - m12) / s, 0.25 * s, (m01 + m10) / s, (m02 + m20) / s], 1))
    s = 2.0 * torch.sqrt((1.0 + m11 - m00 - m22).clamp_min(1e-12))
    branches.append(torch.stack([(m02 - m20) / s, (m01 + m10) / s, 0.25 * s, (m12 + m21) / s], 1))
    s = 2.0 * torch.sqrt((1.0 + m22 - m00 - m11).clamp_min(1e-12))
    branches.append(torch.stack([(m10 - m01) / s, (m02 + m20) / s, (m12 + m21) / s, 0.25 * s], 1))
    which = torch.stack([trace, m00, m11, m22], 1).argmax(1)
    q = torch.stack(branches, 1)[torch.arange(len(m)), which]
    return (q / q.norm(dim=1, keepdim=True)).to(R.dtype)


def flake_covariances(
    diameters: torch.Tensor, velocities: torch.Tensor, up: torch.Tensor, aspect_ratio: float, exposure_s: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """(Σ_flake, Σ_blurred) [N, 3, 3] of oblate flakes (diameters [N], velocities [N, 3], same length unit per
    second) thin along ``up`` [3], swept over ``exposure_s``: Σ_flake + (L²/12)·ŵŵᵀ with L = |w|·T."""
    s2 = (diameters / 4.0) ** 2
    eye = torch.eye(3, dtype=diameters.dtype)
    flat = eye - (1.0 - aspect_ratio**2) * torch.outer(up, up)
    sigma_flake = s2[:, None, None] * flat
    length = velocities.norm(dim=1) * exposure_s
    w = velocities / velocities.norm(dim=1, keepdim=True).clamp_min(1e-12)
    blur = (length**2 / 12.0)[:, None, None] * (w[:, :, None] * w[:, None, :])
    return sigma_flake, sigma_flake + blur


def scales_and_quats(sigma: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Symmetric positive covariances [N, 3, 3] -> (standard deviations [N, 3], quaternions wxyz [N, 4])."""
    evals, evecs = torch.linalg.eigh(sigma)
    flip = torch.linalg.det(evecs) < 0
    evecs = torch.where(flip[:, None, None], evecs * torch.tensor([1.0, 1.0, -1.0], dtype=evecs.dtype), evecs)
    return torch.sqrt(evals.clamp_min(0.0)), quat_wxyz_from_rotmat(evecs)


def screen_covariances(sigma_cam: torch.Tensor, means_cam: torch.Tensor, fx: float, fy: float) -> torch.Tensor:
    """EWA screen covariances J Σ Jᵀ [N, 2, 2] of camera-space covariances [N, 3, 3] at camera-space means [N, 3]."""
    x, y, z = means_cam.unbind(1)
    zero = torch.zeros_like(z)
    J = torch.stack([fx / z, zero, -fx * x / z**2, zero, fy / z, -fy * y / z**2], 1).reshape(-1, 2, 3)
    return J @ sigma_cam @ J.transpose(1, 2)


class Snow(WeatherModel):
    """Snowflake Gaussians, different in every view."""

    stage = "gaussians"
    name = "snow"
    kind = "snow"
    transient = True

    def __init__(self, config: SnowConfig, theta: Theta, scene: WeatherScene):
        super().__init__(theta, scene)
        self.config = config
        cond, cam = theta.conditions, theta.camera
        rate = config.rate_mm_h if config.rate_mm_h is not None else (cond.precip_mm_per_h or 0.0)
        if config.only_reported_snow and cond.precip_kind != "snow":
            rate = 0.0
        far = config.far_m if config.far_m is not None else (cam.far_m if cam.far_m is not None else cam.far_max_m)
        if cond.visibility_m is not None and not cond.visibility_at_least:
            far = min(far, cond.visibility_m)
        self.params: SnowParams = map_snow(
            rate,
            theta.rain.wind_at_drop_height_m_per_s,
            theta.rain.wind_dir_to_deg,
            cam.exposure_s,
            cam.fov_x_deg,
            cam.fov_y_deg,
            cam.near_m,
            far,
            config.melted_min_mm,
            config.melted_max_mm,
            config.mass_coeff_mg,
            config.mass_exponent,
        )
        """The snowfall as the camera sees it (`metegs_snow.physics.SnowParams`)."""
        p = self.params
        up = scene.up.detach().double().cpu()
        up = up / up.norm()
        east, north = horizontal_frame(up, scene.north_hint(config.north))
        if p.wind_dir_to_deg is not None:
            a = math.radians(p.wind_dir_to_deg)
            wind = p.wind_m_s * (math.sin(a) * east + math.cos(a) * north)
        else:  # direction unknown (or calm): the drift still applies, towards "north"
            wind = p.wind_m_s * north
        self.up = up
        self.wind_m_s = wind
        """[3] horizontal wind at flake height, m/s (world axes)."""
        velocity = wind - p.fall_speed_m_s * up
        self.fall_direction = (velocity / velocity.norm().clamp_min(1e-12)).float()
        """[3] unit direction the mean flake moves in (world)."""
        expected = p.expected_count if p.active else 0.0
        count = expected if config.max_count is None else min(expected, float(config.max_count))
        self.count = int(math.floor(count + 0.5))
        """Flakes drawn per view."""
        self.subsample = self.count / expected if expected > 0 and self.count > 0 else 1.0
        """count / physical count (≤ 1); the opacities are divided by it."""
        self._colours: dict[int, torch.Tensor] = {}

    @property
    def active(self) -> bool:
        return self.params.active and self.count > 0

    def colour_for(self, view: int) -> torch.Tensor:
        """[3] flake colour of view ``view`` (computed once per view)."""
        if view not in self._colours:
            self._colours[view] = self._colour_of(view)
        return self._colours[view]

    def _colour_of(self, view: int) -> torch.Tensor:
        if self.config.colour is not None:
            return torch.tensor(self.config.colour, dtype=torch.float32)
        if not self.scene.images:
            return torch.full((3,), float(self.config.albedo))
        im = self.scene.images[view].detach().float().cpu().reshape(-1, 3)
        k = max(1, im.shape[0] // 10)
        sky = im[torch.topk(im.mean(dim=1), k).indices].mean(0)
        return torch.full((3,), float(self.config.albedo * sky.max())).clamp(0.0, 1.0)

    def gaussians_for(self, view: int) -> GaussianSet | None:
        if not self.active:
            return None
        g = self.draw(view)
        keep = g["keep"]
        opacity = torch.maximum(g["opacity"], torch.full_like(g["opacity"], self.config.min_opacity))[keep] + ALPHA_MIN
        opacity = opacity.clamp(max=0.99)
        sh = rgb_to_sh(self.colour_for(view)).expand(int(keep.sum()), 1, 3)
        device = self.scene.cameras.camera_to_worlds.device
        return GaussianSet(
            g["means"][keep].to(device),
            g["quats"][keep].to(device),
            g["scales"][keep].to(device),
            opacity.float().to(device),
            sh.to(device),
        )

    def draw(self, view: int) -> dict[str, torch.Tensor]:
        """All flakes drawn for view ``view`` before the opacity floor: means, quats, scales (world, float32),
        coverage-preserving ``opacity`` (float64, at most 0.99 − 1/255), ``keep`` (the random opacity-floor
        choice), ``area_px`` (each flake's projected disk area, px) and ``footprint_px`` (2π·sqrt(det(Σ₂ + εI)),
        px, of the Gaussian as drawn: opacity × footprint = area / subsample)."""
        p, scene, c = self.params, self.scene, self.config
        cam = scene.cameras[view]
        gen = torch.Generator().manual_seed((int(scene.seed) * 1_000_003 + int(view)) ^ SEED_SALT)
        m = c.margin
        n = int(round(self.count * (1 + 2 * m) ** 2))
        f64 = torch.float64
        near, far = float(scene.to_units(p.near_m)), float(scene.to_units(p.far_m))
        u = torch.rand(n, generator=gen, dtype=f64)
        z = (near**3 + u * (far**3 - near**3)) ** (1.0 / 3.0)
        W, H = int(cam.width[0]), int(cam.height[0])
        fx, fy, cx, cy = (float(v[0]) for v in (cam.fx, cam.fy, cam.cx, cam.cy))
        px = (torch.rand(n, generator=gen, dtype=f64) * (1 + 2 * m) - m) * W
        py = (torch.rand(n, generator=gen, dtype=f64) * (1 + 2 * m) - m) * H
        local = torch.stack([(px - cx) / fx * z, (py - cy) / fy * z, z], dim=1)
        c2w = cam.camera_to_worlds[0].double().cpu()
        rot = c2w[:3, :3]
        means = local @ rot.T + c2w[:3, 3]

        melted = gm_sample_melted_diameter_mm(
            torch.rand(n, generator=gen, dtype=f64), p.rate_mm_h, c.melted_min_mm, c.melted_max_mm
        )
        flake_mm = flake_diameter_mm(melted, c.mass_coeff_mg, c.mass_exponent)
        velocity = self.wind_m_s[None, :] - fall_speed_m_s(flake_mm)[:, None] * self.up[None, :]  # m/s
        diam_units = torch.as_tensor(scene.to_units(flake_mm * 1e-3), dtype=f64)
        vel_units = torch.as_tensor(scene.to_units(velocity), dtype=f64)
        sigma_flake, sigma = flake_covariances(diam_units, vel_units, self.up, c.aspect_ratio, p.exposure_s)
        scales, quats = scales_and_quats(sigma)

        eps = RenderSettings().eps2d
        to_cam = lambda s: rot.T @ s @ rot  # noqa: E731 - world -> camera axes
        cov_flake = screen_covariances(to_cam(sigma_flake), local, fx, fy)
        cov = screen_covariances(to_cam(sigma), local, fx, fy)
        area_px = 2.0 * 2.0 * math.pi * torch.sqrt(torch.linalg.det(cov_flake).clamp_min(0.0))
        det = torch.linalg.det(cov).clamp_min(0.0)
        trace = cov[:, 0, 0] + cov[:, 1, 1]
        footprint_px = 2.0 * math.pi * torch.sqrt(det + eps * trace + eps * eps)  # 2π·sqrt(det(Σ₂ + εI))
        alpha_px = area_px / self.subsample
        """Integrated alpha each drawn flake must carry (its own area, and that of the flakes it stands for)."""
        opacity = alpha_px / footprint_px
        # a flake that would need more than the largest opacity is widened instead, by the t = s² that solves
        # det(tΣ₂ + εI) = (alpha / (2π·o_max))², as if the flakes it stands for were merged into one
        o_max = 0.99 - ALPHA_MIN
        wide = opacity > o_max
        if bool(wide.any()):
            target = (alpha_px[wide] / (2.0 * math.pi * o_max)) ** 2
            dw, tw = det[wide].clamp_min(1e-30), trace[wide]
            t = (-eps * tw + torch.sqrt((eps * tw) ** 2 - 4.0 * dw * (eps * eps - target))) / (2.0 * dw)
            t = t.clamp_min(1.0)
            scales[wide] = scales[wide] * torch.sqrt(t)[:, None]
            footprint_px[wide] = 2.0 * math.pi * torch.sqrt(t * t * dw + t * eps * tw + eps * eps)
            opacity[wide] = alpha_px[wide] / footprint_px[wide]
        keep = torch.rand(n, generator=gen, dtype=f64) < (opacity / c.min_opacity).clamp(max=1.0)
        return {
            "means": means.float(),
            "quats": quats.float(),
            "scales": scales.float(),
            "opacity": opacity,
            "keep": keep,
            "area_px": area_px,
            "footprint_px": footprint_px,
        }

    def describe(self) -> str:
        """One line: rate, flake number density and size, fall speed and tilt, flakes per view."""
        p = self.params
        return (
            f"snow {p.rate_mm_h:.2f} mm/h w.e.: {p.number_density_per_m3:.0f} flakes/m³, mean flake "
            f"{p.flake_mean_mm:.1f} mm, falling {p.fall_speed_m_s:.2f} m/s, tilt {p.tilt_deg:.0f}°; "
            f"{self.count} flakes/view (×{1 / self.subsample:.1f} opacity)"
        )
