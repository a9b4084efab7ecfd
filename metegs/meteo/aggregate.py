"""Weather conditions at a capture time: aggregate a window of records, grade it, gate by present weather.

``conditions_at(table, time, window="1h", agg="max")`` returns a ``WeatherConditions``: the rate P with
the paper's ``Agg ∈ {mean, max, min}`` over the window, its WMO class, the paper's normalised
``s_t = clip((Agg(P) − Pmin)/(Pmax − Pmin), 0, 1)``, a WMO-anchored score, visibility, wind and which
effects the present weather calls for (fog without rain, rain without fog).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from datetime import datetime
from typing import Literal

import numpy as np

from metegs.errors import ConfigError, DataError
from metegs.meteo import physics
from metegs.meteo.observations import Observation, ObservationTable, epoch_s, parse_time
from metegs.meteo.rates import precip_series
from metegs.meteo.units import parse_duration_s
from metegs.meteo.weather_codes import PresentWeather

Agg = Literal["mean", "max", "min"]
AGGS: tuple[str, ...] = ("mean", "max", "min")

RAIN_CLASSES: tuple[tuple[float, str], ...] = (
    (2.5, "light"),
    (10.0, "moderate"),
    (50.0, "heavy"),
    (math.inf, "violent"),
)
"""WMO rain intensity classes (upper bound mm/h, name): light < 2.5 ≤ moderate < 10 ≤ heavy < 50 ≤ violent (WMO-No. 8 Ch. 14)."""
DRIZZLE_CLASSES: tuple[tuple[float, str], ...] = ((0.1, "light"), (0.5, "moderate"), (math.inf, "heavy"))
"""WMO drizzle intensity classes: light < 0.1 ≤ moderate < 0.5 ≤ heavy mm/h (WMO-No. 8 Ch. 14)."""
WMO_SCORE_KNOTS: tuple[tuple[float, float], ...] = ((0.1, 0.0), (2.5, 0.25), (10.0, 0.5), (50.0, 0.75), (100.0, 1.0))
"""(rate mm/h, score): the WMO-anchored monotone score is piecewise linear in log P through these knots (§8.0)."""
MIST_LIMIT_M = 5000.0
"""Mist (BR) and haze (HZ) are reported up to 5 km; fog (FG) below 1 km (ICAO Annex 3 App. 3 §4.4)."""
FOG_LIMIT_M = 1000.0

_OBSCURATION_KIND = {"fog": "fog", "mist": "mist", "haze": "haze", "smoke": "haze", "dust": "haze", "spray": "mist"}


def intensity_class(rate_mm_per_h: float | None, kind: str = "rain") -> str:
    """``none``, ``light``, ``moderate``, ``heavy`` or ``violent`` (WMO classes; drizzle has its own lower bounds)."""
    if rate_mm_per_h is None:
        return "unknown"
    if rate_mm_per_h <= 0:
        return "none"
    for upper, name in DRIZZLE_CLASSES if kind == "drizzle" else RAIN_CLASSES:
        if rate_mm_per_h < upper:
            return name
    return "violent"


def wmo_score(rate_mm_per_h: float) -> float:
    """A monotone score in [0, 1], piecewise linear in log P through the WMO class bounds (0.1→0 … 100→1)."""
    if rate_mm_per_h <= WMO_SCORE_KNOTS[0][0]:
        return 0.0
    for (p0, s0), (p1, s1) in zip(WMO_SCORE_KNOTS, WMO_SCORE_KNOTS[1:]):
        if rate_mm_per_h <= p1:
            return s0 + (s1 - s0) * math.log(rate_mm_per_h / p0) / math.log(p1 / p0)
    return 1.0


def normalised_intensity(value: float, p_min: float, p_max: float) -> float:
    """The paper's s_t = clip((value − Pmin)/(Pmax − Pmin), 0, 1); 0 when Pmax ≤ Pmin."""
    if p_max <= p_min:
        return 0.0
    return min(1.0, max(0.0, (value - p_min) / (p_max - p_min)))


