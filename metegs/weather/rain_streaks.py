"""`rain-streaks`: per-view transient rain streaks as elongated Gaussians (research note §8.1).

Each photo is its own instant: view v gets its own drops, drawn from a generator seeded with
(seed, v), uniform in the volume of that camera's frustum between θ's near distance and streak
visibility limit (depth density ∝ z²). A streak is a Gaussian elongated along the drop velocity
(fall speed from the drop size, tilt from the wind) with θ's along/across standard deviations.

Coverage is preserved on screen: a streak's alpha integrated over the image equals its drop's
projected cross-section π(fD/z)²/4 divided by θ's subsampling ratio, i.e. the opacity is
θ's world-space opacity times sqrt(det Σ₂ / det(Σ₂ + ε I)), undoing the rasteriser's ε = 0.3 px²
dilation of sub-pixel footprints. Streaks whose opacity would fall below ``min_opacity`` (the
rasteriser skips alphas below 1/255) are kept with probability o/min_opacity at opacity
min_opacity (unbiased coverage, no invisible work). The rasteriser skips alphas below 1/255, which
removes exactly 1/255 × the footprint's area from a streak's integrated alpha; 1/255 is added back. Colour: the environment-lit drop colour of θ
(env_weight × the view's bright-sky radiance + ambient_weight × its mean radiance).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from metegs.cameras import rotation_to_quat_wxyz
from metegs.gaussians.model import GaussianSet
from metegs.gaussians.sh import rgb_to_sh
from metegs.meteo.mapping import Theta
from metegs.render.base import ALPHA_MIN, RenderSettings
from metegs.render.projection import project_gaussians
from metegs.weather.base import WeatherModel, WeatherModelConfig, WeatherScene


def horizontal_frame(up: torch.Tensor, forward_hint: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(east, north) unit vectors perpendicular to ``up``; north follows ``forward_hint`` projected horizontally."""
    up = up / up.norm()
    north = forward_hint - (forward_hint @ up) * up
    if north.norm() < 1e-6:  # looking straight up or down: any horizontal direction
        north = torch.tensor([1.0, 0.0, 0.0], dtype=up.dtype) - up[0] * up
        if north.norm() < 1e-6:
            north = torch.tensor([0.0, 1.0, 0.0], dtype=up.dtype) - up[1] * up
    north = north / north.norm()
    east = torch.linalg.cross(north, up)
    return east, north


@dataclass
class RainStreaksConfig(WeatherModelConfig):
    """Per-view rain streaks from θ_rain."""

    _target: type = field(default_factory=lambda: RainStreaks, repr=False)
    north: tuple[float, float, float] | None = None
    """World direction of geographic north, for the wind direction; None: the mean horizontal viewing direction."""
    max_count: int | None = None
    """Cap on streaks per view below θ's N_max (faster); the opacity of the kept ones rises to keep coverage."""
    min_opacity: float = 0.02
    """Floor of a streak's opacity; fainter streaks are kept at random with probability o / min_opacity."""
    colour: tuple[float, float, float] | None = None
    """Streak colour in [0, 1]; None: environment-lit from each view's image (θ's weights)."""
    margin: float = 0.1
    """Drops are also drawn this fraction of the image size beyond each edge (their streaks reach in)."""


