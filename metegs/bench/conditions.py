"""Benchmark weather from real records: rain hours picked per WMO class, fog picked per visibility.

- Rain: `pick_rain_hour` scans a precipitation record (e.g. a UCI Beijing PRSA station file, hourly
  accumulations) for the hour whose rate is closest (in log) to the middle of a WMO class (light 0.5,
  moderate 5, heavy 22.4, violent 70.7 mm/h: the geometric means of the class bounds, the last one of
  50-100 mm/h), earliest first among equals, and returns the capture time at the middle of that hour:
  a 1-h window around it covers exactly that accumulation period. The pick is checked with
  `conditions_at`: the conditions at that time are in the class and call for rain.
- Fog: `pick_visibility` scans a visibility record (e.g. NOAA ISD) for the observation closest (in log)
  to a target visibility whose conditions call for fog (an obscuration such as FG or BR is reported, or
  the visibility alone implies it) and not for rain, within a factor ``tolerance``.
- Rain + fog: a rain hour of one record with the visibility of a fog pick in place of the record's (PRSA
  records have no visibility), through ``ConditionsConfig.visibility_m``.

A `ConditionSpec` (one entry of a suite's ``conditions:``) resolves to a `ResolvedCondition`: the
`ConditionsConfig` a training run takes and the provenance (record files, times, rates, visibilities)
written next to the results.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any

from metegs.errors import ConfigError, DataError
from metegs.meteo.aggregate import RAIN_CLASSES
from metegs.weather.conditions import ConditionsConfig
from metegs.weather.degrade import FAMILIES
from metegs.weather.kinds import parse_kinds, precipitation_kinds

CLASS_TARGET_MM_H: dict[str, float] = {
    "light": math.sqrt(0.1 * 2.5),
    "moderate": math.sqrt(2.5 * 10.0),
    "heavy": math.sqrt(10.0 * 50.0),
    "violent": math.sqrt(50.0 * 100.0),
}
"""Rate aimed at in each WMO rain class, mm/h: the geometric mean of its bounds (violent: of 50-100 mm/h)."""


def class_bounds(name: str) -> tuple[float, float]:
    """(lower, upper) mm/h of a WMO rain class (lower bound of light: just above 0)."""
    lower = 0.0
    for upper, cls in RAIN_CLASSES:
        if cls == name:
            return lower, upper
        lower = upper
    raise ConfigError(f"unknown WMO rain class {name!r}; expected one of {', '.join(CLASS_TARGET_MM_H)}")


@lru_cache(maxsize=8)
def _load(path: str, reader: str | None):
    """(table, reader options) of a record, read once per process (PRSA files take seconds)."""
    from metegs.meteo.theta_plan import load_record

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # reader notes about unreconcilable periods are not ours to report
        return load_record(Path(path), reader)


def _conditions(table, time: str, station: str | None = None):
    from metegs.meteo import conditions_at

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return conditions_at(table, time, "1h", "max", station=station)


def _at_given_time(path: Path, src: dict):
    """Conditions of the record at ``path`` at a condition entry's ``time`` (with its reader and station)."""
    table, _ = _load(str(path.resolve()), src.get("reader"))
    return _conditions(table, str(src["time"]), src.get("station"))


@dataclass
class RainPick:
    """A rain hour of a record."""

    record: str
    time: str
    """Capture time (UTC ISO): the middle of the picked hour."""
    precip_mm_h: float
    wmo_class: str
    station: str


@dataclass
class FogPick:
    """A visibility observation of a record."""

    record: str
    time: str
    """Capture time (UTC ISO): the observation's time."""
    visibility_m: float
    fog_kind: str | None
    present_weather: list[str]
    station: str


def pick_rain_hour(record: Path, wmo_class: str, reader: str | None = None, station: str | None = None) -> RainPick:
    """The hour of ``record`` whose rate is nearest the middle of ``wmo_class`` (see the module docstring)."""
    from datetime import timedelta

    lower, upper = class_bounds(wmo_class)
    target = CLASS_TARGET_MM_H[wmo_class]
    table, _ = _load(str(Path(record).resolve()), reader)
    table = table.for_station(station)
    candidates = []
    for obs in table.records:
        acc = obs.shortest_accumulation
        if acc is None or acc.trace or acc.period_h <= 0:
            continue
        rate = acc.amount_mm / acc.period_h
        if lower < rate < upper or (math.isinf(upper) and rate >= lower):
            mid = obs.time_utc - timedelta(hours=acc.period_h / 2)
            candidates.append((abs(math.log(rate / target)), obs.time_utc, mid, rate))
    candidates.sort(key=lambda c: (c[0], c[1]))
    for _, _, mid, _rate in candidates[:50]:
        when = mid.strftime("%Y-%m-%dT%H:%MZ")
        cond = _conditions(table, when, station)
        if cond.rain_active and cond.intensity_class == wmo_class:
            return RainPick(str(Path(record).resolve()), when, float(cond.precip_mm_per_h), wmo_class, cond.station)
    raise DataError(record, f"no hour in the {wmo_class} rain class ({lower:g}-{upper:g} mm/h) found")