@dataclass(frozen=True)
class WeatherConditions:
    """What the weather was at a capture time, after aggregation and gating (input of the mapping θ)."""

    time_utc: datetime
    """Capture time (UTC)."""
    window_s: float = 3600.0
    """Length of the aggregation window, s."""
    agg: str = "max"
    """Aggregation of the window: ``mean``, ``max`` or ``min``."""
    precip_mm_per_h: float | None = None
    """Rate used for the mapping, mm/h; None when nothing is known about precipitation."""
    precip_source: str = "none"
    """``measured`` (rates/accumulations), ``present_weather`` (§1.5 representative rate), ``trace`` or ``none``."""
    precip_coverage: float = 0.0
    """Fraction of the window covered by precipitation data (gaps are not zeros)."""
    precip_kind: str = "unknown"
    """``rain``, ``drizzle``, ``snow``, ``none`` (reported dry) or ``unknown`` (no present weather)."""
    intensity_class: str = "unknown"
    """WMO class of ``precip_mm_per_h`` for its kind (``none``, ``light`` … ``violent``)."""
    wmo_score: float = 0.0
    """WMO-anchored score in [0, 1] (``wmo_score``)."""
    normalised: float | None = None
    """The paper's s_t in [0, 1] against ``p_range_mm_per_h``, or None."""
    p_range_mm_per_h: tuple[float, float] | None = None
    """(Pmin, Pmax) used for ``normalised``: the record's range unless given."""
    visibility_m: float | None = None
    """Visibility, m (the window's minimum for ``max``, maximum for ``min``, harmonic mean for ``mean``)."""
    visibility_at_least: bool = False
    """The visibility is only a lower bound (9999, CAVOK, 10SM): no fog."""
    wind_speed_m_per_s: float = 0.0
    """10-m wind speed, m/s (0 when not reported)."""
    wind_gust_m_per_s: float | None = None
    """Largest gust in the window, m/s."""
    wind_dir_deg_from: float | None = None
    """Direction the wind blows from, degrees; None for calm, variable or unknown."""
    weather: tuple[PresentWeather, ...] = ()
    """Present-weather groups at the station in the window."""
    weather_reported: bool = False
    """True if any record in the window reports present weather (even "none")."""
    rain_active: bool = False
    """Render rain (streaks, veil): liquid precipitation is measured or reported."""
    fog_active: bool = False
    """Render fog/mist/haze beyond the rain's own extinction."""
    fog_kind: str | None = None
    """``fog``, ``mist`` or ``haze`` when ``fog_active``."""
    n_records: int = 0
    """Records used for visibility, wind and weather."""
    station: str = ""
    """Station the conditions come from."""
    notes: tuple[str, ...] = field(default_factory=tuple)
    """Assumptions and fallbacks taken (human readable)."""


def window_bounds(time: datetime, window_s: float, align: str = "center") -> tuple[float, float]:
    """(start, end) of the window in s since the epoch: ``center`` (default), ``before`` or ``after`` the time."""
    t = epoch_s(time)
    if align == "center":
        return t - window_s / 2.0, t + window_s / 2.0
    if align == "before":
        return t - window_s, t
    if align == "after":
        return t, t + window_s
    raise ConfigError(f"unknown window alignment {align!r}; use center, before or after")


