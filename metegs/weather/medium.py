"""The fog medium both fog models share: extinction per channel, whether it is called for, and the airlight."""

from __future__ import annotations

import torch

from metegs.meteo.mapping import Theta
from metegs.weather.airlight import estimate_airlight
from metegs.weather.base import WeatherScene


def fog_extinction_rgb(theta: Theta, include_rain_veil: bool) -> torch.Tensor:
    """[3] float64 β per R, G, B (1/m): θ_fog's, plus the rain's extinction beyond the streaks when it rains."""
    beta = torch.tensor(theta.fog.beta_rgb_per_m, dtype=torch.float64)
    if include_rain_veil and theta.rain.active:
        beta = beta + theta.fog.beta_rain_per_m
    return beta


def fog_called_for(theta: Theta, include_rain_veil: bool) -> bool:
    """Fog is reported (or implied by the visibility), or it rains and the rain's veil is wanted."""
    return bool(theta.fog.active or (include_rain_veil and theta.rain.active and theta.fog.beta_rain_per_m > 0))


def choose_airlight(explicit: tuple[float, float, float] | None, theta: Theta, scene: WeatherScene) -> torch.Tensor:
    """[3] airlight: the config's, else θ's, else estimated from the scene's images, else light grey (0.8)."""
    if explicit is not None:
        return torch.tensor(explicit, dtype=torch.float32)
    if theta.fog.airlight_rgb is not None:
        return torch.tensor(theta.fog.airlight_rgb, dtype=torch.float32)
    if scene.images:
        return estimate_airlight([im.detach().cpu() for im in scene.images])
    return torch.full((3,), 0.8)
