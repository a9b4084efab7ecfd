"""NOAA GHCNh (Global Historical Climatology Network - hourly) pipe-separated ``.psv`` files.

Columns used (GHCNh documentation): ``Station_ID``, ``Year``..``Minute`` (UTC), ``wind_direction``
(degrees or ``VRB``), ``wind_speed`` and ``wind_gust`` (m/s), ``visibility`` (km), ``precipitation``
(mm since the previous routine report: one hour for METAR/SYNOP hourly rows, less for a SPECI),
``precipitation_N_hour`` (mm over N hours) and ``pres_wx_MW1..3`` / ``AU1..3`` / ``AW1..3``
(``CODE:number``). A ``_Measurement_Code`` of ``9-Missing`` means not reported even when the value
reads 0.0; ``2-Trace`` is a trace. Quality codes 2, 3, 6 and 7 (suspect/erroneous, ISD convention)
make the value count as not reported.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from datetime import datetime, timedelta, timezone
from pathlib import Path
from typing import Literal

from metegs.errors import DataError
from metegs.meteo import limits
from metegs.meteo.observations import Accumulation, Observation
from metegs.meteo.readers.base import (
    CommonOptions,
    ObservationReader,
    Problems,
    RecordError,
    check_precip,
    finite_number,
    read_text,
)
from metegs.meteo.weather_codes import PresentWeather, parse_weather_token, weather_from_synop

_BAD_QUALITY = {"2", "3", "6", "7"}
_PERIODS = (3, 6, 9, 12, 15, 18, 21, 24)
_MAX_VISIBILITY_KM = 500.0
_US_VISIBILITY_CAP_KM = 16.09  # 10 statute miles: US METARs report no more


@dataclass
class GhcnhOptions(CommonOptions):
    """Options of the GHCNh reader."""

    time_order: Literal["strict", "sort"] = "sort"
    """GHCNh extracts are not always in time order, so records are sorted by default."""


class GhcnhReader(ObservationReader):
    """NOAA GHCNh hourly ``.psv`` files."""

    name = "ghcnh"
    priority = 10
    Options = GhcnhOptions

    @classmethod
    def can_read(cls, path: Path, head: str) -> bool:
        return head.startswith("Station_ID|") or (path.suffix.lower() == ".psv" and "|Year|" in head[:400])

    def _read(self, path: Path, opts: GhcnhOptions, problems: Problems):
        lines = read_text(path).split("\n")
        if not lines or not lines[0].startswith("Station_ID|"):
            raise DataError(path, "line 1: expected the GHCNh header starting with 'Station_ID|'")
        header = lines[0].split("|")
        index = {h: i for i, h in enumerate(header)}
        for col in ("Year", "Month", "Day", "Hour", "Minute"):
            if col not in index:
                raise DataError(path, f"line 1: no {col!r} column in the GHCNh header")
        rows: list[tuple[int, dict[str, str]]] = []
        total = 0
        for number, text in enumerate(lines[1:], start=2):
            if not text.strip():
                continue
            total += 1
            fields = text.split("|")
            if len(fields) != len(header):
                problems.skip(number, None, f"{len(fields)} fields, the header has {len(header)}")
                continue
            rows.append((number, {h: v.strip() for h, v in zip(header, fields) if v.strip() != ""}))
        routine = self._routine_minutes(rows)
        records = []
        for number, row in rows:
            try:
                records.append(self._observation(number, row, routine, problems))
            except RecordError as exc:
                problems.fail(number, exc.field, exc.message)
        return records, total, []

    @staticmethod
    def _routine_minutes(rows) -> dict[str, int]:
        counts: dict[str, Counter] = {}
        for _, row in rows:
            if row.get("precipitation_Report_Type", row.get("wind_speed_Report_Type", "")) == "FM15-METAR":
                minute = row.get("Minute", "0")
                if minute.isdigit():
                    counts.setdefault(row.get("Station_ID", ""), Counter())[int(minute)] += 1
        return {st: c.most_common(1)[0][0] for st, c in counts.items()}

    def _observation(self, line: int, row: dict[str, str], routine: dict[str, int], problems: Problems) -> Observation:
        try:
            t = datetime(*(int(row[c]) for c in ("Year", "Month", "Day", "Hour", "Minute")), tzinfo=timezone.utc)
        except (KeyError, ValueError) as exc:
            raise RecordError("Year..Minute", f"cannot read the time: {exc}") from None
        station = row.get("Station_ID", "")

        def value(col: str, *, allow_negative: bool = False) -> float | None:
            if col not in row or row.get(f"{col}_Measurement_Code", "").startswith("9-"):
                return None
            if row.get(f"{col}_Quality_Code", "") in _BAD_QUALITY:
                problems.ignore_value(line, col, f"quality code {row[f'{col}_Quality_Code']} (suspect/erroneous)")
                return None
            return finite_number(row[col], col, allow_negative=allow_negative)

        accums = []
        precip = value("precipitation")
        if precip is not None:
            check_precip(precip, "precipitation")
            kind = row.get("precipitation_Report_Type", "")
            period_h = 1.0
            if kind == "FM16-SPECI":
                minute = routine.get(station, 53)
                last = t.replace(minute=minute)
                if last >= t:
                    last -= timedelta(hours=1)
                period_h = (t - last).total_seconds() / 3600.0
            trace = row.get("precipitation_Measurement_Code", "").startswith("2-")
            accums.append(Accumulation(precip, period_h, trace and precip == 0, "precipitation"))
        for hours in _PERIODS:
            col = f"precipitation_{hours}_hour"
            amount = value(col)
            if amount is not None:
                check_precip(amount, col)
                trace = row.get(f"{col}_Measurement_Code", "").startswith("2-")
                accums.append(Accumulation(amount, float(hours), trace and amount == 0, col))
        visibility_m = None
        at_least = below = False
        vis_km = value("visibility")
        if vis_km is not None:
            if vis_km > _MAX_VISIBILITY_KM:
                problems.ignore_value(line, "visibility", f"{vis_km:g} km is beyond {_MAX_VISIBILITY_KM:g} km")
            elif vis_km == 0:  # below the smallest reportable value
                visibility_m, below = limits.ZERO_VISIBILITY_M, True
            else:
                visibility_m = vis_km * 1000.0
                report = row.get("visibility_Report_Type", "")
                at_least = report in ("FM15-METAR", "FM16-SPECI") and vis_km >= _US_VISIBILITY_CAP_KM
        speed = value("wind_speed")
        gust = value("wind_gust")
        direction = None
        raw_dir = row.get("wind_direction")
        if (
            raw_dir is not None
            and raw_dir.upper() != "VRB"
            and not row.get("wind_direction_Measurement_Code", "").startswith(("9-", "C-", "V-"))
        ):
            direction = finite_number(raw_dir, "wind_direction", allow_negative=False)
            if direction > 360:
                raise RecordError("wind_direction", f"{raw_dir!r} is not within 0-360 degrees")
            direction %= 360.0
        if speed is None and row.get("wind_speed_Measurement_Code", "").startswith("C-"):
            speed = 0.0
        weather = self._weather(row)
        return Observation(
            time_utc=t,
            station=station,
            precip_accums=tuple(accums),
            visibility_m=visibility_m,
            visibility_at_least=at_least,
            visibility_below=below,
            wind_speed_m_per_s=speed,
            wind_gust_m_per_s=gust,
            wind_dir_deg_from=direction,
            weather=weather,
            report_type=_report_type(row),
            line=line,
        )

    @staticmethod
    def _weather(row: dict[str, str]) -> tuple[PresentWeather, ...] | None:
        found: dict[str, PresentWeather] = {}
        any_column = False
        for family in ("MW", "AU", "AW"):
            for k in (1, 2, 3):
                raw = row.get(f"pres_wx_{family}{k}")
                if raw is None:
                    continue
                any_column = True
                text, _, number = raw.partition(":")
                wx = None
                if family == "MW" and number.isdigit():
                    wx = weather_from_synop(int(number))
                if wx is None:
                    wx = parse_weather_token(text)
                if wx is not None:
                    key = "".join(sorted(wx.phenomena)) + wx.descriptor
                    found.setdefault(key, wx)
        return tuple(found.values()) if any_column else None


def _report_type(row: dict[str, str]) -> str:
    """``METAR``, ``SPECI``, ``SYNOP`` from GHCNh's ``FM15-METAR`` style codes, else the code as given."""
    for col in ("precipitation_Report_Type", "visibility_Report_Type", "wind_speed_Report_Type"):
        code = row.get(col)
        if code:
            return code.split("-", 1)[1] if code[:2] == "FM" and "-" in code else code
    return ""
