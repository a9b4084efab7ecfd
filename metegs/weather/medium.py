"""The fog medium both fog models share: extinction per channel, whether it is called for, and the airlight."""

from __future__ import annotations

import math

import torch

from metegs.cameras import Cameras
from metegs.meteo.mapping import Theta
from metegs.weather.airlight import estimate_airlight
from metegs.weather.base import WeatherScene
from metegs.weather.conditions import LIGHT_OR_NONE, rain_phrase, scene_depth_m


def fog_extinction_rgb(theta: Theta, include_rain_veil: bool) -> torch.Tensor:
    """[3] float64 β per R, G, B (1/m): θ_fog's, plus the rain's extinction beyond the streaks when it rains."""
    beta = torch.tensor(theta.fog.beta_rgb_per_m, dtype=torch.float64)
    if include_rain_veil and theta.rain.active:
        beta = beta + theta.fog.beta_rain_per_m
    return beta


VISIBLE_CONTRAST_LOSS = 0.05
"""Contrast change a person just notices: the eye's contrast threshold ε on which the WMO defines the
meteorological optical range (ε = 0.05). A veil that takes less of a surface's contrast at the scene's own
depths cannot be told in the photos from the surfaces' colours."""


def veil_fraction(beta_per_m: float, depth_m: float) -> float:
    """Share of a surface's contrast the medium takes at ``depth_m``: 1 − exp(−β·d)."""
    return -math.expm1(-max(beta_per_m, 0.0) * max(depth_m, 0.0))


def typical_depth_m(
    cameras: Cameras, points: torch.Tensor | None, metres_per_unit: float, max_points: int = 4096
) -> float:
    """Median distance in metres from the cameras to the scene points in front of them (a typical pixel's depth).

    cameras: the views; points: [P, 3] scene points (SfM or surface samples; at most ``max_points`` of them are
    used, evenly spread) or None, then the cameras' spread (`weather.conditions.scene_depth_m`) stands in."""
    if points is None or len(points) == 0:
        return scene_depth_m(cameras, metres_per_unit)
    pts = torch.as_tensor(points, dtype=torch.float64).cpu()
    pts = pts[:: max(1, len(pts) // max_points)]
    w2c = cameras.world_to_cameras().double().cpu()  # [V, 4, 4]
    z = torch.einsum("vij,pj->vpi", w2c[:, :3, :3], pts) + w2c[:, None, :3, 3]
    dist = z.norm(dim=-1)[z[..., 2] > 0]
    if dist.numel() == 0:
        return scene_depth_m(cameras, metres_per_unit)
    return float(dist.median()) * metres_per_unit


def visible_weather(theta: Theta, depth_m: float) -> str | None:
    """What of ``theta``'s weather a person would see in the photos, as a phrase: rain heavier than light, or a
    medium (fog, the rain's veil) over clear air that takes at least `VISIBLE_CONTRAST_LOSS` of a surface's contrast
    at the scene's typical depth ``depth_m`` (`typical_depth_m`); None for clear air or light rain alone."""
    rain = theta.rain
    if rain.intensity_class not in LIGHT_OR_NONE:
        return rain_phrase(rain)
    beta = theta.fog.beta_veil_per_m - theta.fog.beta_background_per_m
    veil = veil_fraction(beta, depth_m)
    if veil >= VISIBLE_CONTRAST_LOSS:
        return f"a medium taking {veil:.0%} of the contrast at the scene's typical depth ({depth_m:.0f} m)"
    return None


MEASURABLE_DISTANCE_SPREAD = 1.5
"""Median ratio of the farthest to the nearest distance at which the views see a scene point, from which the
photos measure fog's β themselves (a point's fog changes between its views by exp(−β·Δd)). Below it (forward-
facing captures: 1.07-1.26 on the Ethiopian head) a hazy scene under thinner fog fits the photos as well as the
true fog; the built-in scene's surrounding views see points 1.8-2.2 times farther in one view than in another."""


def nearest_and_farthest(point: torch.Tensor, distance: torch.Tensor, points: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The smallest and largest ``distance`` [N] over each point's observations (``point`` [N], indices below
    ``points``) -> (near [points], far [points]); inf and 0 for a point not observed."""
    near = torch.full((points,), float("inf")).scatter_reduce(0, point, distance, "amin")
    far = torch.zeros(points).scatter_reduce(0, point, distance, "amax")
    return near, far


def distance_spread(cameras: Cameras, points: torch.Tensor | None, max_points: int = 4096) -> float | None:
    """Median over scene points seen by at least two views of (largest / smallest camera distance among those
    views), or None without such points. cameras: the views; points [P, 3] (at most ``max_points`` used)."""
    if points is None or len(points) == 0:
        return None
    pts = torch.as_tensor(points, dtype=torch.float32).cpu()
    pts = pts[:: max(1, len(pts) // max_points)]
    cameras = cameras.to("cpu")
    seen = cameras.sees(pts)  # [C, P]
    dist = (pts[None] - cameras.centers[:, None]).norm(dim=-1)
    view, point = seen.nonzero(as_tuple=True)
    near, far = nearest_and_farthest(point, dist[view, point], len(pts))
    twice = seen.sum(0) >= 2
    if not twice.any():
        return None
    return float((far[twice] / near[twice]).median())


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