def conditions_at(
    table: ObservationTable,
    time: str | datetime,
    window: str | float = "1h",
    agg: str = "max",
    *,
    align: str = "center",
    station: str | None = None,
    p_range_mm_per_h: tuple[float, float] | None = None,
    trace_amount_mm: float = 0.05,
    max_gap: str | float = "3h",
) -> WeatherConditions:
    """Aggregate ``table`` over a window around ``time`` into WeatherConditions (see the module docstring).

    Instantaneous quantities (visibility, wind, present weather) come from the records inside the window;
    if there are none, from the nearest record within ``max_gap`` (noted). Precipitation comes from the
    reconciled periods overlapping the window; without any, from the present weather's representative
    rate; else it stays unknown.
    """
    if agg not in AGGS:
        raise ConfigError(f"unknown aggregation {agg!r}; use one of {', '.join(AGGS)}")
    t = parse_time(time)
    window_s = parse_duration_s(window)
    gap_s = parse_duration_s(max_gap)
    table = table.for_station(station)
    if not len(table):
        raise DataError(table.source or None, "no records to aggregate")
    t0, t1 = window_bounds(t, window_s, align)
    notes: list[str] = []

    series = precip_series(table, trace_amount_mm=trace_amount_mm)
    if window_s > 0:
        overlap = series.overlap_s(t0, t1)
        idx = overlap > 0
    else:
        tc = epoch_s(t)
        idx = (series.start_s < tc) & (series.end_s >= tc)
        overlap = idx.astype(float)
    precip: float | None = None
    coverage = 0.0
    source = "none"
    if idx.any():
        rates = series.rate_mm_per_h[idx]
        w = overlap[idx]
        precip = float({"mean": np.sum(rates * w) / np.sum(w), "max": rates.max(), "min": rates.min()}[agg])
        coverage = float(min(1.0, w.sum() / window_s)) if window_s > 0 else 1.0
        source = "trace" if precip > 0 and series.trace[idx].all() else "measured"
        if coverage < 0.999:
            notes.append(f"precipitation data cover {coverage:.0%} of the window; the rest is a gap (not zero)")
    if p_range_mm_per_h is None and len(series):
        p_range_mm_per_h = (float(series.rate_mm_per_h.min()), float(series.rate_mm_per_h.max()))

    times = table.times_s()
    inside = [r for r, tr in zip(table.records, times) if t0 <= tr <= t1]
    if not inside:
        nearest = int(np.argmin(np.abs(times - epoch_s(t))))
        if abs(times[nearest] - epoch_s(t)) <= gap_s:
            inside = [table.records[nearest]]
            notes.append(
                f"no record inside the window; visibility, wind and weather from the nearest one at {table.records[nearest].time_utc:%Y-%m-%d %H:%M}Z"
            )
        else:
            notes.append(
                f"no record within {gap_s / 3600:g} h of the capture time: visibility, wind and weather unknown"
            )

    visibility, at_least = _aggregate_visibility(inside, agg)
    speed, gust, direction = _aggregate_wind(inside, agg)
    weather_reported = any(r.weather is not None for r in inside)
    weather = _union_weather(inside)

    liquid = [w for w in weather if w.liquid_kind is not None]
    if liquid:
        kind = "rain" if any(w.liquid_kind == "rain" for w in liquid) else "drizzle"
    elif any(w.is_precipitation for w in weather):
        kind = "snow"
    else:
        kind = "none" if weather_reported else "unknown"

    if liquid and (precip is None or precip <= 0):
        if precip is None:
            reps = [w.representative_rate_mm_per_h for w in liquid]
            reps = [r for r in reps if r is not None]
            precip = float({"mean": np.mean(reps), "max": max(reps), "min": min(reps)}[agg])
            source = "present_weather"
            notes.append("no measured amount: rate from the present-weather intensity (WMO class geometric mean)")
        else:
            precip = trace_amount_mm
            source = "trace"
            notes.append(f"rain reported but the measured amount is zero: taken as a trace, {trace_amount_mm:g} mm/h")

    if weather_reported:
        rain_active = kind in ("rain", "drizzle") and precip is not None and precip > 0
        if kind == "snow":
            notes.append("snow or ice pellets reported: not rendered as rain")
        elif not rain_active and precip is not None and precip > 0:
            notes.append("precipitation measured in the window but none reported at the records' times: rain gated off")
    else:
        rain_active = precip is not None and precip > 0
        if rain_active:
            kind = "rain"

    obscurations = [w for w in weather if w.is_obscuration]
    if weather_reported:
        fog_active = bool(obscurations)
    else:
        fog_active = False
        if visibility is not None and not at_least and visibility < MIST_LIMIT_M:
            excess = physics.beta_from_visibility_per_m(visibility) - physics.beta_rain_per_m(precip or 0.0)
            fog_active = excess > physics.beta_from_visibility_per_m(MIST_LIMIT_M)
    fog_kind = None
    if fog_active:
        kinds = {k for w in obscurations for k in w.kinds}
        for candidate in ("fog", "mist", "haze", "smoke", "dust", "spray"):
            if candidate in kinds:
                fog_kind = _OBSCURATION_KIND[candidate]
                break
        if fog_kind is None:
            fog_kind = "fog" if visibility is not None and visibility < FOG_LIMIT_M else "mist"

    rate_for_class = precip if precip is not None else None
    normalised = None
    if p_range_mm_per_h is not None and precip is not None:
        normalised = normalised_intensity(precip, *p_range_mm_per_h)
    return WeatherConditions(
        time_utc=t,
        window_s=window_s,
        agg=agg,
        precip_mm_per_h=precip,
        precip_source=source,
        precip_coverage=coverage,
        precip_kind=kind,
        intensity_class=intensity_class(rate_for_class, "drizzle" if kind == "drizzle" else "rain"),
        wmo_score=wmo_score(precip) if precip is not None else 0.0,
        normalised=normalised,
        p_range_mm_per_h=p_range_mm_per_h,
        visibility_m=visibility,
        visibility_at_least=at_least,
        wind_speed_m_per_s=speed,
        wind_gust_m_per_s=gust,
        wind_dir_deg_from=direction,
        weather=weather,
        weather_reported=weather_reported,
        rain_active=rain_active,
        fog_active=fog_active,
        fog_kind=fog_kind,
        n_records=len(inside),
        station=table.records[0].station,
        notes=tuple(notes),
    )


