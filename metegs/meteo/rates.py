"""Accumulations → precipitation rates, never counting rain twice; gaps stay gaps.

Every rate and accumulation of a station becomes a period ``(start, end]`` with an amount (research
note §6.7: hourly totals belong to the hour *ending* at their time stamp). Periods are then made
disjoint, shortest first:

- a period that overlaps nothing is kept;
- a longer period that *contains* shorter kept ones (a METAR hourly ``P`` group around a SPECI's ``P``
  group, a 6-h SYNOP total around a 3-h one) keeps only its remainder, with its amount minus theirs;
- a period that overlaps another only partly, or whose amount is smaller than what it contains, cannot
  be split honestly and is dropped, counted in one ``MeteoWarning``.

Time not covered by any period is a gap: it is never filled with zeros.
"""

from __future__ import annotations

import bisect
import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from metegs.meteo.observations import ObservationTable, epoch_s
from metegs.meteo.readers.base import MeteoWarning

EPS_S = 1.0
"""Times closer than this (s) are the same instant."""


@dataclass(frozen=True)
class PrecipSeries:
    """Disjoint precipitation periods of one station, sorted by start."""

    start_s: np.ndarray
    """[K] float64, period starts (s since the epoch, exclusive)."""
    end_s: np.ndarray
    """[K] float64, period ends (s since the epoch, inclusive)."""
    rate_mm_per_h: np.ndarray
    """[K] float64, mean rate over each period, mm/h."""
    trace: np.ndarray
    """[K] bool, the period's amount was a trace."""
    station: str = ""
    """The station the periods belong to."""

    def __len__(self) -> int:
        return int(self.start_s.size)

    def overlap_s(self, t0: float, t1: float) -> np.ndarray:
        """[K] seconds of each period that fall inside ``[t0, t1]``."""
        return np.clip(np.minimum(self.end_s, t1) - np.maximum(self.start_s, t0), 0.0, None)

    @property
    def max_rate_mm_per_h(self) -> float | None:
        return float(self.rate_mm_per_h.max()) if len(self) else None

    @property
    def min_rate_mm_per_h(self) -> float | None:
        return float(self.rate_mm_per_h.min()) if len(self) else None

    def covered_s(self) -> float:
        """Total time covered by precipitation data, s."""
        return float((self.end_s - self.start_s).sum())


@dataclass
class _Period:
    start: float
    end: float
    amount_mm: float
    trace: bool
    line: int | None


def precip_series(
    table: ObservationTable,
    *,
    station: str | None = None,
    trace_amount_mm: float = 0.05,
    tolerance_mm: float = 0.1,
) -> PrecipSeries:
    """The disjoint precipitation periods of one station of ``table``.

    ``trace_amount_mm`` is the depth given to a trace (0 turns traces into dry periods);
    ``tolerance_mm`` absorbs rounding when a longer total is compared with the shorter ones it contains
    (2 % of the longer total if that is more).
    """
    table = table.for_station(station)
    fallback_h = (table.median_step_s() or 3600.0) / 3600.0
    periods: list[_Period] = []
    for r in table.records:
        end = epoch_s(r.time_utc)
        if r.precip_rate_mm_per_h is not None:
            p_h = r.precip_rate_period_h if r.precip_rate_period_h else fallback_h
            periods.append(_Period(end - p_h * 3600.0, end, r.precip_rate_mm_per_h * p_h, False, r.line))
        for acc in r.precip_accums:
            if acc.period_h * 3600.0 <= EPS_S:
                continue
            amount = trace_amount_mm if acc.trace and acc.amount_mm <= 0 else acc.amount_mm
            periods.append(_Period(end - acc.period_h * 3600.0, end, amount, acc.trace, r.line))
    kept, conflicts = disjoint_periods(periods, tolerance_mm)
    if conflicts:
        shown = "; ".join(conflicts[:3]) + (" ..." if len(conflicts) > 3 else "")
        warnings.warn(
            f"{table.source or 'observations'}{' station ' + table.records[0].station if table.records and table.records[0].station else ''}: "
            f"ignored {len(conflicts)} precipitation period(s) that cannot be reconciled with shorter ones ({shown})",
            MeteoWarning,
            stacklevel=2,
        )
    start = np.array([p.start for p in kept], dtype=np.float64)
    end = np.array([p.end for p in kept], dtype=np.float64)
    hours = (end - start) / 3600.0
    amount = np.array([p.amount_mm for p in kept], dtype=np.float64)
    rate = np.divide(amount, hours, out=np.zeros_like(amount), where=hours > 0)
    return PrecipSeries(
        start,
        end,
        rate,
        np.array([p.trace for p in kept], dtype=bool),
        table.records[0].station if table.records else "",
    )


