"""What every observation reader shares: options, bad-record accounting, time zones and time order.

A reader is a class registered in the ``meteo_reader`` registry with ``name``, ``priority``,
``can_read(path, head)`` (a cheap look at the file name and its first few KB) and
``read(path, **options) -> ObservationTable``. Options are a dataclass (``Options``), so unknown or
mistyped options fail with a ConfigError that lists the valid ones.

Bad input: a value that cannot be used raises ``DataError`` naming the file, the line and the field
(``on_error="raise"``, the default), or with ``on_error="skip"`` the record is skipped and counted;
records that are skipped by rule (an unparsable METAR, a duplicate) are always counted. A value beyond the
plausibility bounds of `metegs.meteo.limits` (more rain than ever measured, visibility under 1 m, wind over
120 m/s) is bad input too. Files are decoded by `read_text`: UTF-8, or UTF-16 with a byte-order mark. Each file gives
at most one ``MeteoWarning`` that states how many records were skipped and shows the first reasons.
"""

from __future__ import annotations

import codecs
import dataclasses
import math
import re
import typing
import warnings
from datetime import datetime, timezone, tzinfo
from pathlib import Path
from typing import Any, ClassVar, Literal

from metegs.config import coerce
from metegs.errors import ConfigError, DataError
from metegs.meteo import limits
from metegs.meteo.observations import Observation, ObservationTable, epoch_s


class MeteoWarning(UserWarning):
    """Records of a meteorological file were skipped or changed; the message counts them and says why."""


@dataclasses.dataclass
class CommonOptions:
    """Options every reader accepts."""

    on_error: Literal["raise", "skip"] = "raise"
    """A bad value (negative rain, NaN, unreadable number): raise a DataError naming file, line and field, or skip the record (counted in one warning)."""
    time_order: Literal["strict", "sort"] = "strict"
    """``strict``: a time going backwards (per station) is bad input; ``sort``: sort the records by time."""
    station: str | None = None
    """Keep only this station (for files holding several)."""


class Problems:
    """Counts skipped records of one file and raises or warns about them."""

    def __init__(self, path: Path | str, on_error: str = "raise", max_examples: int = 3):
        self.path = path
        self.on_error = on_error
        self.count = 0
        self.examples: list[str] = []
        self.max_examples = max_examples
        self.ignored = 0
        self.ignored_examples: list[str] = []

    @staticmethod
    def where(line: int | None, field: str | None) -> str:
        parts = []
        if line is not None:
            parts.append(f"line {line}")
        if field:
            parts.append(f"field {field!r}")
        return ", ".join(parts)

    def fail(self, line: int | None, field: str | None, message: str) -> None:
        """A bad value: raise (``on_error="raise"``) or count the record as skipped."""
        if self.on_error == "raise":
            where = self.where(line, field)
            raise DataError(self.path, f"{where}: {message}" if where else message)
        self.skip(line, field, message)

    def skip(self, line: int | None, field: str | None, message: str) -> None:
        """Count a skipped record (always, whatever ``on_error`` says)."""
        self.count += 1
        if len(self.examples) < self.max_examples:
            where = self.where(line, field)
            self.examples.append(f"{where}: {message}" if where else message)

    def ignore_value(self, line: int | None, field: str | None, message: str) -> None:
        """Count one implausible value that is treated as not reported (the record itself is kept)."""
        self.ignored += 1
        if len(self.ignored_examples) < self.max_examples:
            where = self.where(line, field)
            self.ignored_examples.append(f"{where}: {message}" if where else message)

    def warn(self, total: int | None = None, what: str = "records") -> None:
        """One warning for the file if anything was skipped or ignored."""
        parts = []
        if self.count:
            of = f" of {total}" if total is not None else ""
            more = " ..." if self.count > len(self.examples) else ""
            parts.append(f"skipped {self.count}{of} {what} ({'; '.join(self.examples)}{more})")
        if self.ignored:
            more = " ..." if self.ignored > len(self.ignored_examples) else ""
            parts.append(
                f"treated {self.ignored} implausible value(s) as not reported ({'; '.join(self.ignored_examples)}{more})"
            )
        if parts:
            warnings.warn(f"{self.path}: {'; '.join(parts)}", MeteoWarning, stacklevel=4)


class RecordError(Exception):
    """Raised inside a reader for one bad field; the reader turns it into ``Problems.fail``."""

    def __init__(self, field: str, message: str):
        super().__init__(message)
        self.field = field
        self.message = message


