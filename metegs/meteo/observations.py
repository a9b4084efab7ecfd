"""The tidy observation table every reader returns: one record per report, UTC times, units in names."""

from __future__ import annotations

import math
import re
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field, replace
from datetime import datetime, timedelta, timezone, tzinfo

import numpy as np

from metegs.errors import ConfigError, DataError
from metegs.meteo.weather_codes import PresentWeather

UTC = timezone.utc


@dataclass(frozen=True)
class Accumulation:
    """Precipitation that fell over a period ending at the record's time."""

    amount_mm: float
    """Liquid-equivalent depth, mm (0 with ``trace`` for a trace)."""
    period_h: float
    """Length of the period that ends at the record time, hours."""
    trace: bool = False
    """A trace: precipitation fell but too little to measure (METAR ``P0000``, SYNOP 990, ISD condition 2)."""
    label: str = ""
    """Where it came from, e.g. ``P`` (METAR hourly group), ``6`` (3/6-h group), ``AA1``, ``precipitation_6_hour``."""


@dataclass(frozen=True)
class Observation:
    """One report of one station. ``None`` means "not reported", never zero."""

    time_utc: datetime
    """Time of the report, timezone-aware UTC."""
    station: str = ""
    """Station identifier (ICAO, WMO, GHCNh ID or the CSV station column); ``""`` when unknown."""
    precip_rate_mm_per_h: float | None = None
    """Precipitation rate, mm/h, averaged over ``precip_rate_period_h`` ending at ``time_utc``."""
    precip_rate_period_h: float | None = None
    """Averaging period of ``precip_rate_mm_per_h``, hours (ends at ``time_utc``)."""
    precip_accums: tuple[Accumulation, ...] = ()
    """Accumulations reported with this record (e.g. METAR ``P`` and ``6`` groups), each with its period."""
    visibility_m: float | None = None
    """Horizontal (prevailing / MOR) visibility, m."""
    visibility_at_least: bool = False
    """The visibility is a lower bound: ``9999``, ``CAVOK``, ``10SM``, ``P6SM`` or a sensor's maximum."""
    visibility_below: bool = False
    """The visibility is an upper bound: ``M1/4SM``, ``0000`` (< 50 m)."""
    wind_speed_m_per_s: float | None = None
    """Mean wind speed at 10 m, m/s (0 for calm)."""
    wind_gust_m_per_s: float | None = None
    """Gust speed, m/s."""
    wind_dir_deg_from: float | None = None
    """Direction the wind blows from, degrees true; None for calm or variable (``VRB``)."""
    weather: tuple[PresentWeather, ...] | None = None
    """Present-weather groups; ``()`` means reported as none, None means not reported at all."""
    report_type: str = ""
    """``METAR``, ``SPECI``, ``SYNOP``, ``hourly`` (table rows), ``forecast`` ..."""
    line: int | None = None
    """1-based line in the source file where the record starts (for error messages)."""

    @property
    def precip_accum_mm(self) -> float | None:
        """Amount of the shortest accumulation reported (mm), or None."""
        acc = self.shortest_accumulation
        return None if acc is None else acc.amount_mm

    @property
    def precip_period_h(self) -> float | None:
        """Period of the shortest accumulation reported (h), or None."""
        acc = self.shortest_accumulation
        return None if acc is None else acc.period_h

    @property
    def shortest_accumulation(self) -> Accumulation | None:
        return min(self.precip_accums, key=lambda a: a.period_h, default=None)

    def with_(self, **changes) -> Observation:
        """A copy with some fields replaced."""
        return replace(self, **changes)


COLUMNS = (
    "precip_rate_mm_per_h",
    "precip_rate_period_h",
    "precip_accum_mm",
    "precip_period_h",
    "visibility_m",
    "wind_speed_m_per_s",
    "wind_gust_m_per_s",
    "wind_dir_deg_from",
)
"""Numeric columns available through ``ObservationTable.column`` (NaN where not reported)."""


def to_utc(t: datetime) -> datetime:
    """``t`` as aware UTC; naive datetimes are taken to be UTC already."""
    return t.replace(tzinfo=UTC) if t.tzinfo is None else t.astimezone(UTC)


def epoch_s(t: datetime) -> float:
    """Seconds since 1970-01-01 UTC."""
    return to_utc(t).timestamp()


def from_epoch_s(s: float) -> datetime:
    return datetime.fromtimestamp(s, tz=UTC)


_OFFSET = re.compile(r"^(?:UTC|GMT)?\s*([+-])(\d{1,2})(?::?(\d{2}))?$", re.IGNORECASE)


