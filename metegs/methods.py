"""Named, complete method configs (registry kind ``method``). Variants derive from a base with `replace`; MeteGS's
carry a typed field for every registered weather model, plugins' included (`plugin_weather_fields`)."""

from __future__ import annotations

from metegs.engine.config import TrainConfig
from metegs.engine.metegs_config import MeteGSConfig, plugin_weather_fields


def gaussian_splatting() -> TrainConfig:
    """Plain 3D Gaussian Splatting with the reference defaults: 0.8·L1 + 0.2·(1 − SSIM), ADC densification."""
    return TrainConfig(method="3dgs")


def metegs_full() -> MeteGSConfig:
    """MeteGS: rain streaks + analytic fog rendered with the scene, GTN, clean branch, depth pruning, extra points."""
    return plugin_weather_fields(MeteGSConfig)(method="metegs-full")


def metegs_rain() -> MeteGSConfig:
    """MeteGS with rain streaks only (no fog model)."""
    return plugin_weather_fields(MeteGSConfig)(method="metegs-rain", weather=("rain-streaks",))


def metegs_fog() -> MeteGSConfig:
    """MeteGS with analytic fog only (no rain model)."""
    return plugin_weather_fields(MeteGSConfig)(method="metegs-fog", weather=("fog-analytic",))
