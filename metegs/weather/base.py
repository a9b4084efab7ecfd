"""The `WeatherModel` interface: what a weather component gives the renderer, and what it is built from."""

from __future__ import annotations

from collections.abc import Callable
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
    north: torch.Tensor | None = None
    """[3] world direction taken as geographic north for the wind (None: the cameras' mean viewing direction); the
    viewer pins it to the training views' so that the wind keeps its direction whichever way one looks."""

    def north_hint(self, configured: tuple[float, float, float] | None = None) -> torch.Tensor:
        """[3] float64 direction of north: ``configured`` (a model's option) when given, else `north`, else the mean
        viewing direction of the cameras (to be made horizontal, e.g. by `rain_streaks.horizontal_frame`)."""
        if configured is not None:
            return torch.tensor(configured, dtype=torch.float64)
        if self.north is not None:
            return self.north.detach().double().cpu()
        return self.cameras.camera_to_worlds.double().cpu()[:, :3, 2].mean(0)

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
    kind: ClassVar[str] = "weather"
    """What weather this is (``rain``, ``fog``, ``drops``, ``snow`` ...): the word `--degrade`, `metegs-synth --kinds`
    and the benchmark's conditions use for it, and what `--degrade auto` synthesises for a method that models it."""
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

    def seen_through(self, colour: torch.Tensor, alpha: torch.Tensor, depth: torch.Tensor, view: int) -> torch.Tensor:
        """A layer in front of a view's backdrop (premultiplied colour [H, W, 3], alpha [H, W], camera depth [H, W])
        as seen through this medium: its light attenuated and the light the medium scatters in front of it added
        where it covers -> [H, W, 3]. The default (no medium) leaves it unchanged."""
        return colour

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


MODEL_SEED_OFFSET = 7919
"""Added to a run's seed for the weather models it trains (and the viewer shows): never the seed a dataset was
synthesised with, so that a model never knows the streaks it has to find."""


def model_seed(seed: int) -> int:
    """The seed of a run's weather models for the run's ``seed``."""
    return int(seed) + MODEL_SEED_OFFSET


@dataclass(frozen=True)
class SynthesisRequest:
    """What a dataset's synthesis asks of the weather models (`WeatherModelConfig.for_synthesis`)."""

    kinds: frozenset[str]
    """Weather kinds asked for, e.g. {"rain", "fog"}."""
    theta: Theta
    """θ of the views being degraded."""
    airlight: Callable[[], tuple[float, float, float]]
    """The airlight of every view, estimated once from all clean images (for media that need one)."""


@dataclass
class WeatherModelConfig(InstantiateConfig):
    """Base of weather model configs: ``setup(theta=..., scene=...)`` builds the model."""

    enabled: bool = True
    """Build this model at all (it is still inactive when θ does not call for it)."""

    @property
    def kind(self) -> str:
        """The weather kind of the model this config builds (`WeatherModel.kind`)."""
        return self.model_class().kind

    def model_class(self) -> type[WeatherModel]:
        """The `WeatherModel` subclass this config builds."""
        target = getattr(self, "_target", None)
        if isinstance(target, str):
            from metegs.registry import Entry

            target = Entry(type(self).__name__, target).load()
        return target

    def for_synthesis(self, request: SynthesisRequest) -> WeatherModelConfig | None:
        """The config with which this model degrades a dataset for ``request`` (`metegs-synth`, `--degrade`), or None
        when it adds nothing to that weather: by default itself when its kind is asked for. A model whose weather
        another one synthesises better returns None; a medium that needs an airlight takes ``request.airlight()``."""
        return self if self.kind in request.kinds else None
