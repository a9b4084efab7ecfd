"""Where a run's weather comes from (a met record at a capture time, or explicit values) and its θ for a scene."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import torch

from metegs.cameras import Cameras
from metegs.errors import ConfigError
from metegs.meteo import CameraSpec, Theta, theta_from_record, theta_from_values


@dataclass
class ConditionsConfig:
    """The weather of the capture: a station record at a time, or explicit values (which win)."""

    record: Path | None = None
    """Met record (any metegs-meteo reader, detected); None: the storm record shipped with metegs."""
    time: str | None = None
    """Capture time, ISO 8601 (e.g. 2013-08-11T07:40Z); None: the shipped record's default hour."""
    window: str = "1h"
    """Aggregation window around the capture time."""
    agg: Literal["mean", "max", "min"] = "max"
    """Aggregation of the rate over the window."""
    precip_mm_h: float | None = None
    """Precipitation rate, mm/h (overrides the record; with it, no record is read)."""
    visibility_m: float | None = None
    """Visibility, m (overrides the record's; None keeps it)."""
    wind_speed_m_s: float | None = None
    """Wind speed, m/s (overrides the record's)."""
    wind_dir_deg: float | None = None
    """Direction the wind blows from, degrees clockwise from north (overrides the record's)."""
    exposure_s: float | None = None
    """Exposure time, s; None: the cameras' (EXIF), else 1/60 s."""
    metres_per_unit: float | None = None
    """Metres per scene unit for the weather; None: the scene's own scale (metric scenes), else 1."""
    capture_width_px: int = 1920
    """Width of the photos as the camera took them (streak visibility depends on the sensor's resolution,
    not the training resolution); 0: the dataset's stored width."""


def camera_spec(cameras: Cameras, config: ConditionsConfig, far_max_m: float = 10.0) -> CameraSpec:
    """The camera θ is mapped for: the first view's field of view at the capture resolution."""
    width, height, fx, fy = (float(v[0]) for v in (cameras.width, cameras.height, cameras.fx, cameras.fy))
    scale = config.capture_width_px / width if config.capture_width_px > 0 else 1.0
    exposure = config.exposure_s
    if exposure is None and cameras.exposure_time_s is not None:
        exposure = float(cameras.exposure_time_s[0])
    exposure = exposure or 1.0 / 60.0
    if not (math.isfinite(exposure) and exposure > 0):
        raise ConfigError(f"--conditions.exposure-s must be a positive number of seconds, got {exposure}")
    return CameraSpec.from_intrinsics(
        fx * scale, round(width * scale), round(height * scale), fy=fy * scale, exposure_s=exposure, far_max_m=far_max_m
    )


def scene_depth_m(cameras: Cameras, metres_per_unit: float) -> float:
    """A scene's typical viewing distance in metres: the mean camera distance to the cameras' centroid."""
    centres = cameras.camera_to_worlds[:, :3, 3].double()
    if len(centres) < 2:
        return 10.0
    return float((centres - centres.mean(0)).norm(dim=1).mean()) * metres_per_unit


def theta_for_cameras(config: ConditionsConfig, cameras: Cameras, metres_per_unit: float) -> Theta:
    """θ of the configured weather for a scene's cameras (streaks no farther than the scene itself)."""
    far_max = max(1.0, min(10.0, scene_depth_m(cameras, metres_per_unit)))
    spec = camera_spec(cameras, config, far_max_m=far_max)
    if config.precip_mm_h is not None:
        return theta_from_values(
            config.precip_mm_h,
            config.visibility_m,
            config.wind_speed_m_s or 0.0,
            config.wind_dir_deg,
            camera=spec,
        )
    theta = theta_from_record(config.record, config.time, config.window, config.agg, camera=spec)
    c = theta.conditions
    overrides = (config.visibility_m, config.wind_speed_m_s, config.wind_dir_deg)
    if all(v is None for v in overrides):
        return theta
    return theta_from_values(
        c.precip_mm_per_h,
        config.visibility_m if config.visibility_m is not None else c.visibility_m,
        config.wind_speed_m_s if config.wind_speed_m_s is not None else (c.wind_speed_m_per_s or 0.0),
        config.wind_dir_deg if config.wind_dir_deg is not None else c.wind_dir_deg_from,
        kind="drizzle" if c.precip_kind == "drizzle" else "rain",
        camera=spec,
    )


def scene_metres_per_unit(config: ConditionsConfig, metric_scale: float | None) -> float:
    """The scale the weather uses: the configured one, else the scene's, else 1 (with the choice left to the caller to report)."""
    value = config.metres_per_unit if config.metres_per_unit is not None else (metric_scale or 1.0)
    if not (math.isfinite(value) and value > 0):
        raise ConfigError(f"--conditions.metres-per-unit must be a positive number, got {value}")
    return float(value)


def describe(theta: Theta) -> str:
    """One line: rate and class, visibility, streak count, fog extinction."""
    c, r, f = theta.conditions, theta.rain, theta.fog
    vis = "none" if c.visibility_m is None else f"{c.visibility_m:.0f} m"
    return (
        f"{c.precip_mm_per_h:.1f} mm/h ({r.intensity_class}), visibility {vis}, wind "
        f"{c.wind_speed_m_per_s or 0:.1f} m/s; {r.count if r.active else 0} streaks/view, "
        f"fog β {torch.tensor(f.beta_rgb_per_m).mean():.2e}/m" + (" (fog)" if f.active else "")
    )
