"""The real storm excerpt shipped with metegs (Beijing, 11 August 2013) and its default capture time."""

from __future__ import annotations

from datetime import datetime, timezone
from importlib import resources
from pathlib import Path
from typing import Any

from metegs.meteo.observations import ObservationTable

STORM_FILE = "beijing_aotizhongxin_2013-08-11.csv"
"""File name of the excerpt inside ``metegs/meteo/data`` (attribution in ``data/README.txt``)."""

PRSA_COLUMNS = ("year", "month", "day", "hour", "RAIN", "wd", "WSPM", "station")
"""Header columns of the UCI Beijing PRSA files: a csv with all of them is read with ``STORM_READER_OPTIONS``."""

STORM_READER_OPTIONS: dict[str, Any] = {
    "time_columns": ("year", "month", "day", "hour"),
    "timezone": "Asia/Shanghai",
    "precip_column": "RAIN",
    "precip_unit": "mm",
    "precip_kind": "accumulation",
    "precip_period": "1h",
    "wind_speed_column": "WSPM",
    "wind_dir_column": "wd",
    "station_column": "station",
}
"""Options of the ``csv`` reader for the UCI Beijing PRSA files (options only, no special code)."""

DEFAULT_CAPTURE_TIME = datetime(2013, 8, 11, 7, 40, tzinfo=timezone.utc)
"""15:40 Beijing time: with a 1-h window the hour of 6.8 mm/h (moderate rain) right after the 72.5 mm/h burst."""


def default_storm_path() -> Path:
    """Path of the shipped excerpt."""
    return Path(str(resources.files("metegs.meteo") / "data" / STORM_FILE))


def default_storm_record() -> ObservationTable:
    """The shipped storm excerpt as an ObservationTable (28 hourly records of one station)."""
    from metegs.meteo.readers import read_observations

    return read_observations(default_storm_path(), reader="csv", **STORM_READER_OPTIONS)
