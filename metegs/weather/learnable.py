"""Learnable per-view transient weather (rain, snow): the photo teaches position, opacity and colour of
each view's weather Gaussians within bounds, while their shape (fall direction, aspect ratio) stays physical.

A meteorological prior keeps each view's rain coverage Σ oᵢ·aᵢ / (W·H) (aᵢ the streak's screen
footprint 2π·sqrt(det Σ₂)) near the θ-predicted coverage, so the weather cannot swallow scene content.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn

from metegs.gaussians.model import GaussianSet
from metegs.gaussians.sh import rgb_to_sh, sh_to_rgb
from metegs.render.base import RenderOutput, RenderSettings
from metegs.render.projection import project_gaussians
from metegs.weather.base import WeatherModel


@dataclass
class LearnableWeatherConfig:
    """Bounds and learning rates of learnable per-view weather Gaussians."""

    position_bound: float = 1.0
    """Largest offset of a streak's centre, in units of its own length σ∥ (per axis)."""
    opacity_bound: float = 2.0
    """Opacity stays within [0, this × θ's opacity]."""
    position_lr: float = 0.02
    """Learning rate of the (tanh-bounded) position offsets."""
    opacity_lr: float = 0.05
    """Learning rate of the (sigmoid-bounded) opacity factors."""
    colour_lr: float = 0.02
    """Learning rate of the colour logits."""
    coverage_weight: float = 0.1
    """Weight of the prior ((coverage / θ coverage) − 1)²."""


def screen_footprints(gaussians: GaussianSet, camera) -> torch.Tensor:
    """Screen area 2π·sqrt(det Σ₂) of each Gaussian in pixels (0 when not drawn). camera: one view -> [N]."""
    W, H = int(camera.width[0]), int(camera.height[0])
    with torch.no_grad():
        p = project_gaussians(
            gaussians.means.float().cpu(),
            gaussians.quats.float().cpu(),
            gaussians.scales.float().cpu(),
            camera.world_to_cameras()[0].float().cpu(),
            camera.intrinsics()[0].float().cpu(),
            W,
            H,
            eps2d=0.0,
        )
        a, b, c = p.conics.double().unbind(-1)
        det_conic = a * c - b * b
        ok = (p.radii > 0) & (det_conic > 0)
        area = 2 * math.pi / torch.sqrt(torch.where(ok, det_conic, torch.ones_like(det_conic)))
        return torch.where(ok, area, torch.zeros_like(area)).float()


class _ViewResiduals(nn.Module):
    """One view's base Gaussians (buffers) and their bounded residuals (parameters)."""

    def __init__(self, base: GaussianSet, footprint: torch.Tensor):
        super().__init__()
        n = len(base)
        self.register_buffer("means", base.means.detach().clone())
        self.register_buffer("quats", base.quats.detach().clone())
        self.register_buffer("scales", base.scales.detach().clone())
        self.register_buffer("opacities", base.opacities.detach().clone())
        self.register_buffer("footprint", footprint.to(base.means))
        rgb = sh_to_rgb(base.sh[:, 0].detach()).clamp(1e-3, 1 - 1e-3)
        self.offset = nn.Parameter(torch.zeros(n, 3, device=base.means.device))
        self.opacity_logit = nn.Parameter(torch.zeros(n, device=base.means.device))
        self.colour_logit = nn.Parameter(torch.logit(rgb))


class LearnableTransients(WeatherModel):
    """Wraps a per-view weather model: training views get learnable residuals, other views its physical Gaussians."""

    stage = "gaussians"

    def __init__(self, inner: WeatherModel, views: list[int], config: LearnableWeatherConfig | None = None):
        super().__init__(inner.theta, inner.scene)
        self.inner = inner
        self.name = f"learnable-{inner.name}"
        self.config = config or LearnableWeatherConfig()
        self.views = nn.ModuleDict()
        for v in views:
            base = inner.gaussians_for(v)
            if base is not None and len(base) > 0:
                self.views[str(v)] = _ViewResiduals(base, screen_footprints(base, inner.scene.cameras[v]))

    @property
    def active(self) -> bool:
        return self.inner.active

    def _set(self, r: _ViewResiduals) -> GaussianSet:
        bound = self.config.position_bound * r.scales.amax(dim=1, keepdim=True)
        means = r.means + bound * torch.tanh(r.offset)
        opacities = (self.config.opacity_bound * torch.sigmoid(r.opacity_logit) * r.opacities).clamp(max=0.99)
        sh = rgb_to_sh(torch.sigmoid(r.colour_logit))[:, None, :]
        return GaussianSet(means, r.quats, r.scales, opacities, sh)

    def gaussians_for(self, view: int) -> GaussianSet | None:
        r = self.views[str(view)] if str(view) in self.views else None
        return self.inner.gaussians_for(view) if r is None else self._set(r)

    def apply(self, rgb: torch.Tensor, out: RenderOutput, view: int, settings: RenderSettings) -> torch.Tensor:
        return self.inner.apply(rgb, out, view, settings)

    def coverage_ratio(self, view: int) -> torch.Tensor | None:
        """Rendered coverage over θ's for a training view (scalar, 1 at the start), or None."""
        r = self.views[str(view)] if str(view) in self.views else None
        if r is None:
            return None
        o = (self.config.opacity_bound * torch.sigmoid(r.opacity_logit) * r.opacities).clamp(max=0.99)
        return (o * r.footprint).sum() / (r.opacities * r.footprint).sum().clamp_min(1e-12)

    def prior(self, view: int) -> torch.Tensor | None:
        """Weighted coverage prior of a training view (scalar), or None."""
        ratio = self.coverage_ratio(view)
        return None if ratio is None else self.config.coverage_weight * (ratio - 1.0) ** 2

    def param_groups(self) -> list[dict]:
        """Adam parameter groups (one per kind of residual)."""
        c = self.config
        views = list(self.views.values())
        return [
            {"params": [r.offset for r in views], "lr": c.position_lr, "name": "weather_position"},
            {"params": [r.opacity_logit for r in views], "lr": c.opacity_lr, "name": "weather_opacity"},
            {"params": [r.colour_logit for r in views], "lr": c.colour_lr, "name": "weather_colour"},
        ]