def disjoint_periods(periods: Sequence[_Period], tolerance_mm: float = 0.1) -> tuple[list[_Period], list[str]]:
    """Shortest-first reconciliation of overlapping periods (see the module docstring); returns (kept, reasons dropped)."""
    order = sorted(periods, key=lambda p: (p.end - p.start, p.end))
    starts: list[float] = []
    ends: list[float] = []
    kept: list[_Period] = []
    conflicts: list[str] = []
    for p in order:
        lo = bisect.bisect_right(ends, p.start + EPS_S)
        hi = bisect.bisect_left(starts, p.end - EPS_S)
        inside = kept[lo:hi]
        if any(q.start < p.start - EPS_S or q.end > p.end + EPS_S for q in inside):
            conflicts.append(f"line {p.line}: its period overlaps another one only partly")
            continue
        residual = p.amount_mm - sum(q.amount_mm for q in inside)
        tol = max(tolerance_mm, 0.02 * p.amount_mm)
        pieces = []
        cursor = p.start
        for q in inside:
            if q.start - cursor > EPS_S:
                pieces.append((cursor, q.start))
            cursor = max(cursor, q.end)
        if p.end - cursor > EPS_S:
            pieces.append((cursor, p.end))
        if residual < -tol:
            conflicts.append(
                f"line {p.line}: {p.amount_mm:g} mm over {(p.end - p.start) / 3600:g} h is less than the "
                f"{p.amount_mm - residual:g} mm of the shorter periods inside it"
            )
            continue
        if not pieces:
            if abs(residual) > tol and not p.trace:
                conflicts.append(
                    f"line {p.line}: {p.amount_mm:g} mm disagrees with the {p.amount_mm - residual:g} mm of the periods it covers"
                )
            continue
        residual = max(residual, 0.0)
        length = sum(b - a for a, b in pieces)
        for a, b in pieces:
            piece = _Period(a, b, residual * (b - a) / length, p.trace, p.line)
            i = bisect.bisect_left(starts, a)
            starts.insert(i, a)
            ends.insert(i, b)
            kept.insert(i, piece)
    return kept, conflicts


def deaccumulate(
    times_s: Sequence[float],
    totals_mm: Sequence[float],
    *,
    reset_hour_utc: int | None = None,
    tolerance_mm: float = 0.05,
) -> list[tuple[float, float] | None | str]:
    """Running totals → per-step ``(amount_mm, period_h)`` ending at each time (ERA5-Land style, §6.4/§6.7).

    With ``reset_hour_utc`` (0 for ERA5-Land) the total restarts at that hour each day and the value *at*
    the reset hour still belongs to the cycle that ends there. Without it a decrease is bad input. The
    first record gives None (unknown start) unless the reset hour tells when its total began. An item is
    a string saying what is wrong when a total decreases within a cycle.
    """
    out: list[tuple[float, float] | None | str] = []
    prev_t: float | None = None
    prev_total: float | None = None
    for t, total in zip(times_s, totals_mm):
        reset_start = None if reset_hour_utc is None else _reset_start(t, reset_hour_utc)
        if prev_t is None:
            out.append(None if reset_start is None else (total, (t - reset_start) / 3600.0))
        elif reset_start is None or prev_t > reset_start + EPS_S:
            diff = total - prev_total
            if diff < -tolerance_mm:
                out.append(
                    f"running total decreases from {prev_total:g} to {total:g} mm"
                    + ("" if reset_hour_utc is not None else " (give precip_reset_hour_utc if it restarts daily)")
                )
                prev_t, prev_total = t, total
                continue
            out.append((max(diff, 0.0), (t - prev_t) / 3600.0))
        else:  # the previous value closed an earlier cycle: this total counts from the reset
            out.append((total, (t - reset_start) / 3600.0))
        prev_t, prev_total = t, total
    return out


def _reset_start(t: float, hour: int) -> float:
    """Latest instant strictly before ``t`` at ``hour``:00 UTC."""
    start = math.floor(t / 86400.0) * 86400.0 + hour * 3600.0
    while start >= t - EPS_S:
        start -= 86400.0
    while start + 86400.0 < t - EPS_S:
        start += 86400.0
    return start
