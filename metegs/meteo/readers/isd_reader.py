"""NOAA ISD (DS3505) full-format fixed-width records.

Positions (NCEI "Federal Climate Complex Data Documentation for Integrated Surface Data", 1-based):
5-10 USAF id, 11-15 WBAN id, 16-23 date, 24-27 time (UTC), 42-46 report type, 61-63 wind direction
(999 missing), 64 its quality, 65 wind type (``C`` calm, ``V`` variable), 66-69 wind speed (m/s × 10,
9999 missing), 70 its quality, 79-84 visibility (m, 999999 missing), 85 its quality, 106-108 ``ADD``.
Additional data (before ``REM``/``EQD``): ``AA1``-``AA4`` liquid precipitation ``pp dddd c q`` (period h,
depth mm × 10, condition ``2`` = trace, quality), ``MW1``-``MW7`` manual present weather ``ww q``
(WMO table 4677). Quality codes 2, 3, 6, 7 (suspect, erroneous) make a value count as not reported.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

from metegs.meteo import limits
from metegs.meteo.observations import Accumulation, Observation
from metegs.meteo.readers.base import CommonOptions, ObservationReader, Problems, RecordError, read_text
from metegs.meteo.weather_codes import weather_from_synop

_BAD_QUALITY = set("2367")
_FIRST = re.compile(r"^\d{4}[0-9A-Z]{6}\d{5}\d{12}.[+-]\d{5}[+-]\d{6}")
_AA = re.compile(r"AA([1-4])(\d{2})(\d{4})([0-9A-Z])([0-9A-Z])")
_MW = re.compile(r"MW([1-7])(\d{2})([0-9A-Z])")


@dataclass
class IsdOptions(CommonOptions):
    """Options of the ISD reader."""


class IsdReader(ObservationReader):
    """NOAA ISD full-format (DS3505) fixed-width files."""

    name = "isd"
    priority = 20
    Options = IsdOptions

    @classmethod
    def can_read(cls, path: Path, head: str) -> bool:
        return bool(_FIRST.match(head))

    def _read(self, path: Path, opts: IsdOptions, problems: Problems):
        records = []
        total = 0
        no_period = 0
        for number, line in enumerate(read_text(path).split("\n"), start=1):
            if not line.strip():
                continue
            total += 1
            if len(line) < 105 or not _FIRST.match(line):
                problems.skip(number, None, f"not an ISD record ({len(line)} characters; the fixed part has 105)")
                continue
            try:
                obs, skipped_periods = self._observation(number, line, problems)
            except RecordError as exc:
                problems.fail(number, exc.field, exc.message)
                continue
            no_period += skipped_periods
            records.append(obs)
        notes = []
        if no_period:
            notes.append(f"{no_period} AA precipitation group(s) without a period (pp = 99) were not used")
        return records, total, notes

    @staticmethod
    def _observation(number: int, line: str, problems: Problems) -> tuple[Observation, int]:
        try:
            t = datetime(
                int(line[15:19]),
                int(line[19:21]),
                int(line[21:23]),
                int(line[23:25]),
                int(line[25:27]),
                tzinfo=timezone.utc,
            )
        except ValueError as exc:
            raise RecordError("date/time (columns 16-27)", f"{line[15:27]!r}: {exc}") from None
        station = f"{line[4:10]}-{line[10:15]}"
        direction = speed = None
        if line[65:69] != "9999" and line[69] not in _BAD_QUALITY:
            speed = _number(line, 65, 69, "wind speed") / 10.0
        elif line[69] in _BAD_QUALITY:
            problems.ignore_value(number, "wind speed (columns 66-69)", f"quality code {line[69]}")
        if line[64] == "C":
            speed = 0.0 if speed is None else speed
        elif line[60:63] != "999" and line[64] != "V" and line[63] not in _BAD_QUALITY:
            direction = float(_number(line, 60, 63, "wind direction") % 360)
        visibility, below = None, False
        if line[78:84] != "999999":
            if line[84] in _BAD_QUALITY:
                problems.ignore_value(number, "visibility (columns 79-84)", f"quality code {line[84]}")
            else:
                visibility = float(_number(line, 78, 84, "visibility"))
                if visibility == 0:  # below the smallest reportable value
                    visibility, below = limits.ZERO_VISIBILITY_M, True
        additional = ""
        if line[105:108] == "ADD":
            additional = re.split(r"REM|EQD", line[108:], maxsplit=1)[0]
        accums = []
        no_period = 0
        for _, period, depth, condition, quality in _AA.findall(additional):
            if period == "99":
                no_period += 1
                continue
            if quality in _BAD_QUALITY:
                problems.ignore_value(number, "AA precipitation", f"quality code {quality}")
                continue
            trace = condition == "2"
            if depth == "9999":
                if not trace:
                    continue
                amount = 0.0
            else:
                amount = int(depth) / 10.0
            if int(period) == 0:
                continue
            accums.append(Accumulation(amount, float(int(period)), trace and amount == 0, "AA"))
        weather = None
        codes = _MW.findall(additional)
        if codes:
            found = []
            for _, ww, quality in codes:
                if quality in _BAD_QUALITY:
                    continue
                wx = weather_from_synop(int(ww))
                if wx is not None:
                    found.append(wx)
            weather = tuple(found)
        obs = Observation(
            time_utc=t,
            station=station,
            precip_accums=tuple(accums),
            visibility_m=visibility,
            visibility_below=below,
            wind_speed_m_per_s=speed,
            wind_dir_deg_from=direction,
            weather=weather,
            report_type={"FM-12": "SYNOP", "FM-15": "METAR", "FM-16": "SPECI"}.get(line[41:46], line[41:46].strip()),
            line=number,
        )
        return obs, no_period


def _number(line: str, start: int, end: int, name: str) -> int:
    """The unsigned integer in columns ``start+1``..``end`` of ``line``; RecordError names the columns otherwise."""
    text = line[start:end]
    if not text.isdigit():
        raise RecordError(f"{name} (columns {start + 1}-{end})", f"{text!r} is not a number")
    return int(text)
