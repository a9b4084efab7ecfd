"""Any delimited table of station records: columns detected from the header, or named by options.

Without column options the reader finds the time, precipitation, visibility, wind, weather and station
columns itself from a table of common names (`detect_columns`, the same function for every command);
options that are given always win. Example with every option spelled out, the UCI Beijing PRSA files (hourly ``RAIN`` in mm, local Beijing time)::

    read_observations("PRSA_Data_Aotizhongxin_20130301-20170228.csv", reader="csv",
                      time_columns=("year", "month", "day", "hour"), timezone="Asia/Shanghai",
                      precip_column="RAIN", precip_period="1h", wind_speed_column="WSPM",
                      wind_dir_column="wd", station_column="station")
"""

from __future__ import annotations

import csv
import dataclasses
import io
import math
import re
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import datetime, timedelta, timezone
from pathlib import Path
from typing import Any, Literal

from metegs.errors import ConfigError, DataError
from metegs.meteo import units
from metegs.meteo.observations import Accumulation, Observation, resolve_timezone
from metegs.meteo.readers.base import (
    CommonOptions,
    ObservationReader,
    Problems,
    RecordError,
    check_precip,
    decode_text,
    finite_number,
    read_text,
)
from metegs.meteo.storm import PRSA_COLUMNS, STORM_READER_OPTIONS
from metegs.meteo.weather_codes import parse_weather_token