class RainStreaks(WeatherModel):
    """Rain streak Gaussians, different in every view."""

    stage = "gaussians"
    name = "rain-streaks"
    kind = "rain"
    transient = True

    def __init__(self, config: RainStreaksConfig, theta: Theta, scene: WeatherScene):
        super().__init__(theta, scene)
        self.config = config
        rain = theta.rain
        up = scene.up.detach().double().cpu()
        up = up / up.norm()
        east, north = horizontal_frame(up, scene.north_hint(config.north))
        if rain.velocity_enu_m_per_s is not None:
            e, n, u = rain.velocity_enu_m_per_s
            velocity = e * east + n * north + u * up
        else:  # wind direction unknown: the tilt still applies, towards "north"
            v = rain.fall_speed_m_per_s
            velocity = v * math.tan(math.radians(rain.tilt_deg)) * north - v * up
        self.fall_direction = (velocity / velocity.norm().clamp_min(1e-12)).float()
        """[3] unit direction the drops move in (world)."""
        a = self.fall_direction.double()
        helper = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
        if abs(float(a @ helper)) > 0.9:
            helper = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
        b = torch.linalg.cross(a, helper)
        b = b / b.norm()
        c = torch.linalg.cross(a, b)
        self.quat = rotation_to_quat_wxyz(torch.stack([a, b, c], dim=1)).float()
        count = rain.count if config.max_count is None else min(rain.count, config.max_count)
        self.count = int(count) if rain.active else 0
        """Streaks drawn per view."""
        self.subsample = (self.count / rain.expected_count) if rain.expected_count > 0 else 1.0
        self._colours: dict[int, torch.Tensor] = {}
        self.colour_env_weight = rain.colour_env_weight
        self.colour_ambient_weight = rain.colour_ambient_weight

    @property
    def active(self) -> bool:
        return self.theta.rain.active and self.count > 0

    def colour_for(self, view: int) -> torch.Tensor:
        """[3] environment-lit drop colour of view ``view`` (computed once per view)."""
        if view not in self._colours:
            self._colours[view] = self._colour_of(view)
        return self._colours[view]

    def _colour_of(self, view: int) -> torch.Tensor:
        if self.config.colour is not None:
            return torch.tensor(self.config.colour, dtype=torch.float32)
        if not self.scene.images:
            return torch.full((3,), 0.8)
        im = self.scene.images[view].detach().float().cpu().reshape(-1, 3)
        lum = im.mean(dim=1)
        k = max(1, im.shape[0] // 10)
        sky = im[torch.topk(lum, k).indices].mean(0)
        colour = self.colour_env_weight * sky + self.colour_ambient_weight * im.mean(0)
        return colour.clamp(0.0, 1.0)

    def gaussians_for(self, view: int) -> GaussianSet | None:
        if not self.active:
            return None
        rain, scene = self.theta.rain, self.scene
        cam = scene.cameras[view]
        gen = torch.Generator().manual_seed(int(scene.seed) * 1_000_003 + int(view))
        m = self.config.margin
        n = int(round(self.count * (1 + 2 * m) ** 2))
        near, far = float(scene.to_units(rain.near_m)), float(scene.to_units(rain.far_m))
        u = torch.rand(n, generator=gen, dtype=torch.float64)
        z = (near**3 + u * (far**3 - near**3)) ** (1.0 / 3.0)
        W, H = int(cam.width[0]), int(cam.height[0])
        fx, fy, cx, cy = (float(v[0]) for v in (cam.fx, cam.fy, cam.cx, cam.cy))
        px = (torch.rand(n, generator=gen, dtype=torch.float64) * (1 + 2 * m) - m) * W
        py = (torch.rand(n, generator=gen, dtype=torch.float64) * (1 + 2 * m) - m) * H
        local = torch.stack([(px - cx) / fx * z, (py - cy) / fy * z, z], dim=1)
        c2w = cam.camera_to_worlds[0].double().cpu()
        means = (local @ c2w[:3, :3].T + c2w[:3, 3]).float()
        scales = torch.tensor(
            [
                scene.to_units(rain.sigma_parallel_m),
                scene.to_units(rain.sigma_perp_m),
                scene.to_units(rain.sigma_perp_m),
            ],
            dtype=torch.float32,
        ).expand(n, 3)
        quats = self.quat.expand(n, 4)
        opacity = self._screen_opacity(means, quats, scales, cam, rain.opacity / self.subsample)
        keep = torch.rand(n, generator=gen) < (opacity / self.config.min_opacity).clamp(max=1.0)
        # + ALPHA_MIN: the rasteriser drops the tail where o·e^{-q/2} < ALPHA_MIN, whose mass is exactly
        # ALPHA_MIN × 2π·sqrt(det Σ₂); adding it back keeps the integrated alpha
        opacity = (torch.maximum(opacity, torch.full_like(opacity, self.config.min_opacity))[keep] + ALPHA_MIN).clamp(
            max=0.99
        )
        colour = self.colour_for(view)
        sh = rgb_to_sh(colour).expand(int(keep.sum()), 1, 3)
        device = scene.cameras.camera_to_worlds.device
        return GaussianSet(
            means[keep].to(device), quats[keep].to(device), scales[keep].to(device), opacity.to(device), sh.to(device)
        )

    @staticmethod
    def _screen_opacity(means, quats, scales, cam, world_opacity: float, eps2d: float | None = None) -> torch.Tensor:
        """World opacity times sqrt(det Σ₂ / det(Σ₂ + εI)) (undoes the rasteriser's dilation) -> [N]."""
        eps = RenderSettings().eps2d if eps2d is None else eps2d
        W, H = int(cam.width[0]), int(cam.height[0])
        with torch.no_grad():
            p = project_gaussians(
                means, quats, scales, cam.world_to_cameras()[0].cpu(), cam.intrinsics()[0].cpu(), W, H, eps2d=eps
            )
            A, B, C = p.conics.double().unbind(-1)
            det_conic = A * C - B * B
            ok = (p.radii > 0) & (det_conic > 0)
            det_conic = torch.where(ok, det_conic, torch.ones_like(det_conic))
            s00, s01, s11 = C / det_conic, -B / det_conic, A / det_conic  # Σ₂ + εI
            det_dilated = s00 * s11 - s01 * s01
            det_plain = ((s00 - eps) * (s11 - eps) - s01 * s01).clamp_min(0.0)
            ratio = torch.sqrt(det_plain / det_dilated.clamp_min(1e-30))
            return torch.where(ok, world_opacity * ratio, torch.zeros_like(ratio)).float()