def finite_number(text: str, field: str, *, allow_negative: bool = True) -> float:
    """``text`` as a finite float; NaN, infinities, junk and (optionally) negatives raise RecordError."""
    try:
        value = float(text)
    except ValueError:
        raise RecordError(field, f"{text!r} is not a number") from None
    if not math.isfinite(value):
        raise RecordError(
            field,
            f"{text!r} is not a finite number (NaN/inf are not allowed; list it as a missing marker if it means 'missing')",
        )
    if not allow_negative and value < 0:
        raise RecordError(field, f"negative value {value:g} is not physical")
    return value


def check_precip(value_mm: float, field: str) -> float:
    """A precipitation depth or rate: finite and non-negative, else RecordError."""
    if not math.isfinite(value_mm):
        raise RecordError(field, f"precipitation {value_mm!r} is not finite")
    if value_mm < 0:
        raise RecordError(field, f"negative precipitation {value_mm:g} mm")
    return value_mm


def make_options(cls: type, options: dict[str, Any], reader: str) -> Any:
    """Build the reader's option dataclass; unknown names and bad values give a ConfigError listing the valid options."""
    hints = typing.get_type_hints(cls)
    names = [f.name for f in dataclasses.fields(cls)]
    kwargs = {}
    for key, value in options.items():
        if key not in names:
            raise ConfigError(f"reader {reader!r} has no option {key!r}; options: {', '.join(names)}")
        kwargs[key] = coerce(value, hints[key], f"reader {reader!r} option {key!r}", text=True)
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"reader {reader!r}: {exc}") from exc


def order_records(records: list[Observation], problems: Problems, time_order: str) -> list[Observation]:
    """Records sorted by (station, time): backwards times are bad input under ``strict``; exact duplicates are dropped and counted."""
    by_station: dict[str, list[Observation]] = {}
    for r in records:
        by_station.setdefault(r.station, []).append(r)
    out: list[Observation] = []
    for station in by_station:
        recs = by_station[station]
        if time_order == "strict":
            kept = []
            for r in recs:
                if kept and r.time_utc < kept[-1].time_utc:
                    prev = kept[-1]
                    problems.fail(
                        r.line,
                        "time",
                        f"time {r.time_utc:%Y-%m-%d %H:%M}Z goes backwards (line {prev.line} is at "
                        f"{prev.time_utc:%Y-%m-%d %H:%M}Z){' for station ' + station if station else ''}; "
                        "pass time_order='sort' if the file is not in time order",
                    )
                    continue
                kept.append(r)
            recs = kept
        else:
            recs = sorted(recs, key=lambda r: epoch_s(r.time_utc))
        previous: Observation | None = None
        for r in recs:
            if (
                previous is not None
                and r.time_utc == previous.time_utc
                and dataclasses.replace(r, line=None) == dataclasses.replace(previous, line=None)
            ):
                problems.skip(r.line, None, f"duplicate of line {previous.line}")
                continue
            out.append(r)
            previous = r
    return out


_MAGIC = {
    b"\x89PNG": "a PNG image",
    b"\xff\xd8\xff": "a JPEG image",
    b"GIF8": "a GIF image",
    b"%PDF": "a PDF document",
    b"PK\x03\x04": "a ZIP archive (an .xlsx workbook is one: export the sheet as CSV)",
    b"\x1f\x8b": "gzip-compressed (decompress it first)",
}
_TEXT_CONTROLS = frozenset(b"\t\n\r\x0b\x0c\x01\x03")  # SOH/ETX frame WMO bulletins


def decode_text(path: Path, data: bytes, errors: str = "strict") -> str:
    """``data`` as LF-ended text (UTF-8, or UTF-8/16 with a byte-order mark); DataError if empty, binary or not UTF-8."""
    if not data.strip():
        raise DataError(path, "file is empty")
    for bom, codec, name in (
        (codecs.BOM_UTF8, "utf-8-sig", "UTF-8"),
        (codecs.BOM_UTF16_LE, "utf-16", "UTF-16"),
        (codecs.BOM_UTF16_BE, "utf-16", "UTF-16"),
    ):
        if data.startswith(bom):
            try:
                return _unix_newlines(data.decode(codec, errors))
            except UnicodeDecodeError as exc:
                raise DataError(
                    path, f"starts with a {name} byte-order mark but byte {exc.start} is not {name}"
                ) from None
    for magic, what in _MAGIC.items():
        if data.startswith(magic):
            raise DataError(path, f"is {what}, not a text record")
    head = data[:8192]
    if max(head[0::2].count(0), head[1::2].count(0)) > len(head) // 4:
        raise DataError(path, "looks like UTF-16 text without a byte-order mark: save it as UTF-8")
    if sum(b < 32 and b not in _TEXT_CONTROLS or b == 127 for b in head) > 0.05 * len(head):
        raise DataError(path, "is a binary file, not a text record")
    try:
        return _unix_newlines(data.decode("utf-8", errors))
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        raise DataError(
            path,
            f"line {line}: byte 0x{data[exc.start]:02x} is not UTF-8 text: save the file as UTF-8 "
            "(it may be Latin-1 / Windows-1252)",
        ) from None


