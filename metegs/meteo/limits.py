"""Plausibility bounds: a meteorological value beyond them is corrupt or in the wrong unit, not weather.

The bounds sit just above the world records (WMO World Weather and Climate Extremes Archive; NOAA NWS
Hydrometeorological Design Studies Center, "World record point precipitation measurements"), so that no real
observation is refused while a unit mix-up (inches read as mm, km/h as m/s), a missing-value code (``9999``)
or a typed extra digit is.
"""

from __future__ import annotations

import math

PRECIP_RECORDS_MM: tuple[tuple[float, float], ...] = ((1.0 / 60.0, 40.0), (1.0, 400.0), (24.0, 2000.0))
"""(period h, largest plausible depth mm), just above the world's greatest point rainfalls: 38 mm in 1 minute
(Barot, Guadeloupe, 26 Nov 1970, NWS HDSC), 305 mm in 60 minutes (Holt, Missouri, 22 Jun 1947, WMO) and 1825 mm in
24 hours (Foc-Foc, La Réunion, 7-8 Jan 1966, WMO)."""
MAX_WIND_M_S = 120.0
"""Largest plausible wind speed or gust, m/s: above the strongest gust measured, 113.3 m/s (Barrow Island,
Australia, 10 Apr 1996, WMO)."""
MIN_VISIBILITY_M = 1.0
"""Smallest plausible visibility, m: reports stop at 50 m (METAR ``0000``), so less than 1 m is a unit error or a
missing-value marker."""
ZERO_VISIBILITY_M = 50.0
"""Visibility given to a report of zero (METAR ``0000``, ISD ``000000``): below the smallest reportable value,
an upper bound."""


def max_precip_rate_mm_h(period_h: float | None = None) -> float:
    """Largest plausible mean rate over ``period_h`` hours (None: instantaneous, taken as 1 minute), mm/h.

    A period shorter than a record's holds at most that record's depth; a longer one at most its mean rate.
    """
    d = 1.0 / 60.0 if period_h is None or not period_h > 0 else period_h
    return min(depth / min(d, hours) for hours, depth in PRECIP_RECORDS_MM)


MAX_PRECIP_RATE_MM_H = max_precip_rate_mm_h()
"""Largest plausible instantaneous rate, mm/h (2400: 40 mm in one minute)."""


def range_problem(value: float, low: float, high: float, unit: str) -> str | None:
    """Why ``value`` is not a finite number within [low, high] of ``unit``, or None."""
    if not math.isfinite(value):
        return f"{value!r} is not a finite number"
    if value < low:
        return f"{value:g} {unit} is below {low:g} {unit}"
    if value > high:
        return f"{value:g} {unit} is above {high:g} {unit}"
    return None
