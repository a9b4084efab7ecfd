"""The configuration of the MeteGS dual-branch method (`metegs-full`, `metegs-rain`, `metegs-fog`)."""

from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass, field
from typing import Annotated, Literal, TypeVar

from metegs.densify.adc import ADCConfig
from metegs.densify.depth_prune import DepthPruneConfig
from metegs.densify.extra_points import ExtraPointsConfig
from metegs.engine.config import TrainConfig
from metegs.losses.dark_channel import DarkChannelPriorConfig
from metegs.losses.perceptual import PerceptualLossConfig
from metegs.losses.robust import RobustMaskConfig
from metegs.models.gtn import GTNConfig
from metegs.validate import NON_NEGATIVE, Range
from metegs.weather.base import WeatherModelConfig
from metegs.weather.fog_analytic import FogAnalyticConfig
from metegs.weather.fog_gaussians import FogGaussiansConfig
from metegs.weather.learnable import LearnableWeatherConfig
from metegs.weather.lens_droplets import LensDropletsConfig
from metegs.weather.medium import VISIBLE_CONTRAST_LOSS
from metegs.weather.rain_streaks import RainStreaksConfig

C = TypeVar("C")

BLURRED_PRUNE_OPACITY = 0.005
"""MeteGS's base opacity-pruning threshold (Deblurring-3DGS's): blurred photos need faint Gaussians."""
SHARP_PRUNE_OPACITY = ADCConfig().prune_opacity
"""3dgs's threshold, which training takes where nothing in the weather blurs the photos."""


@dataclass
class LossWeights:
    """Weights of the terms of L = λ_photo·L_photo + λ_perc·L_perc + λ_clean·L_clean."""

    photo: Annotated[float, NON_NEGATIVE] = 1.0
    """λ_photo: weather branch against the observed (degraded) photo, (1−λ)·L1 + λ·(1−SSIM)."""
    perceptual: Annotated[float, NON_NEGATIVE] = 0.05
    """λ_perc: clean branch against the clean reference on frozen pretrained features (0: off)."""
    clean: Annotated[float, NON_NEGATIVE] = 2.0
    """λ_clean: the clean branch against the clean reference, with L_photo's (1−λ)·L1 + λ·(1−SSIM), twice the photos'
    weight: the references hold the scene, the weather models take the rest (0: off)."""
    pseudo: Annotated[float, NON_NEGATIVE] = 0.5
    """λ_pseudo: L1 of the clean branch's detail against the 2D-restored photo's (`pseudo_references restore`, blind
    runs; `pseudo_detail_px`)."""


