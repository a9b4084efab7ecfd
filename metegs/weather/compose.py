"""Render a view with weather: one sorted rasterisation of scene + weather Gaussians, then image-space effects."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch

from metegs.cameras import Cameras
from metegs.gaussians.model import GaussianSet
from metegs.meteo.mapping import Theta
from metegs.registry import registry
from metegs.render.base import RenderOutput, RenderSettings
from metegs.weather.base import WeatherModel, WeatherModelConfig, WeatherScene

_STAGE_ORDER = {"gaussians": 0, "medium": 1, "lens": 2}


@dataclass
class WeatherRender:
    """A view rendered with weather."""

    rgb: torch.Tensor
    """[H, W, 3] final image (image-space effects applied)."""
    out: RenderOutput
    """The rasterisation of scene + weather Gaussians (its radii/means2d cover both; scene ones first)."""
    num_scene: int
    """How many of the rasterised Gaussians are scene Gaussians (the first ``num_scene``)."""
    num_weather: int
    """How many weather Gaussians were rasterised with them."""

    @property
    def scene_mask(self) -> torch.Tensor:
        """[N] bool, True for scene Gaussians (what densification, pruning and export may see)."""
        mask = torch.zeros(self.num_scene + self.num_weather, dtype=torch.bool, device=self.rgb.device)
        mask[: self.num_scene] = True
        return mask


def build_weather_models(
    configs: Sequence[str | WeatherModelConfig], theta: Theta, scene: WeatherScene
) -> list[WeatherModel]:
    """Weather models from registry names or configs, in stage order (inactive ones are kept but cost nothing)."""
    models = []
    for c in configs:
        config = registry("weather").get(c)() if isinstance(c, str) else c
        if config.enabled:
            models.append(config.setup(theta=theta, scene=scene))
    return sorted(models, key=lambda m: _STAGE_ORDER[m.stage])


def render_with_weather(
    rasterizer,
    scene_gaussians: GaussianSet,
    models: Sequence[WeatherModel],
    view: int,
    camera: Cameras,
    settings: RenderSettings | None = None,
) -> WeatherRender:
    """Render view ``view`` (camera of len 1): weather Gaussians join the scene's in a single rasterisation."""
    settings = settings or RenderSettings()
    active = [m for m in models if m.active]
    extra = []
    for m in active:
        if m.stage == "gaussians":
            g = m.gaussians_for(view)
            if g is not None and len(g) > 0:
                extra.append(g)
    gaussians = GaussianSet.cat([scene_gaussians, *extra]) if extra else scene_gaussians
    out = rasterizer.render(gaussians, camera, settings)
    rgb = out.rgb
    for m in active:
        if m.stage != "gaussians":
            rgb = m.apply(rgb, out, view, settings)
    return WeatherRender(
        rgb=rgb, out=out, num_scene=len(scene_gaussians), num_weather=len(gaussians) - len(scene_gaussians)
    )