@dataclass
class CsvOptions(CommonOptions):
    """How to read a table: which columns hold what, in which units and time zone."""

    time_columns: tuple[str, ...] = ("time",)
    """One column with a date-time, two (a date and a time of day), or 3-5 integer columns year, month, day[, hour[, minute]]; not given: detected."""
    time_format: str | None = None
    """``strptime`` format of the time column(s) (several columns are joined with one space); None: ISO 8601, else ``dateutil``."""
    dayfirst: bool = False
    """For dates read without ``time_format``: ``01/02/2024`` is 1 February (True) or 2 January (False)."""
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
    missing: tuple[str, ...] = ("", "NA", "N/A", "M", "999999", "-9999")
    """Cell values that mean "not reported" (``M``: IEM's marker). A precipitation of ``T`` (trace) reads as 0."""
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

    def read(self, path: str | Path, **options: Any):
        path = Path(path)
        if path.is_file():  # missing files: the base class says so
            options, self._detect_notes = _with_detected(path, options)
        return super().read(path, **options)

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
        if len(opts.time_columns) not in (1, 2, 3, 4, 5):
            raise DataError(
                path,
                "time_columns must name 1 column (a date-time), 2 (a date and a time of day) "
                "or 3-5 (year, month, day[, hour[, minute]])",
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
        dates_only = True  # every time is a date without a time of day: a daily record
        for row in rows:
            line = reader.line_num
            if not row or all(not c.strip() for c in row):
                continue
            total += 1
            if len(row) < len(header):
                problems.skip(line, None, f"{len(row)} fields, the header has {len(header)}")
                continue
            try:
                time_fields = [row[i].strip() for i in time_idx]
                time_utc = _parse_time(time_fields, opts, tz)
                dates_only = dates_only and _date_only(time_fields, opts)
                raw_precip = cell(row, opts.precip_column)
                precip = None
                if raw_precip is not None and raw_precip.upper() == "T":  # trace: less than the gauge resolves
                    precip = 0.0
                elif raw_precip is not None:
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
        notes = list(getattr(self, "_detect_notes", []))
        if dates_only and parsed and opts.precip_column is not None and opts.precip_period is None:
            opts = dataclasses.replace(opts, precip_period="24h")
            notes.append("a daily record (dates without times): precipitation taken as 24-h totals")
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


# ---- column detection --------------------------------------------------------------------------------------------
# Header names are compared after `_key`: lower case, every run of other characters than a-z/0-9 as one "_"
# ("Rain (mm)" -> "rain_mm", "Wind Speed [km/h]" -> "wind_speed_km_h").

TIME_NAMES = (
    "time", "date", "datetime", "date_time", "timestamp", "valid", "valid_time", "obs_time",
    "observation_time", "time_utc", "datetime_utc", "date_utc", "utc_time",
)  # fmt: skip
"""One column holding a date-time (or a date: a daily record). ``date`` + ``time`` together: a date and a time of day."""
SPLIT_TIME_NAMES = ("year", "month", "day", "hour", "minute")
"""Integer columns year, month, day[, hour[, minute]] (as in the UCI Beijing PRSA files)."""

ROLE_NAMES: dict[str, tuple[str | None, tuple[str, ...], dict[str, str]]] = {
    "precip_column": (
        "precip_unit",
        ("precip", "precipitation", "prcp", "rain", "rainfall", "precip_1h", "rain_1h", "precipitation_amount"),
        {"p01m": "mm", "p01i": "in"},
    ),
    "visibility_column": ("visibility_unit", ("vis", "visibility", "visib"), {"vsby": "mi"}),
    "wind_speed_column": (
        "wind_speed_unit",
        ("wspd", "wind_speed", "windspeed", "wind_spd", "ws", "wspm"),
        {"sknt": "kt", "wind_ms": "m/s", "wind_kt": "kt", "wind_kmh": "km/h", "wind_mph": "mph"},
    ),
    "wind_gust_column": (None, ("gust", "wind_gust", "gust_speed", "wgst"), {}),
    "wind_dir_column": (None, ("drct", "wd", "wind_dir", "wind_direction", "winddir", "wdir"), {}),
    "weather_column": (None, ("wxcodes", "weather", "present_weather", "wx"), {}),
    "station_column": (None, ("station", "station_id", "stn", "site", "site_id", "icao"), {}),
}
"""Per column option: its unit option, known names (unit not stated: the option's default, mm, m, m/s), and
names that state their unit (IEM ASOS: ``p01i`` inches, ``vsby`` statute miles, ``sknt`` knots). A known name
followed by a unit (``precip_in``, ``rain_mm``, ``visibility_km``, ``wind_speed_kt``) takes that unit."""

UNIT_SUFFIXES: dict[str, dict[str, str]] = {
    "precip_unit": {"mm": "mm", "cm": "cm", "in": "in", "inch": "in", "inches": "in"},
    "visibility_unit": {"m": "m", "km": "km", "mi": "mi", "miles": "mi", "sm": "mi", "ft": "ft"},
    "wind_speed_unit": {
        "ms": "m/s", "m_s": "m/s", "mps": "m/s", "kt": "kt", "kts": "kt", "knots": "kt",
        "kmh": "km/h", "km_h": "km/h", "kph": "km/h", "mph": "mph",
    },
}  # fmt: skip
"""Unit suffixes a known name may carry, per unit option."""

DATA_COLUMNS = ("precip_column", "visibility_column", "wind_speed_column", "weather_column")
"""At least one of these must be found or given."""

KNOWN_LAYOUTS: tuple[tuple[tuple[str, ...], dict[str, Any], str], ...] = (
    (PRSA_COLUMNS, STORM_READER_OPTIONS, "UCI Beijing PRSA layout (local Beijing time, hourly RAIN in mm)"),
)
"""Headers recognised as a whole (all their columns present): the options that names alone cannot tell (time zone)."""


def _key(name: str) -> str:
    return re.sub(r"[^0-9a-z]+", "_", name.strip().lower()).strip("_")


def _match(role: str, key: str) -> tuple[bool, str | None]:
    """(the header key fits ``role``, the unit its name states or None)."""
    unit_option, names, with_unit = ROLE_NAMES[role]
    if key in with_unit:
        return True, with_unit[key]
    if key in names:
        return True, None
    for suffix, unit in UNIT_SUFFIXES.get(unit_option, {}).items():
        if key.endswith("_" + suffix) and key[: -len(suffix) - 1] in names:
            return True, unit
    return False, None


def detect_columns(
    header: list[str], given: dict[str, Any], source: str | Path = ""
) -> tuple[dict[str, Any], list[str]]:
    """Reader options for the roles ``given`` leaves open, found from the ``header`` names; and notes saying what was found.

    Given options always win (``visibility_column=None`` turns a column off). No time column, no data
    column, or two candidates for one role: one DataError listing the columns and the ``--set`` option to give.
    """
    keys = {_key(h): h for h in reversed(header)}  # first column wins for duplicate keys
    found: dict[str, Any] = {}
    notes: list[str] = []
    problems: list[str] = []
    for columns, options, what in KNOWN_LAYOUTS:
        if all(c in header for c in columns):
            found.update({k: v for k, v in options.items() if k not in given})
            notes.append(f"recognised the {what}")
    if "time_columns" not in given and "time_columns" not in found:
        single = [h for h in header if _key(h) in TIME_NAMES]
        split = []
        for k in SPLIT_TIME_NAMES:  # year, month, day, then hour and minute if present in that order
            if k not in keys:
                break
            split.append(keys[k])
        split = split if len(split) >= 3 else []
        dated = {_key(h): h for h in single}
        if len(single) == 2 and set(dated) == {"date", "time"}:
            found["time_columns"] = (dated["date"], dated["time"])
        elif len(single) == 1 and not split:
            found["time_columns"] = (single[0],)
        elif split and not single:
            found["time_columns"] = tuple(split)
        elif not single and not split:
            problems.append(
                "no time column found (known names: " + ", ".join(TIME_NAMES) + ", or year,month,day[,hour]): "
                "give it with --set time_columns=NAME (or time_columns=YEAR,MONTH,DAY,HOUR)"
            )
        else:
            both = single + ([",".join(split)] if split else [])
            problems.append(
                f"{len(both)} candidates for the time ({'; '.join(both)}): choose with --set time_columns=NAME"
            )
    for role, (unit_option, _, _) in ROLE_NAMES.items():
        if role in given or role in found:
            if unit_option and unit_option not in given and unit_option not in found and given.get(role):
                ok, unit = _match(role, _key(str(given[role])))
                if ok and unit:  # a named column whose name states its unit
                    found[unit_option] = unit
            continue
        hits = [(h, unit) for h in header for ok, unit in [_match(role, _key(h))] if ok]
        if len(hits) > 1:
            problems.append(
                f"{len(hits)} candidates for {role} ({', '.join(h for h, _ in hits)}): "
                f"choose with --set {role}=NAME (or {role}=none)"
            )
        elif hits:
            column, unit = hits[0]
            found[role] = column
            if unit_option and unit_option not in given:
                if unit is not None:
                    found[unit_option] = unit
                unit_text = found.get(unit_option) or f"{_DEFAULT_UNITS[unit_option]}, assumed"
                notes.append(f"{role}={column} ({unit_text})")
            else:
                notes.append(f"{role}={column}")
    ambiguous = any(f"candidates for {role}" in p for p in problems for role in DATA_COLUMNS)
    if not ambiguous and not any({**given, **found}.get(role) for role in DATA_COLUMNS):
        problems.append(
            "no precipitation, visibility, wind-speed or weather column found: give one with --set "
            "precip_column=NAME (or visibility_column, wind_speed_column, weather_column)"
        )
    if problems:
        raise DataError(
            source,
            "cannot tell which columns to read: " + "; ".join(problems) + f" (columns: {', '.join(header)}; "
            "in Python the same options are keyword arguments of read_observations)",
        )
    if "time_columns" in found and "time_columns" not in given:
        notes.insert(0, f"time_columns={','.join(found['time_columns'])}")
    if notes:
        notes = ["columns detected from the header: " + "; ".join(notes)]
    if found and "timezone" not in given and "timezone" not in found:
        notes.append("times without an offset taken as UTC (set timezone=... otherwise)")
    return found, notes


_DEFAULT_UNITS = {"precip_unit": "mm", "visibility_unit": "m", "wind_speed_unit": "m/s"}


def read_header(path: Path, delimiter: str | None = None) -> list[str]:
    """The header names of the table ``path`` (first line; ``delimiter`` None: sniffed)."""
    text = decode_text(path, path.read_bytes()[:65536], errors="replace")
    first = text.split("\n", 1)[0]
    return [h.strip() for h in next(csv.reader([first], delimiter=delimiter or _sniff_delimiter(first)), [])]


def _with_detected(path: Path, options: dict[str, Any]) -> tuple[dict[str, Any], list[str]]:
    header = read_header(path, options.get("delimiter") or None)
    found, notes = detect_columns(header, options, path)
    return {**found, **options}, notes


def csv_options(path: str | Path, options: dict[str, Any] | None = None) -> dict[str, Any]:
    """The csv reader's options for ``path``: ``options`` plus the columns detected from its header (see `detect_columns`).

    Every command reads a csv through this (``read_observations`` calls it); ``metegs-train``/``metegs-synth``
    record its result in weather.json.
    """
    return _with_detected(Path(path), dict(options or {}))[0]


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
        elif len(fields) <= 2:
            t = _parse_datetime(" ".join(fields), opts.dayfirst)
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


def _parse_datetime(text: str, dayfirst: bool) -> datetime:
    """ISO 8601 (``Z`` allowed), else whatever ``dateutil`` reads (``2012/01/01``, ``01.02.2024 13:00``)."""
    iso = text[:-1] + "+00:00" if text.endswith(("Z", "z")) else text
    try:
        return datetime.fromisoformat(iso)
    except ValueError:
        pass
    from dateutil import parser

    if not any(ch.isdigit() for ch in text):
        raise ValueError("no digits")
    # fields the text lacks come from 2000-01-01 00:00, never from today's date
    return parser.parse(text, dayfirst=dayfirst, default=datetime(2000, 1, 1))


def _date_only(fields: list[str], opts: CsvOptions) -> bool:
    """True if the time fields hold a date without a time of day (a daily record)."""
    if len(fields) != 1:
        return len(fields) == 3  # year, month, day
    if opts.time_format is not None:
        return not any(c in opts.time_format for c in "HIMSp")
    return ":" not in fields[0] and sum(c.isdigit() for c in fields[0]) <= 8


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
