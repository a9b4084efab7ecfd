"""Weather models (registry kind ``weather``): rain streaks, fog and lens drops built from θ.

Every model derives from `WeatherModel`; `render_with_weather` composites the weather Gaussians of
all models with the scene Gaussians in one sorted rasterisation and then applies image-space effects.
"""

from metegs.weather.base import WeatherModel, WeatherModelConfig, WeatherScene
from metegs.weather.compose import WeatherRender, build_weather_models, render_with_weather

__all__ = [
    "WeatherModel",
    "WeatherModelConfig",
    "WeatherRender",
    "WeatherScene",
    "build_weather_models",
    "render_with_weather",
]
