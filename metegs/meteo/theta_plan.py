"""θ for the views of a scene: from a met record at capture time(s), or from explicit numbers.

Several capture times are spread over the views in order, in equal contiguous blocks (view v gets time
``floor(v·T/N)``), as if the views had been taken one after the other through the record's period.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path

from metegs.errors import ConfigError, DataError, MetegsError
from metegs.meteo import (
    DEFAULT_CAPTURE_TIME,
    CameraSpec,
    ObservationTable,
    Theta,
    conditions_at,
    default_storm_path,
    default_storm_record,
    map_conditions,
    parse_time,
    read_observations,
    theta_from_values,
)
from metegs.meteo.aggregate import FOG_LIMIT_M, MIST_LIMIT_M
from metegs.meteo.readers import detect_reader
from metegs.meteo.readers.csv_reader import csv_options
from metegs.meteo.storm import STORM_READER_OPTIONS


def load_record(path: Path | None, reader: str | None = None, options: dict[str, str] | None = None):
    """(table, reader options used) for ``path`` (None: the shipped storm excerpt).

    The reader is detected from the file unless given; a csv gets the columns detected from its header
    (`metegs.meteo.readers.csv_reader.csv_options`, the same detection as ``metegs-meteo``; a PRSA file the
    storm's options), which are returned so that weather.json records them.
    """
    if path is None:
        return default_storm_record(), dict(STORM_READER_OPTIONS)
    path = Path(path)
    options = dict(options or {})
    if reader in (None, "csv") and path.is_file() and (reader or detect_reader(path)) == "csv":
        reader = "csv"
        options = csv_options(path, options)
    return read_observations(path, reader, **options), options


@dataclass
class ThetaPlan:
    """θ per view and where it came from (for weather.json)."""

    thetas: list[Theta]
    """One θ per view (views sharing a capture time share one object)."""
    times: list[str | None]
    """Capture time (ISO, UTC) per distinct θ, None for explicit values."""
    view_time_index: list[int]
    """Index into ``times``/``distinct`` per view."""
    distinct: list[Theta]
    """The distinct θ, in time order."""
    source: dict
    """The record: file, reader, options, window, agg, or the explicit values."""


def view_blocks(num_views: int, num_times: int) -> list[int]:
    """Time index per view: equal contiguous blocks in view order."""
    return [min(num_times - 1, (v * num_times) // max(num_views, 1)) for v in range(num_views)]


def plan_from_record(
    num_views: int,
    camera: CameraSpec,
    record: Path | None = None,
    times: list[str] | None = None,
    *,
    reader: str | None = None,
    options: dict[str, str] | None = None,
    window: str = "1h",
    agg: str = "max",
    station: str | None = None,
    visibility_m: float | None = None,
) -> ThetaPlan:
    """θ per view from ``record`` (None: the shipped storm) at ``times`` (None: the storm's default time).

    ``visibility_m`` replaces the record's visibility (records such as PRSA have none).
    """
    if not times:
        if record is not None:
            raise ConfigError("--time is needed with --record (e.g. --time 2016-07-20T02:30Z)")
        times = [DEFAULT_CAPTURE_TIME.isoformat()]
    table, used = load_record(record, reader, options)
    distinct, iso = [], []
    for t in times:
        try:
            when = parse_time(t) if isinstance(t, str) else t
        except MetegsError as exc:
            raise ConfigError(f"--time {t!r}: {exc}") from exc
        _check_in_record(table, when, record)
        try:
            conditions = conditions_at(table, when, window, agg, station=station)
        except MetegsError as exc:
            raise DataError(record or default_storm_path(), f"at {when.isoformat()}: {exc}") from exc
        if visibility_m is not None:
            conditions = with_visibility(conditions, visibility_m)
        distinct.append(map_conditions(conditions, camera))
        iso.append(when.isoformat())
    blocks = view_blocks(num_views, len(distinct))
    source = {
        "file": str(Path(record).resolve()) if record is not None else f"{default_storm_path()} (shipped storm)",
        "reader": table.reader,
        "reader_options": {k: list(v) if isinstance(v, tuple) else v for k, v in used.items()},
        "window": window,
        "agg": agg,
        "station": station,
        "visibility_override_m": visibility_m,
    }
    return ThetaPlan([distinct[b] for b in blocks], iso, blocks, distinct, source)


def plan_from_values(
    num_views: int,
    camera: CameraSpec,
    precip_mm_h: float = 0.0,
    visibility_m: float | None = None,
    wind_speed_m_per_s: float = 0.0,
    wind_dir_deg: float | None = None,
) -> ThetaPlan:
    """One θ for every view from explicit numbers."""
    theta = theta_from_values(precip_mm_h, visibility_m, wind_speed_m_per_s, wind_dir_deg, camera=camera)
    source = {
        "values": {
            "precip_mm_h": precip_mm_h,
            "visibility_m": visibility_m,
            "wind_speed_m_per_s": wind_speed_m_per_s,
            "wind_dir_deg_from": wind_dir_deg,
        }
    }
    return ThetaPlan([theta] * num_views, [None], [0] * num_views, [theta], source)


def with_visibility(conditions, visibility_m: float):
    """Conditions with a measured visibility (fog/mist is called for below 5 km, like ``theta_from_values``)."""
    if not (math.isfinite(visibility_m) and visibility_m > 0):
        raise ConfigError(f"--visibility-m must be a positive number, got {visibility_m}")
    fog_active = conditions.fog_active or visibility_m < MIST_LIMIT_M
    kind = conditions.fog_kind
    if fog_active and kind is None:
        kind = "fog" if visibility_m < FOG_LIMIT_M else "mist"
    return dataclasses.replace(
        conditions, visibility_m=visibility_m, visibility_at_least=False, fog_active=fog_active, fog_kind=kind
    )


def _check_in_record(table: ObservationTable, when, record: Path | None) -> None:
    start, end = table.start_utc, table.end_utc
    if start is None or end is None or not len(table):
        raise DataError(record or default_storm_path(), "the record holds no observations")
    if when < start or when > end:
        raise DataError(
            record or default_storm_path(),
            f"capture time {when.isoformat()} is outside the record ({start.isoformat()} .. {end.isoformat()})",
        )
