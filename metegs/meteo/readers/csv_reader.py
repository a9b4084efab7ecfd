"""Any delimited table of station records, described by options alone (no per-dataset code).

Example, the UCI Beijing PRSA files (hourly ``RAIN`` in mm, local Beijing time)::

    read_observations("PRSA_Data_Aotizhongxin_20130301-20170228.csv", reader="csv",
                      time_columns=("year", "month", "day", "hour"), timezone="Asia/Shanghai",
                      precip_column="RAIN", precip_period="1h", wind_speed_column="WSPM",
                      wind_dir_column="wd", station_column="station")
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import datetime, timedelta, timezone
from pathlib import Path
from typing import Literal

from metegs.errors import ConfigError, DataError
from metegs.meteo import units
from metegs.meteo.observations import Accumulation, Observation
from metegs.meteo.readers.base import (
    CommonOptions,
    ObservationReader,
    Problems,
    RecordError,
    check_precip,
    finite_number,
    read_text,
    resolve_timezone,
)
from metegs.meteo.weather_codes import parse_weather_token


@dataclass
class CsvOptions(CommonOptions):
    """How to read a table: which columns hold what, in which units and time zone."""

    time_columns: tuple[str, ...] = ("time",)
    """One column with a date-time (ISO 8601 unless ``time_format``), or 3-5 integer columns year, month, day[, hour[, minute]]."""
    time_format: str | None = None
    """``strptime`` format of the time column(s) (several columns are joined with one space)."""
    timezone: str = "UTC"
    """Time zone of times without an offset: ``UTC``, ``UTC+8`` or an IANA name such as ``Asia/Shanghai``."""
    precip_column: str | None = None
    """Column with precipitation (None: the table has none)."""
    precip_unit: str = "mm"
    """Unit of the precipitation column: ``mm``, ``cm`` or ``in`` (per hour for rates)."""
    precip_kind: Literal["accumulation", "rate", "running"] = "accumulation"
    """``accumulation``: amount over the period ending at the row time; ``rate``: per hour; ``running``: total since a reset."""
    precip_period: str | None = None
    """Period of an accumulation or averaging period of a rate, e.g. ``1h``; None: the median time step."""
    precip_reset_hour_utc: int | None = None
    """For ``running`` totals: the UTC hour at which the total restarts (0 for ERA5-Land); None: never."""
    visibility_column: str | None = None
    """Column with visibility."""
    visibility_unit: str = "m"
    """Unit of visibility: ``m``, ``km``, ``mi`` (statute), ``ft``."""
    wind_speed_column: str | None = None
    """Column with the mean wind speed (10 m)."""
    wind_speed_unit: str = "m/s"
    """Unit of wind speeds: ``m/s``, ``kt``, ``km/h``, ``mph``."""
    wind_gust_column: str | None = None
    """Column with gust speed (same unit as the wind speed)."""
    wind_dir_column: str | None = None
    """Column with the direction the wind blows from: degrees, or compass points (``NNE``); ``VRB``/``C`` for none."""
    weather_column: str | None = None
    """Column with METAR-style present-weather groups separated by spaces (``-RA BR``)."""
    station_column: str | None = None
    """Column with a station identifier."""
    missing: tuple[str, ...] = ("", "NA", "N/A", "999999", "-9999")
    """Cell values that mean "not reported"."""
    delimiter: str | None = None
    """Field separator; None: sniffed from the header (``,`` ``;`` tab ``|``)."""


class CsvReader(ObservationReader):
    """Delimited text tables (CSV, TSV, PSV), configured by options."""

    name = "csv"
    priority = 90
    Options = CsvOptions

    @classmethod
    def can_read(cls, path: Path, head: str) -> bool:
        return path.suffix.lower() in (".csv", ".tsv", ".tab")

    def _read(self, path: Path, opts: CsvOptions, problems: Problems):
        try:
            precip_factor = units.to_mm(1.0, opts.precip_unit.removesuffix("/h").removesuffix("/hr"))
            vis_factor = units.to_m(1.0, opts.visibility_unit)
            wind_factor = units.to_m_per_s(1.0, opts.wind_speed_unit)
            tz = resolve_timezone(opts.timezone)
        except ConfigError as exc:
            raise DataError(path, f"option error: {exc}") from exc
        text = read_text(path)
        delimiter = opts.delimiter or _sniff_delimiter(text.split("\n", 1)[0])
        reader = csv.reader(io.StringIO(text), delimiter=delimiter)
        rows = _rows(reader, problems)
        header = [h.strip() for h in next(rows, [])]
        index = {h: i for i, h in enumerate(header)}
        wanted = {
            "time_columns": list(opts.time_columns),
            "precip_column": [opts.precip_column],
            "visibility_column": [opts.visibility_column],
            "wind_speed_column": [opts.wind_speed_column],
            "wind_gust_column": [opts.wind_gust_column],
            "wind_dir_column": [opts.wind_dir_column],
            "weather_column": [opts.weather_column],
            "station_column": [opts.station_column],
        }
        for option, cols in wanted.items():
            for col in cols:
                if col is not None and col not in index:
                    raise DataError(
                        path, f"line 1: option {option}={col!r} names no column; columns: {', '.join(header)}"
                    )
        if not any(
            c is not None
            for c in (opts.precip_column, opts.visibility_column, opts.wind_speed_column, opts.weather_column)
        ):
            raise DataError(
                path,
                "the csv reader needs to know which columns to read: give at least one of precip_column, "
                f"visibility_column, wind_speed_column, weather_column (columns: {', '.join(header)})",
            )
        if len(opts.time_columns) not in (1, 3, 4, 5):
            raise DataError(
                path, "time_columns must name 1 column (a date-time) or 3-5 (year, month, day[, hour[, minute]])"
            )
        missing = set(opts.missing)
        time_idx = [index[c] for c in opts.time_columns]

        def cell(row: list[str], col: str | None) -> str | None:
            if col is None:
                return None
            value = row[index[col]].strip()
            return None if value in missing else value

        parsed: list[tuple[Observation, float | None]] = []
        total = 0
        for row in rows:
            line = reader.line_num
            if not row or all(not c.strip() for c in row):
                continue
            total += 1
            if len(row) < len(header):
                problems.skip(line, None, f"{len(row)} fields, the header has {len(header)}")
                continue
            try:
                time_utc = _parse_time([row[i].strip() for i in time_idx], opts, tz)
                raw_precip = cell(row, opts.precip_column)
                precip = None
                if raw_precip is not None:
                    precip = check_precip(
                        finite_number(raw_precip, opts.precip_column) * precip_factor, opts.precip_column
                    )
                vis = cell(row, opts.visibility_column)
                visibility = None
                if vis is not None:
                    visibility = finite_number(vis, opts.visibility_column, allow_negative=False) * vis_factor
                speed = cell(row, opts.wind_speed_column)
                wind = (
                    None
                    if speed is None
                    else finite_number(speed, opts.wind_speed_column, allow_negative=False) * wind_factor
                )
                gust_text = cell(row, opts.wind_gust_column)
                gust = (
                    None
                    if gust_text is None
                    else finite_number(gust_text, opts.wind_gust_column, allow_negative=False) * wind_factor
                )
                direction = _direction(cell(row, opts.wind_dir_column), opts.wind_dir_column)
                weather = None
                wx_text = cell(row, opts.weather_column)
                if opts.weather_column is not None:
                    weather = tuple(
                        w for w in (parse_weather_token(t) for t in (wx_text or "").split()) if w is not None
                    )
                station = cell(row, opts.station_column) or ""
            except RecordError as exc:
                problems.fail(line, exc.field, exc.message)
                continue
            fields = {
                "time_utc": time_utc,
                "station": station,
                "visibility_m": visibility,
                "wind_speed_m_per_s": wind,
                "wind_gust_m_per_s": gust,
                "wind_dir_deg_from": direction,
                "weather": weather,
                "report_type": "table",
                "line": line,
            }
            parsed.append((fields, precip))
        notes = []
        records = self._attach_precip(parsed, opts, path, problems, notes)
        return records, total, notes

    def _attach_precip(
        self, parsed, opts: CsvOptions, path: Path, problems: Problems, notes: list[str]
    ) -> list[Observation]:
        if opts.precip_column is None or not parsed:
            return [Observation(**fields) for fields, _ in parsed]
        if opts.precip_period is not None:
            period_h = units.parse_duration_s(opts.precip_period) / 3600.0
            if period_h <= 0:
                raise DataError(path, f"option precip_period={opts.precip_period!r} must be longer than zero")
        else:
            period_h = _median_step_h([(f["station"], f["time_utc"]) for f, _ in parsed])
            if period_h is None:
                raise DataError(
                    path, "cannot infer the precipitation period from one record; give precip_period (e.g. 1h)"
                )
            notes.append(f"precipitation period taken as the median time step, {period_h:g} h")
        col = opts.precip_column
        if opts.precip_kind == "rate":
            return [
                Observation(**f)
                if p is None
                else Observation(**f, precip_rate_mm_per_h=p, precip_rate_period_h=period_h)
                for f, p in parsed
            ]
        if opts.precip_kind == "accumulation":
            return [
                Observation(**f)
                if p is None
                else Observation(**f, precip_accums=(Accumulation(p, period_h, label=col),))
                for f, p in parsed
            ]
        from metegs.meteo.rates import deaccumulate

        out = []
        by_station: dict[str, list[tuple[dict, float | None]]] = {}
        for f, p in parsed:
            by_station.setdefault(f["station"], []).append((f, p))
        for items in by_station.values():
            items.sort(key=lambda it: it[0]["time_utc"])
            known = [(f, p) for f, p in items if p is not None]
            steps = deaccumulate(
                [f["time_utc"].timestamp() for f, _ in known],
                [p for _, p in known],
                reset_hour_utc=opts.precip_reset_hour_utc,
            )
            amounts = {id(f): step for (f, _), step in zip(known, steps)}
            for f, _ in items:
                step = amounts.get(id(f))
                if isinstance(step, str):
                    problems.fail(f["line"], col, step)
                    continue
                if step is None:
                    out.append(Observation(**f))
                else:
                    out.append(
                        Observation(
                            **f, precip_accums=(Accumulation(step[0], step[1], label=f"{col} (de-accumulated)"),)
                        )
                    )
        return out


def _rows(reader, problems: Problems) -> Iterator[list[str]]:
    """The rows of ``reader``; a line the csv module cannot split (a stray CR or NUL inside it) is bad input."""
    while True:
        try:
            yield next(reader)
        except StopIteration:
            return
        except csv.Error as exc:
            why = "a stray carriage return (CR) inside the line" if "new-line" in str(exc) else str(exc)
            problems.fail(reader.line_num, None, why)


def _sniff_delimiter(header: str) -> str:
    counts = {d: header.count(d) for d in (",", ";", "\t", "|")}
    best = max(counts, key=counts.get)
    return best if counts[best] else ","


def _parse_time(fields: list[str], opts: CsvOptions, tz) -> datetime:
    where = "+".join(opts.time_columns)
    if any(f == "" for f in fields):
        raise RecordError(where, "time is empty")
    try:
        if opts.time_format:
            t = datetime.strptime(" ".join(fields), opts.time_format)
        elif len(fields) == 1:
            text = fields[0]
            if text.endswith(("Z", "z")):
                text = text[:-1] + "+00:00"
            t = datetime.fromisoformat(text)
        else:
            parts = [int(float(f)) for f in fields]
            day_offset = 0
            if len(parts) >= 4 and parts[3] == 24:  # 24:00 is midnight at the end of the day
                parts[3], day_offset = 0, 1
            t = datetime(*parts) + timedelta(days=day_offset)
    except (ValueError, OverflowError) as exc:
        raise RecordError(where, f"cannot read time {' '.join(fields)!r}: {exc}") from None
    if t.tzinfo is None:
        t = t.replace(tzinfo=tz)
    return t.astimezone(timezone.utc)


def _direction(text: str | None, field: str | None) -> float | None:
    if text is None:
        return None
    key = text.strip().upper()
    if key in ("VRB", "V", "C", "CALM", "CLM"):
        return None
    try:
        value = float(key)
    except ValueError:
        try:
            value = units.compass_to_deg(key)
        except ConfigError as exc:
            raise RecordError(field or "wind_dir", str(exc)) from None
        return None if math.isnan(value) else value
    if not math.isfinite(value) or not 0 <= value <= 360:
        raise RecordError(field or "wind_dir", f"wind direction {text!r} is not within 0-360 degrees")
    return value % 360.0


def _median_step_h(items: list[tuple[str, datetime]]) -> float | None:
    by_station: dict[str, list[float]] = {}
    for station, t in items:
        by_station.setdefault(station, []).append(t.timestamp())
    steps = []
    for times in by_station.values():
        times.sort()
        steps.extend(b - a for a, b in zip(times, times[1:]) if b > a)
    if not steps:
        return None
    steps.sort()
    return steps[len(steps) // 2] / 3600.0
