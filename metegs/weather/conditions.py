"""Where a run's weather comes from (a met record at a capture time, or explicit values) and its θ for a scene."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import torch

from metegs.cameras import Cameras
from metegs.errors import ConfigError, MetegsError
from metegs.meteo import CameraSpec, Theta, limits, parse_options, parse_time
from metegs.meteo.units import parse_duration_s
from metegs.validate import POSITIVE, Range, check_config

DEFAULT_EXPOSURE_S = 1.0 / 60.0
"""Exposure time assumed for cameras that do not say theirs, s."""


@dataclass
class ConditionsConfig:
    """The weather of the capture: a station record at a time, or explicit values (which win)."""

    record: Path | None = None
    """Met record (any metegs-meteo reader, detected); None: the storm record shipped with metegs."""
    time: str | None = None
    """Capture time, ISO 8601 (e.g. 2013-08-11T07:40Z); None: the shipped record's default hour."""
    reader: str | None = None
    """Reader of the record (csv, metar, ghcnh, isd, open-meteo); None: detected from the file."""
    set: tuple[str, ...] = ()
    """Reader options as KEY=VALUE (e.g. year=2024 month=7 for METAR, precip_column=RAIN for a csv)."""
    station: str | None = None
    """Station, for records holding several."""
    window: str = "1h"
    """Aggregation window around the capture time."""
    agg: Literal["mean", "max", "min"] = "max"
    """Aggregation of the rate over the window."""
    precip_mm_h: Annotated[float | None, Range(0, limits.MAX_PRECIP_RATE_MM_H)] = None
    """Explicit precipitation rate, mm/h (instead of a record); at most 2400, 40 mm a minute, above the world record."""
    visibility_m: Annotated[float | None, Range(limits.MIN_VISIBILITY_M)] = None
    """Visibility, m: explicit, or replacing the record's (records such as PRSA have none); at least 1."""
    wind_speed_m_s: Annotated[float | None, Range(0, limits.MAX_WIND_M_S)] = None
    """Explicit wind speed, m/s (with --conditions.precip-mm-h); at most 120, above the strongest gust measured."""
    wind_dir_deg: Annotated[float | None, Range(0, 360)] = None
    """Explicit direction the wind blows from, degrees clockwise from north, 0-360 (with --conditions.precip-mm-h)."""
    exposure_s: Annotated[float | None, Range(0, 3600, lo_open=True)] = None
    """Exposure time, s (at most an hour); None: the photos' (their EXIF, or the nerfstudio ``metegs`` block;
    the median over the views), else 1/60 s."""
    metres_per_unit: Annotated[float | None, POSITIVE] = None
    """Metres per scene unit for the weather; None: the scene's own scale (metric scenes), else 1."""
    capture_width_px: Annotated[int, Range(0, 100_000)] = 1920
    """Width of the photos as the camera took them (streak visibility depends on the sensor's resolution,
    not the training resolution); 0: the dataset's stored width."""

    @property
    def stated(self) -> bool:
        """Whether the user stated the capture's weather (a record, a time in the shipped one, or values) rather
        than leaving the shipped storm record to stand in."""
        return any(v is not None for v in (self.record, self.time, self.precip_mm_h, self.visibility_m))

    def __post_init__(self) -> None:
        """Refuse impossible values when the options are parsed, naming the flag as typed."""
        check_config(self, "conditions.")
        for flag, value, parse in (("window", self.window, parse_duration_s), ("time", self.time, parse_time)):
            try:
                if value is not None:
                    parse(value)
            except MetegsError as exc:
                raise ConfigError(f"--conditions.{flag}: {exc}") from None
        parse_options(self.set, "--conditions.set")
        if self.precip_mm_h is None and (self.wind_speed_m_s is not None or self.wind_dir_deg is not None):
            raise ConfigError("--conditions.wind-* go with --conditions.precip-mm-h (explicit values), not a record")
        if self.record is None and (self.reader is not None or self.set or self.station is not None):
            raise ConfigError("--conditions.reader/--conditions.set/--conditions.station need --conditions.record")