def pick_visibility(
    record: Path,
    visibility_m: float,
    reader: str | None = None,
    station: str | None = None,
    tolerance: float = 1.5,
    allow_rain: bool = False,
) -> FogPick:
    """The observation of ``record`` nearest ``visibility_m`` that calls for fog (see the module docstring)."""
    if not (visibility_m > 0 and math.isfinite(visibility_m)):
        raise ConfigError(f"visibility_m must be a positive number of metres, got {visibility_m}")
    table, _ = _load(str(Path(record).resolve()), reader)
    table = table.for_station(station)
    candidates = [
        (abs(math.log(obs.visibility_m / visibility_m)), obs.time_utc, obs)
        for obs in table.records
        if obs.visibility_m is not None and obs.visibility_m > 0 and not obs.visibility_at_least
    ]
    candidates.sort(key=lambda c: (c[0], c[1]))
    for dist, _, obs in candidates:
        if dist > math.log(max(tolerance, 1.0)):
            break
        when = obs.time_utc.strftime("%Y-%m-%dT%H:%MZ")
        cond = _conditions(table, when, station)
        if cond.fog_active and (allow_rain or not cond.rain_active) and cond.visibility_m is not None:
            return FogPick(
                str(Path(record).resolve()),
                when,
                float(cond.visibility_m),
                cond.fog_kind,
                [w.code for w in cond.weather],
                cond.station,
            )
    raise DataError(
        record, f"no observation within a factor {tolerance:g} of {visibility_m:g} m visibility calls for fog"
    )


@dataclass
class ConditionSpec:
    """One weather condition of a suite (YAML: an entry of ``conditions:``)."""

    name: str
    """Short name (folder and table column), e.g. ``rain-heavy``."""
    kind: str
    """Weather kinds joined with ``+`` (``rain``, ``fog``, ``rain+fog``; a plugin's, e.g. ``snow+fog``): what is
    synthesised on the clean views."""
    rain: dict[str, Any] | None = None
    """Precipitation source (rain, or a plugin's precipitation such as snow): ``{record: FILE, class: light|moderate|heavy|violent}`` (picked), or ``{record, time}``,
    or ``{precip_mm_h: X}``; optional ``reader``, ``station``."""
    fog: dict[str, Any] | None = None
    """Fog source: ``{record: FILE, visibility_m: TARGET}`` (picked; optional ``tolerance``), or
    ``{record, time}``, or ``{visibility_m: X, explicit: true}``; optional ``reader``, ``station``."""
    family: str = "physical"
    """Weather generator of the degraded photos: ``physical`` (metegs's weather models from θ) or ``independent``
    (`metegs.weather.independent`, made without them); the record sets training's θ either way."""

    def __post_init__(self) -> None:
        if self.family not in FAMILIES:
            raise ConfigError(
                f"condition {self.name!r}: family must be one of {', '.join(FAMILIES)}, got {self.family!r}"
            )
        kinds = parse_kinds(self.kind, f"condition {self.name!r}: kind")
        if kinds & precipitation_kinds() and not self.rain:
            raise ConfigError(
                f"condition {self.name!r}: kind {self.kind} needs a 'rain:' source (the precipitation rate)"
            )
        if "fog" in kinds and not self.fog:
            raise ConfigError(f"condition {self.name!r}: kind {self.kind} needs a 'fog:' source")


@dataclass
class ResolvedCondition:
    """A condition as training runs take it, with where it came from."""

    name: str
    kind: str
    conditions: ConditionsConfig
    """What ``--conditions.*`` of every run of this condition is set to."""
    provenance: dict[str, Any] = field(default_factory=dict)
    """Records, times, rates, visibilities and how they were picked (JSON-safe)."""
    family: str = "physical"
    """Weather generator of the degraded photos (`ConditionSpec.family`)."""

    def to_dict(self) -> dict[str, Any]:
        from metegs.config import to_dict

        return {
            "name": self.name,
            "kind": self.kind,
            "family": self.family,
            "conditions": to_dict(self.conditions),
            **self.provenance,
        }


