"""`lens-droplets`: water drops on the lens or its window, as image-space refractive patches (research §5, §8.3).

A drop on the glass is far out of focus and acts as a small ball lens: it shows a minified,
inverted and blurred picture of the scene around it, with a darker rim where light is refracted
away. Each drop is a disc of radius r (θ_drops' footprint radii on a window of θ's area, scaled to
the image) with a soft edge; inside, the image is resampled from the blurred frame at
c − m·(x − c) (m = magnification from the contact angle: flatter drops bend less). Count from
θ_drops; drops are seeded per view. Off unless θ_drops says drops reach the lens or the config
forces it (``force``).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import torch
import torch.nn.functional as F

from metegs.meteo.mapping import Theta
from metegs.render.base import RenderOutput, RenderSettings
from metegs.weather.base import SynthesisRequest, WeatherModel, WeatherModelConfig, WeatherScene


def box_blur(image: torch.Tensor, radius: int) -> torch.Tensor:
    """Separable box blur (applied twice, ≈ Gaussian). image [H, W, 3] -> [H, W, 3]."""
    if radius < 1:
        return image
    x = image.permute(2, 0, 1)[None]
    k = 2 * radius + 1
    for _ in range(2):
        x = F.avg_pool2d(F.pad(x, (radius, radius, 0, 0), mode="replicate"), (1, k), stride=1)
        x = F.avg_pool2d(F.pad(x, (0, 0, radius, radius), mode="replicate"), (k, 1), stride=1)
    return x[0].permute(1, 2, 0)


@dataclass
class LensDropletsConfig(WeatherModelConfig):
    """Drops on the lens (image space)."""

    _target: type = field(default_factory=lambda: LensDroplets, repr=False)
    force: bool = False
    """Render drops even when θ_drops does not call for them."""
    count: int | None = None
    """Number of drops per view; None: θ_drops' count."""
    window_width_m: float | None = None
    """Width of the glass the image spans, m; None: the square root of θ's collecting area."""
    edge_px: float = 1.5
    """Softness of a drop's edge, px."""

    def for_synthesis(self, request: SynthesisRequest) -> LensDropletsConfig | None:
        """Drops on the glass when they are asked for and it rains: θ_drops' count, else the forced default (drops
        belong to one camera, not to the scene's weather, and hide much of a view: never added unasked)."""
        if "drops" not in request.kinds or not request.theta.rain.active:
            return None
        return dataclasses.replace(self, force=True)


class LensDroplets(WeatherModel):
    """Refractive drops on the glass, per view."""

    stage = "lens"
    name = "lens-droplets"
    kind = "drops"

    def __init__(self, config: LensDropletsConfig, theta: Theta, scene: WeatherScene):
        super().__init__(theta, scene)
        self.config = config
        drops = theta.drops
        self.count = int(config.count if config.count is not None else drops.count)
        if config.force and self.count == 0:
            self.count = 8
        self._active = (drops.active or config.force) and self.count > 0

    @property
    def active(self) -> bool:
        return self._active

    def drops_for(self, view: int, width: int, height: int) -> torch.Tensor:
        """[K, 4] drops of a view: centre x, y (px), radius (px), magnification."""
        d = self.theta.drops
        gen = torch.Generator().manual_seed(int(self.scene.seed) * 7_919 + 17 + int(view))
        k = self.count
        window_mm = 1000.0 * (self.config.window_width_m or math.sqrt(d.window_area_m2))
        r_mm = d.radius_mm[0] + (d.radius_mm[1] - d.radius_mm[0]) * torch.rand(k, generator=gen) ** 2
        radius = r_mm / window_mm * width
        angle = d.contact_angle_deg[0] + (d.contact_angle_deg[1] - d.contact_angle_deg[0]) * torch.rand(
            k, generator=gen
        )
        # a spherical cap of contact angle φ has curvature radius r / sin φ: focal length ∝ that / (n − 1);
        # the minified, inverted picture shrinks more for rounder drops
        magnification = (0.15 + 0.5 * torch.sin(torch.deg2rad(angle))) * (d.refractive_index - 1.0) / 0.33
        cx = torch.rand(k, generator=gen) * width
        cy = torch.rand(k, generator=gen) * height
        return torch.stack([cx, cy, radius, magnification], dim=1)

    def apply(self, rgb: torch.Tensor, out: RenderOutput, view: int, settings: RenderSettings) -> torch.Tensor:
        H, W = rgb.shape[:2]
        drops = self.drops_for(view, W, H).to(rgb)
        blurred = box_blur(rgb, max(1, int(round(0.01 * max(H, W)))))
        ys, xs = torch.meshgrid(
            torch.arange(H, device=rgb.device, dtype=rgb.dtype) + 0.5,
            torch.arange(W, device=rgb.device, dtype=rgb.dtype) + 0.5,
            indexing="ij",
        )
        result = rgb
        for cx, cy, r, m in drops:
            dx, dy = xs - cx, ys - cy
            dist = torch.sqrt(dx * dx + dy * dy)
            alpha = torch.sigmoid((r - dist) / self.config.edge_px)[..., None]
            sx, sy = cx - m * dx, cy - m * dy  # inverted, minified view through the drop
            grid = torch.stack([sx / W * 2 - 1, sy / H * 2 - 1], dim=-1)[None]
            inside = F.grid_sample(blurred.permute(2, 0, 1)[None], grid, align_corners=False, padding_mode="border")
            rim = 1.0 - 0.35 * (dist / r).clamp(max=1.0) ** 4
            drop_rgb = inside[0].permute(1, 2, 0) * rim[..., None]
            result = result * (1.0 - alpha) + drop_rgb * alpha
        return result