def camera_spec(
    cameras: Cameras,
    exposure_s: float | None = None,
    capture_width_px: int = 1920,
    far_max_m: float = 10.0,
    far_m: float | None = None,
) -> CameraSpec:
    """The camera θ is mapped for: the first view's field of view at the capture resolution, an exposure
    (``exposure_s``, else the views' median, from their EXIF or the scene file, else 1/60 s), streaks no farther
    than ``far_max_m`` (or at ``far_m``)."""
    width, height, fx, fy = (float(v[0]) for v in (cameras.width, cameras.height, cameras.fx, cameras.fy))
    scale = capture_width_px / width if capture_width_px > 0 else 1.0
    if exposure_s is None and cameras.exposure_time_s is not None:
        exposure_s = float(cameras.exposure_time_s.float().median())
    exposure_s = DEFAULT_EXPOSURE_S if exposure_s is None else exposure_s
    if not (math.isfinite(exposure_s) and exposure_s > 0):
        raise ConfigError(f"exposure time must be a positive number of seconds, got {exposure_s}")
    return CameraSpec.from_intrinsics(
        fx * scale,
        round(width * scale),
        round(height * scale),
        fy=fy * scale,
        exposure_s=exposure_s,
        far_max_m=max(far_max_m, 0.5),
        far_m=far_m,
    )


def scene_depth_m(cameras: Cameras, metres_per_unit: float) -> float:
    """A scene's typical viewing distance in metres: the mean camera distance to the cameras' centroid."""
    centres = cameras.camera_to_worlds[:, :3, 3].double()
    if len(centres) < 2:
        return 10.0
    return float((centres - centres.mean(0)).norm(dim=1).mean()) * metres_per_unit


def theta_camera(
    cameras: Cameras,
    metres_per_unit: float,
    exposure_s: float | None = None,
    capture_width_px: int = 1920,
    far_m: float | None = None,
) -> CameraSpec:
    """`camera_spec` with streaks capped at the scene's own depth (at most 10 m)."""
    far_max = max(1.0, min(10.0, scene_depth_m(cameras, metres_per_unit)))
    return camera_spec(cameras, exposure_s, capture_width_px, far_max_m=far_max, far_m=far_m)


def theta_for_cameras(config: ConditionsConfig, cameras: Cameras, metres_per_unit: float) -> Theta:
    """θ of the configured weather for a scene's cameras: explicit values, else the record at its time."""
    from metegs.meteo.theta_plan import plan_from_record, plan_from_values

    spec = theta_camera(cameras, metres_per_unit, config.exposure_s, config.capture_width_px)
    if config.precip_mm_h is not None:
        plan = plan_from_values(
            1, spec, config.precip_mm_h, config.visibility_m, config.wind_speed_m_s or 0.0, config.wind_dir_deg
        )
    else:
        times = [config.time] if config.time else None
        plan = plan_from_record(
            1,
            spec,
            config.record,
            times,
            reader=config.reader,
            options=parse_options(config.set),
            window=config.window,
            agg=config.agg,
            station=config.station,
            visibility_m=config.visibility_m,
        )
    return plan.thetas[0]


def scene_metres_per_unit(config: ConditionsConfig, metric_scale: float | None) -> float:
    """The scale the weather uses: the configured one, else the scene's, else 1 (with the choice left to the caller to report)."""
    value = config.metres_per_unit if config.metres_per_unit is not None else (metric_scale or 1.0)
    if not (math.isfinite(value) and value > 0):
        raise ConfigError(f"--conditions.metres-per-unit must be a positive number, got {value}")
    return float(value)


def describe_conditions(theta: Theta) -> str:
    """One line of the met conditions θ was mapped from: rate and class, visibility, wind."""
    c = theta.conditions
    vis = "none" if c.visibility_m is None else f"{c.visibility_m:.0f} m"
    return (
        f"{c.precip_mm_per_h:.1f} mm/h ({theta.rain.intensity_class}), visibility {vis}, wind "
        f"{c.wind_speed_m_per_s or 0:.1f} m/s"
    )


LIGHT_OR_NONE = ("none", "light")
"""WMO rain classes whose streaks neither blur the photos nor stand out of them: the GTN and the robust mask stay off
(measured on the built-in scene under independent light rain: each cost 1.6-2.4 dB against leaving it off)."""


def rain_phrase(rain) -> str:
    """``no rain`` or ``light rain (1.5 mm/h)``: the rain of θ_rain in a decision."""
    return (
        "no rain" if rain.intensity_class == "none" else f"{rain.intensity_class} rain ({rain.precip_mm_per_h:g} mm/h)"
    )


def describe(theta: Theta) -> str:
    """One line: the conditions, streak count (and the exposure that sets their length), total extinction and its
    fog / rain-veil parts."""
    r, f = theta.rain, theta.fog
    exposure = f" at 1/{1 / theta.camera.exposure_s:.0f} s" if r.active and theta.camera.exposure_s < 1 else ""
    return (
        f"{describe_conditions(theta)}; {r.count if r.active else 0} streaks/view{exposure}, "
        f"extinction β {f.beta_total_per_m:.2e}/m (fog {torch.tensor(f.beta_rgb_per_m).mean():.2e}, "
        f"rain veil {f.beta_rain_per_m:.2e})" + (", fog on" if f.active else "")
    )
