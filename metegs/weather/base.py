"""The `WeatherModel` interface: what a weather component gives the renderer, and what it is built from."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Literal

import torch

from metegs.cameras import Cameras
from metegs.config import InstantiateConfig
from metegs.gaussians.model import GaussianSet
from metegs.meteo.mapping import Theta
from metegs.render.base import RenderOutput, RenderSettings

Stage = Literal["gaussians", "medium", "lens"]


@dataclass
class WeatherScene:
    """What weather models need to know about a scene besides θ."""

    cameras: Cameras
    """Every view of the scene (weather may be per view)."""
    up: torch.Tensor
    """[3] unit world up vector."""
    metres_per_unit: float = 1.0
    """Length of one scene unit in metres (1 for metric scenes)."""
    images: list[torch.Tensor] | None = None
    """[H, W, 3] images of the views in [0, 1] (clean where known), for colour and airlight estimates."""
    seed: int = 0
    """Seed of every random choice (per view: seed + view)."""

    def to_metres(self, length_units: torch.Tensor | float) -> torch.Tensor | float:
        return length_units * self.metres_per_unit

    def to_units(self, length_m: torch.Tensor | float) -> torch.Tensor | float:
        return length_m / self.metres_per_unit

    def distance_m(self, points: torch.Tensor, view: int) -> torch.Tensor:
        """Distance of world points [N, 3] (scene units) from the camera of view ``view``, in metres -> [N]."""
        return self.to_metres((points - self.cameras.centers[view].to(points)).norm(dim=-1))


class WeatherModel(torch.nn.Module):
    """A weather component built from θ for one scene.

    ``stage`` says where it acts: ``gaussians`` (world-space Gaussians rasterised together with the
    scene's), ``medium`` (an image-space effect of the medium from the rendered depth) or ``lens``
    (an image-space effect on the glass, applied last). An inactive model costs nothing: it gives
    no Gaussians and leaves the image alone. Learnable parameters are ordinary module parameters.
    """

    stage: ClassVar[Stage] = "gaussians"
    name: ClassVar[str] = "weather"
    transient: ClassVar[bool] = False
    """True when the Gaussians differ in every view (rain, snow: each photo is its own instant)."""

    def __init__(self, theta: Theta, scene: WeatherScene):
        super().__init__()
        self.theta = theta
        self.scene = scene

    @property
    def active(self) -> bool:
        """Whether the weather calls for this model at all."""
        return False

    def gaussians_for(self, view: int) -> GaussianSet | None:
        """World-space weather Gaussians of view ``view`` (activated values), or None."""
        return None

    def apply(self, rgb: torch.Tensor, out: RenderOutput, view: int, settings: RenderSettings) -> torch.Tensor:
        """Image-space effect: rgb [H, W, 3] (already composited) -> [H, W, 3]."""
        return rgb

    def transmittance(self, points: torch.Tensor, view: int) -> torch.Tensor | None:
        """Fraction of the light of world points [N, 3] (scene units) that this medium lets reach the camera of
        view ``view`` -> [N] in (0, 1], or None when the model does not attenuate the scene (the default)."""
        return None

    def prior(self, view: int) -> torch.Tensor | None:
        """Weighted prior of the model's learnable parameters for a training step on view ``view`` (scalar added
        to the loss), or None (the default: no prior)."""
        return None

    def summary(self) -> dict | None:
        """The model's learned values next to θ's, for metrics.json (JSON-ready), or None."""
        return None


@dataclass
class WeatherModelConfig(InstantiateConfig):
    """Base of weather model configs: ``setup(theta=..., scene=...)`` builds the model."""

    enabled: bool = True
    """Build this model at all (it is still inactive when θ does not call for it)."""