def _unix_newlines(text: str) -> str:
    """CRLF (and CR CR LF) line ends as LF; a file with CR line ends only (classic Mac) too. A CR inside a line stays."""
    text = re.sub(r"\r+\n", "\n", text)
    return text.replace("\r", "\n") if "\n" not in text else text


def read_text(path: Path, errors: str = "strict") -> str:
    """The file as text (see `decode_text`); a DataError if it is missing, unreadable, empty or not text."""
    if not path.exists():
        raise DataError(path, "file does not exist")
    if not path.is_file():
        raise DataError(path, "is not a file")
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise DataError(path, f"cannot read: {exc}") from exc
    return decode_text(path, data, errors)


def implausible(r: Observation) -> RecordError | None:
    """The first value of ``r`` beyond the bounds of `metegs.meteo.limits` as a RecordError, or None."""
    for acc in r.precip_accums:
        most = limits.max_precip_rate_mm_h(acc.period_h) * acc.period_h
        if acc.period_h > 0 and acc.amount_mm > most:
            return RecordError(
                acc.label or "precipitation",
                f"{acc.amount_mm:g} mm in {acc.period_h:g} h is more rain than ever measured (at most {most:g} mm); "
                "check the value and its unit",
            )
    rate, period = r.precip_rate_mm_per_h, r.precip_rate_period_h
    if rate is not None and rate > (most := limits.max_precip_rate_mm_h(period)):
        return RecordError(
            "precipitation rate",
            f"{rate:g} mm/h is more rain than ever measured (at most {most:g} mm/h"
            f"{f' over {period:g} h' if period else ''}); check the value and its unit",
        )
    checks = (
        ("visibility", r.visibility_m, limits.MIN_VISIBILITY_M, math.inf, "m"),
        ("wind speed", r.wind_speed_m_per_s, 0.0, limits.MAX_WIND_M_S, "m/s"),
        ("wind gust", r.wind_gust_m_per_s, 0.0, limits.MAX_WIND_M_S, "m/s"),
        ("wind direction", r.wind_dir_deg_from, 0.0, 360.0, "degrees"),
    )
    for field, value, low, high, unit in checks:
        why = None if value is None else limits.range_problem(value, low, high, unit)
        if why:
            return RecordError(field, f"{why} (not a plausible {field}; check the value and its unit)")
    return None


class ObservationReader:
    """Base class of the built-in readers (plugins only need the same four members)."""

    name: ClassVar[str] = ""
    """Registry name."""
    priority: ClassVar[int] = 100
    """Detection order: lower is tried first."""
    Options: ClassVar[type] = CommonOptions
    """The option dataclass of this reader."""

    @classmethod
    def can_read(cls, path: Path, head: str) -> bool:
        """True if ``path`` (whose first few KB are ``head``) looks like this format."""
        return False

    def read(self, path: str | Path, **options: Any) -> ObservationTable:
        """Read ``path`` into an ObservationTable; bad input raises DataError naming file, line and field."""
        opts = make_options(self.Options, options, self.name)
        path = Path(path)
        problems = Problems(path, opts.on_error)
        records, total, notes = self._read(path, opts, problems)
        records = [r for r in records if self._plausible(r, problems)]
        records = order_records(records, problems, opts.time_order)
        if opts.station is not None:
            records = [r for r in records if r.station == opts.station]
            if not records:
                raise DataError(path, f"no records of station {opts.station!r}")
        if not records:
            raise DataError(
                path,
                "holds no records"
                if not total
                else f"none of its {total} records can be used ({'; '.join(problems.examples)})",
            )
        problems.warn(total)
        return ObservationTable(records, str(path), self.name, problems.count, notes)

    @staticmethod
    def _plausible(r: Observation, problems: Problems) -> bool:
        """False (after raising or counting it) for a record with a value beyond `metegs.meteo.limits`."""
        bad = implausible(r)
        if bad is not None:
            when = "" if r.line is not None else f"{r.time_utc:%Y-%m-%d %H:%M}Z: "
            problems.fail(r.line, bad.field, when + bad.message)
        return bad is None

    def _read(self, path: Path, opts: Any, problems: Problems) -> tuple[list[Observation], int, list[str]]:
        """Records (any order), the number of records seen, and notes."""
        raise NotImplementedError


def utc_datetime(
    year: int, month: int, day: int, hour: int = 0, minute: int = 0, tz: tzinfo = timezone.utc
) -> datetime:
    """An aware UTC datetime from local fields in ``tz``; ValueError on impossible dates."""
    return datetime(year, month, day, hour, minute, tzinfo=tz).astimezone(timezone.utc)
