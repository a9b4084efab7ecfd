"""The configuration of the MeteGS dual-branch method (`metegs-full`, `metegs-rain`, `metegs-fog`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated, Literal

from metegs.densify.depth_prune import DepthPruneConfig
from metegs.densify.extra_points import ExtraPointsConfig
from metegs.engine.config import TrainConfig
from metegs.losses.perceptual import PerceptualLossConfig
from metegs.losses.robust import RobustMaskConfig
from metegs.models.gtn import GTNConfig
from metegs.validate import NON_NEGATIVE
from metegs.weather.fog_analytic import FogAnalyticConfig
from metegs.weather.fog_gaussians import FogGaussiansConfig
from metegs.weather.learnable import LearnableWeatherConfig
from metegs.weather.lens_droplets import LensDropletsConfig
from metegs.weather.rain_streaks import RainStreaksConfig


@dataclass
class LossWeights:
    """Weights of the terms of L = λ_photo·L_photo + λ_perc·L_perc + λ_clean·L_clean."""

    photo: Annotated[float, NON_NEGATIVE] = 1.0
    """λ_photo: weather branch against the observed (degraded) photo, (1−λ)·L1 + λ·(1−SSIM)."""
    perceptual: Annotated[float, NON_NEGATIVE] = 0.05
    """λ_perc: clean branch against the clean reference on frozen pretrained features (0: off)."""
    clean: Annotated[float, NON_NEGATIVE] = 0.1
    """λ_clean: L1 of the clean branch against the clean reference (0: off)."""


@dataclass
class MeteGSConfig(TrainConfig):
    """MeteGS: scene + weather Gaussians fit the degraded photos; the scene alone is held to the clean domain."""

    _target: type = field(default_factory=lambda: _trainer_class(), repr=False)
    max_steps: int = 1500
    """Number of training steps (one view per step; two renders each: weather and clean branch)."""
    degrade: Literal["off", "auto", "rain", "fog", "rain+fog"] = "auto"
    """Degrade a clean scene in memory before training, with the weather of `conditions` (the clean images become
    the references): auto = the method's weather kinds on the built-in synthetic scene, off for scenes from files."""
    weather: tuple[str, ...] = ("rain-streaks", "fog-analytic")
    """Weather models by registry name, plugins included (e.g. --weather snow fog-analytic)."""
    weather_branch: bool = True
    """Ablation: render weather Gaussians in the photo branch (off: the scene alone fits the degraded photos)."""
    clean_supervision: bool = True
    """Use the clean references when the scene has them (off: blind mode, as with real rainy captures)."""
    weights: LossWeights = field(default_factory=LossWeights)
    """Loss weights."""
    gtn: GTNConfig = field(default_factory=GTNConfig)
    """Gaussian Transformation Network of the weather branch."""
    perceptual: PerceptualLossConfig = field(default_factory=PerceptualLossConfig)
    """Perceptual loss of the clean branch (backbone and layers)."""
    depth_prune: bool = True
    """Depth-aware pruning: the opacity threshold falls with normalised camera depth."""
    depth_prune_options: DepthPruneConfig = field(default_factory=DepthPruneConfig)
    """Depth-aware pruning options."""
    extra_points: bool = True
    """Extra-point compensation in sparse regions, once early in the run."""
    extra_points_options: ExtraPointsConfig = field(default_factory=lambda: ExtraPointsConfig(max_relative=0.25))
    """Extra-point compensation options."""
    learnable_weather: LearnableWeatherConfig = field(default_factory=LearnableWeatherConfig)
    """Bounds, learning rates and coverage prior of the per-view weather Gaussians."""
    weather_lr: Annotated[float, NON_NEGATIVE] = 0.01
    """Learning rate of global weather parameters (fog log-β and airlight logit)."""
    rain_streaks: RainStreaksConfig = field(default_factory=lambda: RainStreaksConfig(max_count=2000))
    """Options of `rain-streaks` (when listed in `weather`)."""
    fog_analytic: FogAnalyticConfig = field(default_factory=FogAnalyticConfig)
    """Options of `fog-analytic` (when listed in `weather`)."""
    fog_gaussians: FogGaussiansConfig = field(default_factory=FogGaussiansConfig)
    """Options of `fog-gaussians` (when listed in `weather`)."""
    lens_droplets: LensDropletsConfig = field(default_factory=LensDropletsConfig)
    """Options of `lens-droplets` (when listed in `weather`)."""
    weather_options: dict[str, dict[str, int | float | bool | str]] = field(default_factory=dict)
    """Options of weather models by name, plugins included (e.g. --weather-options snow max_count 500)."""
    robust: RobustMaskConfig = field(default_factory=RobustMaskConfig)
    """Trimmed photometric loss of the weather branch: pixels no model explains in a view are left out of it."""
    compare_baseline: bool = True
    """After training, train plain `3dgs` on the same photos and print both clean-view metrics."""

    def weather_config(self, name: str):
        """The config of weather model ``name``: the built-ins' fields above, else the registered default
        (plugins), with `weather_options` applied on top."""
        from metegs.config import apply_overrides
        from metegs.registry import registry

        builtin = {
            "rain-streaks": self.rain_streaks,
            "fog-analytic": self.fog_analytic,
            "fog-gaussians": self.fog_gaussians,
            "lens-droplets": self.lens_droplets,
        }.get(name)
        config = builtin if builtin is not None else registry("weather").get(name)()
        options = self.weather_options.get(name)
        return apply_overrides(config, options, f"weather_options.{name}") if options else config


def _trainer_class():
    from metegs.engine.metegs_trainer import MeteGSTrainer

    return MeteGSTrainer