def _aggregate_visibility(records: list[Observation], agg: str) -> tuple[float | None, bool]:
    items = [(r.visibility_m, r.visibility_at_least) for r in records if r.visibility_m is not None]
    if not items:
        return None, False
    if agg == "max":  # the most intense weather: lowest visibility
        return min(items, key=lambda it: (it[0], it[1]))
    if agg == "min":
        return max(items, key=lambda it: (it[0], not it[1]))
    inverse = np.mean([1.0 / v for v, _ in items])  # mean extinction
    return float(1.0 / inverse), all(a for _, a in items)


def _aggregate_wind(records: list[Observation], agg: str) -> tuple[float, float | None, float | None]:
    items = [(r.wind_speed_m_per_s, r.wind_dir_deg_from) for r in records if r.wind_speed_m_per_s is not None]
    gusts = [r.wind_gust_m_per_s for r in records if r.wind_gust_m_per_s is not None]
    gust = max(gusts) if gusts else None
    if not items:
        return 0.0, gust, None
    if agg in ("max", "min"):
        pick = (max if agg == "max" else min)(items, key=lambda it: it[0])
        return float(pick[0]), gust, pick[1]
    speed = float(np.mean([s for s, _ in items]))
    with_dir = [(s, d) for s, d in items if d is not None and s > 0]
    direction = None
    if with_dir:
        u = sum(s * math.sin(math.radians(d)) for s, d in with_dir)
        v = sum(s * math.cos(math.radians(d)) for s, d in with_dir)
        if math.hypot(u, v) > 1e-9:
            direction = math.degrees(math.atan2(u, v)) % 360.0
    return speed, gust, direction


def _union_weather(records: list[Observation]) -> tuple[PresentWeather, ...]:
    seen: dict[tuple, PresentWeather] = {}
    for r in records:
        for w in r.weather or ():
            if w.at_station:
                seen.setdefault((w.code, w.wmo_code), w)
    return tuple(seen.values())