@dataclass
class MeteGSConfig(TrainConfig):
    """MeteGS: scene + weather Gaussians fit the degraded photos; the scene alone is held to the clean domain."""

    _target: type = field(default_factory=lambda: _trainer_class(), repr=False)
    max_steps: int = 1500
    """Number of training steps (one view per step; two renders each: weather and clean branch)."""
    degrade: str = "auto"
    """Degrade a clean scene in memory before training, with the weather of `conditions` (the clean images become
    the references): off, auto (the kinds of the `weather` models on the built-in synthetic scene, off for scenes
    from files) or weather kinds joined with + (rain, fog, rain+fog, +drops; a plugin's, e.g. snow+fog)."""
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
    view_exposure: Literal["auto", "on", "off"] = "auto"
    """Per-view gains and offsets of the photos' tone (see 3dgs); auto: as 3dgs where no fog model is on, off beside
    one, whose airlight and β set each view's tone too (the comparison's 3dgs run gets the same setting)."""
    pseudo_references: Literal["off", "restore"] = "off"
    """Blind runs: restore each training photo in 2D (Kang 2012 for rain, DCP for fog: the active weather's kinds) and
    hold the clean branch's detail to the restored photo's at weight `weights.pseudo` (`pseudo_detail_px`)."""
    pseudo_detail_px: Annotated[int, NON_NEGATIVE] = 15
    """Box width in pixels: the pseudo-reference L1 compares x − box(x), the detail a 2D restorer gets right
    (streaks out, edges kept), not its tone, which the weather models set (0: the whole restored photo)."""
    densify: ADCConfig = field(default_factory=lambda: ADCConfig(prune_opacity=BLURRED_PRUNE_OPACITY))
    """Densification; pruning keeps Deblurring-3DGS's base threshold 0.005, which depth-aware pruning lowers
    for far Gaussians (3dgs's 0.1 costs blind MeteGS 0.9 dB on the default run; where nothing blurs the photos,
    training takes 3dgs's), and 3dgs's world-size prune at half the extent (0.1 cost blind MeteGS 0.4-0.9 dB in
    rain on the Lund street, two seeds)."""
    clear_start_colours: bool = True
    """Start the points' colours from the clean references, or in blind mode from the photos with the weather's medium
    (fog, rain veil) taken out along each point's distance; off: the photos' colours, weather and all."""
    depth_prune: bool = True
    """Depth-aware pruning: the opacity threshold falls with normalised camera depth."""
    depth_prune_options: DepthPruneConfig = field(default_factory=DepthPruneConfig)
    """Depth-aware pruning options."""
    camera_clearance: Annotated[float, NON_NEGATIVE] = 0.5
    """Prune the Gaussians closer to a training camera than this fraction of the median distance between
    neighbouring cameras (at most a tenth of the scene's typical depth) that none of the cameras there sees, when
    training ends: the cameras stood there (0: off)."""
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
    robust: RobustMaskConfig = field(default_factory=RobustMaskConfig)
    """Trimmed photometric loss of the weather branch: pixels no model explains in a view are left out of it."""
    min_photo_veil: Annotated[float, Range(0.0, 1.0)] = VISIBLE_CONTRAST_LOSS
    """A medium the record calls for (fog, rain veil) is on only where the training photos' darkest patches show at
    least this share of veil (`photo_veil`: clear photos 0.001-0.014) and, for the rain's veil alone, the scene's
    points show it too (`veil_evidence`); 0: the record alone decides."""
    dark_channel: DarkChannelPriorConfig = field(default_factory=DarkChannelPriorConfig)
    """Blind mode: the photos dehazed by the learned medium keep the dark channel of clear views (sets β)."""
    compare_baseline: bool = True
    """After training, train plain `3dgs` on the same photos and print both clean-view metrics."""

    def weather_config(self, name: str) -> WeatherModelConfig:
        """The config of weather model ``name``: its field (``rain_streaks`` for ``rain-streaks``; a plugin's model has
        one in the configs `plugin_weather_fields` builds, as the method registry gives them), else the registered
        default."""
        from metegs.registry import registry

        config = getattr(self, weather_field(name), None)
        return config if isinstance(config, WeatherModelConfig) else registry("weather").get(name)()


def weather_field(name: str) -> str:
    """The config field of weather model ``name`` (``rain-streaks`` -> ``rain_streaks``)."""
    return name.replace("-", "_")


_WITH_PLUGINS: dict[tuple, type] = {}


def plugin_weather_fields(base: type[C]) -> type[C]:
    """``base`` (a `MeteGSConfig` class) with a typed field for every registered weather model it has none for, the
    plugins' (``--snow.max-count 500`` on the command line, ``snow: {max_count: 500}`` in YAML, listed by ``--help``);
    ``base`` itself when there are none. One class per set of registered models."""
    from metegs.registry import PluginWarning, registry

    own = {f.name: f for f in dataclasses.fields(base)}
    extra = []
    for entry in registry("weather").entries():
        name = weather_field(entry.name)
        config_class = type(entry.load()())
        if name not in own:
            extra.append((name, config_class))
        elif not _holds(own[name], config_class, base):
            warnings.warn(
                f"weather model {entry.name!r} ({entry.source}): its options cannot be set, {name!r} is already a "
                f"field of {base.__name__}; it trains with its defaults",
                PluginWarning,
                stacklevel=2,
            )
    if not extra:
        return base
    key = (base, tuple(extra))
    if key not in _WITH_PLUGINS:
        fields = [(n, c, field(default_factory=c)) for n, c in extra]
        _WITH_PLUGINS[key] = dataclasses.make_dataclass(
            base.__name__, fields, bases=(base,), namespace={"__doc__": base.__doc__, "__module__": base.__module__}
        )
    return _WITH_PLUGINS[key]


def _holds(f: dataclasses.Field, config_class: type, base: type) -> bool:
    """Whether field ``f`` of ``base`` holds a config of ``config_class``."""
    default = f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default
    return isinstance(default, config_class)


def _trainer_class():
    from metegs.engine.metegs_trainer import MeteGSTrainer

    return MeteGSTrainer
