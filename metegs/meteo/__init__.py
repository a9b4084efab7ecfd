"""Meteorology: station records and forecasts → weather conditions at a capture time → weather parameters θ.

    from metegs.meteo import read_observations, theta_from_record
    table = read_observations("station.csv", reader="csv", precip_column="RAIN", ...)
    theta = theta_from_record(table, "2013-08-11T07:40Z", window="1h", agg="max", exposure_s=1/250)
    theta.rain.count, theta.rain.opacity_effective, theta.fog.beta_veil_per_m

With no record, ``theta_from_record()`` uses the real storm excerpt shipped with metegs.
"""

from __future__ import annotations

import dataclasses
from datetime import datetime
from pathlib import Path
from typing import Any

from metegs.errors import ConfigError
from metegs.meteo.aggregate import (
    WeatherConditions,
    conditions_at,
    intensity_class,
    normalised_intensity,
    wmo_score,
)
from metegs.meteo.mapping import (
    CameraSpec,
    MappingConfig,
    PaperMapping,
    Theta,
    ThetaDrops,
    ThetaFog,
    ThetaRain,
    map_conditions,
    theta_from_values,
)
from metegs.meteo.observations import Accumulation, Observation, ObservationTable, parse_time
from metegs.meteo.rates import PrecipSeries, precip_series
from metegs.meteo.readers import MeteoWarning, detect_reader, parse_options, read_observations
from metegs.meteo.storm import DEFAULT_CAPTURE_TIME, default_storm_path, default_storm_record
from metegs.meteo.weather_codes import PresentWeather

__all__ = [
    "DEFAULT_CAPTURE_TIME",
    "Accumulation",
    "CameraSpec",
    "MappingConfig",
    "MeteoWarning",
    "Observation",
    "ObservationTable",
    "PaperMapping",
    "PrecipSeries",
    "PresentWeather",
    "Theta",
    "ThetaDrops",
    "ThetaFog",
    "ThetaRain",
    "WeatherConditions",
    "conditions_at",
    "default_storm_path",
    "default_storm_record",
    "default_theta",
    "detect_reader",
    "intensity_class",
    "map_conditions",
    "normalised_intensity",
    "parse_time",
    "precip_series",
    "parse_options",
    "read_observations",
    "theta_from_record",
    "theta_from_values",
    "wmo_score",
]


def theta_from_record(
    record: ObservationTable | str | Path | None = None,
    time: str | datetime | None = None,
    window: str | float = "1h",
    agg: str = "max",
    *,
    exposure_s: float | None = None,
    camera: CameraSpec | None = None,
    config: MappingConfig | None = None,
    station: str | None = None,
    align: str = "center",
    reader: str | None = None,
    **reader_options: Any,
) -> Theta:
    """θ for a capture time from a station record (a table, or a file read with ``reader``/``reader_options``).

    ``record=None`` uses the shipped storm excerpt and, without ``time``, its ``DEFAULT_CAPTURE_TIME``.
    ``exposure_s`` overrides the camera's exposure time (s).
    """
    if record is None:
        table = default_storm_record()
        time = DEFAULT_CAPTURE_TIME if time is None else time
    elif isinstance(record, ObservationTable):
        table = record
    else:
        table = read_observations(record, reader, **reader_options)
    if time is None:
        raise ConfigError("theta_from_record needs the capture time (e.g. '2013-08-11T07:40Z')")
    camera = camera or CameraSpec()
    if exposure_s is not None:
        camera = dataclasses.replace(camera, exposure_s=exposure_s)
    conditions = conditions_at(table, time, window, agg, align=align, station=station)
    return map_conditions(conditions, camera, config)


def default_theta(camera: CameraSpec | None = None, config: MappingConfig | None = None) -> Theta:
    """θ of the shipped storm at its default capture time (1-h window, max): what ``metegs-full`` uses with no files."""
    return theta_from_record(None, None, "1h", "max", camera=camera, config=config)