def resolve_timezone(name: str | None) -> tzinfo:
    """A tzinfo for ``UTC``, a fixed offset (``UTC+8``, ``+08:00``, ``-0500``) or an IANA name (``Asia/Shanghai``)."""
    if name is None or name.strip().upper() in ("", "UTC", "Z", "GMT"):
        return timezone.utc
    m = _OFFSET.match(name.strip())
    if m:
        sign = 1 if m.group(1) == "+" else -1
        return timezone(sign * timedelta(hours=int(m.group(2)), minutes=int(m.group(3) or 0)))
    try:
        from zoneinfo import ZoneInfo

        return ZoneInfo(name.strip())
    except Exception as exc:  # noqa: BLE001 - ZoneInfoNotFoundError, ValueError
        raise ConfigError(
            f"unknown time zone {name!r}: use UTC, an offset such as UTC+8, or an IANA name such as Asia/Shanghai"
        ) from exc


def parse_time(text: str | datetime, *, default_tz: str | None = None) -> datetime:
    """An ISO-8601 time (``2013-08-11T07:40Z``, ``2013-08-11 15:40+08:00``) as aware UTC.

    Times without an offset are read in ``default_tz`` (an IANA name or ``UTC+8``), else as UTC.
    """
    if isinstance(text, datetime):
        t = text
    else:
        s = str(text).strip()
        if s.endswith(("Z", "z")):
            s = s[:-1] + "+00:00"
        try:
            t = datetime.fromisoformat(s)
        except ValueError as exc:
            raise DataError(None, f"cannot read time {text!r}: write ISO 8601, e.g. 2013-08-11T07:40Z") from exc
    if t.tzinfo is None and default_tz:
        t = t.replace(tzinfo=resolve_timezone(default_tz))
    return to_utc(t)


@dataclass
class ObservationTable:
    """Records of one file in time order (per station), with where they came from."""

    records: list[Observation]
    """The records, sorted by (station, time)."""
    source: str = ""
    """The file (or description) the records were read from."""
    reader: str = ""
    """Registry name of the reader that produced them."""
    skipped: int = 0
    """How many records the reader skipped (each counted in its warning)."""
    notes: list[str] = field(default_factory=list)
    """Human-readable remarks from the reader (assumptions made, options used)."""

    def __len__(self) -> int:
        return len(self.records)

    def __iter__(self) -> Iterator[Observation]:
        return iter(self.records)

    def __getitem__(self, i: int) -> Observation:
        return self.records[i]

    @property
    def stations(self) -> list[str]:
        """Station identifiers present, in first-seen order."""
        return list(dict.fromkeys(r.station for r in self.records))

    def times_s(self) -> np.ndarray:
        """Record times as seconds since the epoch: [N] float64."""
        return np.array([epoch_s(r.time_utc) for r in self.records], dtype=np.float64)

    def column(self, name: str) -> np.ndarray:
        """One numeric column as [N] float64, NaN where not reported (see ``COLUMNS``)."""
        if name not in COLUMNS:
            raise KeyError(f"unknown column {name!r}; columns: {', '.join(COLUMNS)}")
        out = np.full(len(self.records), np.nan)
        for i, r in enumerate(self.records):
            v = getattr(r, name)
            if v is not None:
                out[i] = v
        return out

    def for_station(self, station: str | None) -> ObservationTable:
        """Only the records of ``station``; ``None`` requires the table to hold a single station."""
        stations = self.stations
        if station is None:
            if len(stations) > 1:
                raise DataError(
                    self.source or None,
                    f"holds {len(stations)} stations ({', '.join(stations[:12])}{' ...' if len(stations) > 12 else ''}); "
                    "choose one with station=...",
                )
            return self
        if station not in stations:
            raise DataError(self.source or None, f"no records of station {station!r}; stations: {', '.join(stations)}")
        return self._subset([r for r in self.records if r.station == station])

    def between(self, start: datetime | None = None, end: datetime | None = None) -> ObservationTable:
        """Records with ``start <= time <= end`` (either bound may be None)."""
        s = -math.inf if start is None else epoch_s(start)
        e = math.inf if end is None else epoch_s(end)
        return self._subset([r for r in self.records if s <= epoch_s(r.time_utc) <= e])

    def _subset(self, records: Sequence[Observation]) -> ObservationTable:
        return ObservationTable(list(records), self.source, self.reader, self.skipped, list(self.notes))

    @property
    def start_utc(self) -> datetime | None:
        return min((r.time_utc for r in self.records), default=None)

    @property
    def end_utc(self) -> datetime | None:
        return max((r.time_utc for r in self.records), default=None)

    def median_step_s(self) -> float | None:
        """Median time between consecutive records of the same station (s), or None with < 2 records."""
        steps: list[float] = []
        for st in self.stations:
            t = np.array([epoch_s(r.time_utc) for r in self.records if r.station == st])
            if t.size > 1:
                steps.extend(np.diff(np.sort(t)).tolist())
        steps = [s for s in steps if s > 0]
        return float(np.median(steps)) if steps else None
