"""Open-Meteo JSON (forecast ``/v1/forecast`` or archive ``/v1/archive``), hourly variables.

Reads ``hourly.time`` (ISO 8601 local to ``utc_offset_seconds``, or ``unixtime``), ``precipitation``
(sum over the *preceding* hour, so an accumulation over the hour ending at the time stamp),
``visibility``, ``wind_speed_10m``, ``wind_gusts_10m``, ``wind_direction_10m`` and ``weather_code``
(WMO table 4677 subset), with the units given in ``hourly_units`` (Open-Meteo docs). ``null`` values are
not reported. The file is read from disk; metegs never downloads.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from datetime import datetime, timedelta, timezone
from pathlib import Path

from metegs.errors import ConfigError, DataError
from metegs.meteo import units
from metegs.meteo.observations import Accumulation, Observation
from metegs.meteo.readers.base import CommonOptions, ObservationReader, Problems, RecordError, check_precip, read_text
from metegs.meteo.weather_codes import weather_from_synop

_UNIT_ALIASES = {"inch": "in", "°": "deg", "mp/h": "mph", "kn": "kt"}


@dataclass
class OpenMeteoOptions(CommonOptions):
    """Options of the Open-Meteo reader."""

    precip_variable: str = "precipitation"
    """Hourly variable with the liquid precipitation: ``precipitation`` (all), or ``rain`` (no showers, no snow)."""


class OpenMeteoReader(ObservationReader):
    """Open-Meteo hourly JSON responses saved to a file."""

    name = "open-meteo"
    priority = 30
    Options = OpenMeteoOptions

    @classmethod
    def can_read(cls, path: Path, head: str) -> bool:
        return path.suffix.lower() == ".json" and '"hourly"' in head

    def _read(self, path: Path, opts: OpenMeteoOptions, problems: Problems):
        try:
            doc = json.loads(read_text(path))
        except json.JSONDecodeError as exc:
            raise DataError(path, f"line {exc.lineno}: not valid JSON ({exc.msg})") from None
        if not isinstance(doc, dict) or not isinstance(doc.get("hourly"), dict):
            raise DataError(path, "expected an Open-Meteo response with an 'hourly' object")
        hourly = doc["hourly"]
        units_of = doc.get("hourly_units", {}) or {}
        if not isinstance(units_of, dict):
            raise DataError(path, "field 'hourly_units': expected an object of unit names")
        times = hourly.get("time")
        if not isinstance(times, list):
            raise DataError(path, "field 'hourly.time': expected a list of times")
        n = len(times)
        for key, values in hourly.items():
            if not isinstance(values, list) or len(values) != n:
                raise DataError(path, f"field 'hourly.{key}': expected a list of {n} values like 'hourly.time'")
        try:
            offset = timedelta(seconds=int(doc.get("utc_offset_seconds", 0) or 0))
        except (TypeError, ValueError, OverflowError):
            raise DataError(
                path, f"field 'utc_offset_seconds': {doc['utc_offset_seconds']!r} is not a number of seconds"
            ) from None
        unix = units_of.get("time") == "unixtime"

        def unit(var: str, default: str) -> str:
            u = str(units_of.get(var, default))
            return _UNIT_ALIASES.get(u, u)

        try:
            p_factor = units.to_mm(1.0, unit(opts.precip_variable, "mm"))
            v_factor = units.to_m(1.0, unit("visibility", "m"))
            w_factor = units.to_m_per_s(1.0, unit("wind_speed_10m", "km/h"))
            g_factor = units.to_m_per_s(1.0, unit("wind_gusts_10m", unit("wind_speed_10m", "km/h")))
        except ConfigError as exc:
            raise DataError(path, f"field 'hourly_units': {exc}") from None
        precip = hourly.get(opts.precip_variable)
        records = []
        for i in range(n):
            where = f"hourly.time[{i}]"
            try:
                if unix:
                    t = datetime.fromtimestamp(float(times[i]), tz=timezone.utc)
                else:
                    t = (datetime.fromisoformat(str(times[i])) - offset).replace(tzinfo=timezone.utc)
                accums = ()
                p = _number(precip, i, opts.precip_variable)
                if p is not None:
                    accums = (
                        Accumulation(
                            check_precip(p * p_factor, f"hourly.{opts.precip_variable}[{i}]"),
                            1.0,
                            label=opts.precip_variable,
                        ),
                    )
                vis = _number(hourly.get("visibility"), i, "visibility")
                speed = _number(hourly.get("wind_speed_10m"), i, "wind_speed_10m")
                gust = _number(hourly.get("wind_gusts_10m"), i, "wind_gusts_10m")
                direction = _number(hourly.get("wind_direction_10m"), i, "wind_direction_10m")
                for name, v in (("visibility", vis), ("wind_speed_10m", speed), ("wind_gusts_10m", gust)):
                    if v is not None and v < 0:
                        raise RecordError(f"hourly.{name}[{i}]", f"negative value {v:g}")
                code = _number(hourly.get("weather_code"), i, "weather_code")
                weather = None
                if code is not None:
                    wx = weather_from_synop(int(code))
                    weather = () if wx is None else (wx,)
            except RecordError as exc:
                problems.fail(None, f"{exc.field} ({times[i]!r})", exc.message)
                continue
            except (ValueError, TypeError, OverflowError) as exc:
                problems.fail(None, where, f"cannot read time {times[i]!r}: {exc}")
                continue
            records.append(
                Observation(
                    time_utc=t,
                    station=f"{doc.get('latitude', '?')},{doc.get('longitude', '?')}",
                    precip_accums=accums,
                    visibility_m=None if vis is None else vis * v_factor,
                    wind_speed_m_per_s=None if speed is None else speed * w_factor,
                    wind_gust_m_per_s=None if gust is None else gust * g_factor,
                    wind_dir_deg_from=None if direction is None else direction % 360.0,
                    weather=weather,
                    report_type="forecast",
                    line=None,
                )
            )
        return records, n, [f"times shifted by utc_offset_seconds={offset.total_seconds():g}"] if offset else []


def _number(values, i: int, name: str) -> float | None:
    if values is None or values[i] is None:
        return None
    try:
        v = float(values[i])
    except (TypeError, ValueError):
        raise RecordError(f"hourly.{name}[{i}]", f"{values[i]!r} is not a number") from None
    if not math.isfinite(v):
        raise RecordError(f"hourly.{name}[{i}]", f"{values[i]!r} is not a finite number")
    return v
