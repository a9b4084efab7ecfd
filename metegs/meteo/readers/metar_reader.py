"""METAR/SPECI text: single reports, bulletins and collectives (one report per ``=``).

Reports give only day and time, so the year and month must be given as options. Reports that cannot be
decoded are skipped and counted in one warning, never dropped silently. Precipitation periods (FMH-1):
``P`` is the amount since the last *routine* report (so a SPECI's ``P`` lies inside the next routine
report's, which ``rates.py`` reconciles), ``6`` is 6-h in the 00/06/12/18 UTC reports and 3-h in the
03/09/15/21 UTC ones, ``7`` is 24-h.
"""

from __future__ import annotations

import re
from collections import Counter
from dataclasses import dataclass
from datetime import timedelta
from pathlib import Path
from typing import Literal

from metegs.errors import DataError
from metegs.meteo import units
from metegs.meteo.metar import MetarError, MetarReport, parse_metar, split_bulletin
from metegs.meteo.observations import Accumulation, Observation
from metegs.meteo.readers.base import CommonOptions, ObservationReader, Problems, read_text

_REPORT = re.compile(r"(?m)^\s*(?:METAR |SPECI )?[A-Z][A-Z0-9]{3} \d{6}Z ")


@dataclass
class MetarOptions(CommonOptions):
    """Options of the METAR reader."""

    year: int | None = None
    """Year of the reports (METAR gives only day and time); required."""
    month: int | None = None
    """Month of the reports (1-12); required."""
    routine_minute: int | None = None
    """Minute past the hour of a station's routine reports; None: the most common minute of its METARs (else 53)."""
    time_order: Literal["strict", "sort"] = "sort"
    """Bulletins list stations in any order, so records are sorted by default."""


class MetarReader(ObservationReader):
    """METAR/SPECI reports, bulletins and collectives (our own decoder, see ``metegs.meteo.metar``)."""

    name = "metar"
    priority = 40
    Options = MetarOptions

    @classmethod
    def can_read(cls, path: Path, head: str) -> bool:
        return path.suffix.lower() in (".txt", ".metar", "") and bool(_REPORT.search(head))

    def _read(self, path: Path, opts: MetarOptions, problems: Problems):
        if opts.year is None or opts.month is None:
            raise DataError(
                path, "METAR reports give only day and time: pass year= and month= (CLI: --set year=2024 month=7)"
            )
        if not 1 <= opts.month <= 12:
            raise DataError(path, f"month={opts.month} is not 1-12")
        chunks = split_bulletin(read_text(path, errors="replace"))  # bulletins carry transmission noise
        parsed: list[tuple[int, MetarReport]] = []
        for line, kind, text in chunks:
            try:
                parsed.append((line, parse_metar(text, year=opts.year, month=opts.month, report_type=kind)))
            except MetarError as exc:
                problems.skip(line, None, f"unreadable METAR: {exc}")
        if not parsed:
            raise DataError(
                path,
                f"no METAR report could be read ({len(chunks)} candidate(s); "
                + ("; ".join(problems.examples) or "the file holds no reports")
                + ")",
            )
        routine = self._routine_minutes(parsed, opts)
        records = [self._observation(line, rep, routine[rep.station]) for line, rep in parsed]
        notes = [f"year {opts.year}, month {opts.month} (given)"]
        return records, len(chunks), notes

    @staticmethod
    def _routine_minutes(parsed, opts: MetarOptions) -> dict[str, int]:
        minutes: dict[str, Counter] = {}
        for _, rep in parsed:
            c = minutes.setdefault(rep.station, Counter())
            if rep.report_type == "METAR":
                c[rep.time_utc.minute] += 1
        return {
            st: opts.routine_minute if opts.routine_minute is not None else (c.most_common(1)[0][0] if c else 53)
            for st, c in minutes.items()
        }

    @staticmethod
    def _observation(line: int, rep: MetarReport, routine_minute: int) -> Observation:
        accums = []
        if rep.precip_hourly_in is not None:
            last_routine = rep.time_utc.replace(minute=routine_minute, second=0)
            if last_routine >= rep.time_utc:  # a routine report, or a SPECI before this hour's routine minute
                last_routine -= timedelta(hours=1)
            period_h = (rep.time_utc - last_routine).total_seconds() / 3600.0
            accums.append(Accumulation(units.to_mm(rep.precip_hourly_in, "in"), period_h, rep.precip_hourly_trace, "P"))
        if rep.precip_3_6_hour_in is not None:
            nominal_hour = (rep.time_utc + timedelta(minutes=30)).hour
            period = 6.0 if nominal_hour % 6 == 0 else 3.0 if nominal_hour % 3 == 0 else None
            if period is not None:
                accums.append(
                    Accumulation(units.to_mm(rep.precip_3_6_hour_in, "in"), period, rep.precip_3_6_hour_trace, "6")
                )
        if rep.precip_24_hour_in is not None:
            accums.append(Accumulation(units.to_mm(rep.precip_24_hour_in, "in"), 24.0, rep.precip_24_hour_in == 0, "7"))
        return Observation(
            time_utc=rep.time_utc,
            station=rep.station,
            precip_accums=tuple(accums),
            visibility_m=rep.visibility_m,
            visibility_at_least=rep.visibility_at_least,
            visibility_below=rep.visibility_below,
            wind_speed_m_per_s=rep.wind_speed_m_per_s,
            wind_gust_m_per_s=rep.wind_gust_m_per_s,
            wind_dir_deg_from=rep.wind_dir_deg_from,
            weather=rep.weather,
            report_type=rep.report_type,
            line=line,
        )