def _path(value: Any, base: Path | None, where: str) -> Path:
    if value is None:
        raise ConfigError(f"{where}: 'record' is missing")
    p = Path(str(value)).expanduser()
    if not p.is_absolute() and base is not None:
        p = base / p
    if not p.is_file():
        raise ConfigError(f"{where}: record file {p} not found")
    return p


def _known(source: dict, allowed: set[str], where: str) -> None:
    unknown = sorted(set(source) - allowed)
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {', '.join(unknown)}; allowed: {', '.join(sorted(allowed))}")


def resolve_condition(spec: ConditionSpec, base: Path | None = None) -> ResolvedCondition:
    """Pick the record times of ``spec`` and build its `ConditionsConfig` (relative record paths from ``base``)."""
    where = f"condition {spec.name!r}"
    kinds = parse_kinds(spec.kind, f"{where}: kind")
    prov: dict[str, Any] = {}
    record = time = precip = None
    visibility = None
    if kinds & precipitation_kinds():
        src = dict(spec.rain or {})
        _known(src, {"record", "class", "time", "reader", "station", "precip_mm_h"}, f"{where} rain")
        if "precip_mm_h" in src:
            precip = float(src["precip_mm_h"])
            prov["rain"] = {"source": "explicit value", "precip_mm_h": precip}
        else:
            path = _path(src.get("record"), base, f"{where} rain")
            if "time" in src:
                cond = _at_given_time(path, src)
                pick = RainPick(
                    str(path.resolve()),
                    str(src["time"]),
                    float(cond.precip_mm_per_h or 0.0),
                    cond.intensity_class,
                    cond.station,
                )
                how = "given time"
            elif "class" in src:
                pick = pick_rain_hour(path, str(src["class"]), src.get("reader"), src.get("station"))
                how = f"hour nearest {CLASS_TARGET_MM_H[pick.wmo_class]:.2f} mm/h in the WMO {pick.wmo_class} class"
            else:
                raise ConfigError(f"{where} rain: give 'class' (picked from the record), 'time' or 'precip_mm_h'")
            record, time = path, pick.time
            prov["rain"] = {
                "record": pick.record,
                "time": pick.time,
                "precip_mm_h": pick.precip_mm_h,
                "wmo_class": pick.wmo_class,
                "station": pick.station,
                "picked": how,
            }
    if "fog" in kinds:
        src = dict(spec.fog or {})
        _known(src, {"record", "visibility_m", "time", "reader", "station", "tolerance", "explicit"}, f"{where} fog")
        if src.get("explicit") or "record" not in src:
            if "visibility_m" not in src:
                raise ConfigError(
                    f"{where} fog: give 'record' with 'visibility_m' or 'time', or an explicit visibility_m"
                )
            visibility = float(src["visibility_m"])
            prov["fog"] = {"source": "explicit value", "visibility_m": visibility}
        else:
            path = _path(src.get("record"), base, f"{where} fog")
            if "time" in src:
                cond = _at_given_time(path, src)
                if cond.visibility_m is None:
                    raise DataError(path, f"no visibility at {src['time']}")
                pick = FogPick(
                    str(path.resolve()),
                    str(src["time"]),
                    float(cond.visibility_m),
                    cond.fog_kind,
                    [w.code for w in cond.weather],
                    cond.station,
                )
                how = "given time"
            else:
                target = float(src.get("visibility_m", 0) or 0)
                pick = pick_visibility(
                    path, target, src.get("reader"), src.get("station"), float(src.get("tolerance", 1.5))
                )
                how = f"observation nearest {target:g} m that reports fog and no rain"
            visibility = pick.visibility_m
            prov["fog"] = {
                "record": pick.record,
                "time": pick.time,
                "visibility_m": pick.visibility_m,
                "fog_kind": pick.fog_kind,
                "present_weather": pick.present_weather,
                "station": pick.station,
                "picked": how,
            }
            if record is None:  # fog alone: the fog record at its time
                record, time, visibility = path, pick.time, None
    if record is not None:
        conditions = ConditionsConfig(record=record, time=time, visibility_m=visibility)
    else:
        conditions = ConditionsConfig(precip_mm_h=precip or 0.0, visibility_m=visibility)
    return ResolvedCondition(spec.name, spec.kind, conditions, prov, spec.family)
