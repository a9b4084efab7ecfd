"""Every unit conversion of the meteorology package goes through this module (one table per quantity).

Quantities inside metegs are SI-like with the unit in the name: lengths and visibility in metres,
precipitation depth in mm, rates in mm/h, speeds in m/s, directions in degrees the wind blows *from*,
durations in seconds. Factors are exact by definition (inch = 25.4 mm, statute mile = 1609.344 m,
knot = 1852 m / 3600 s).
"""

from __future__ import annotations

import math
import re

from metegs.errors import ConfigError

LENGTH_M: dict[str, float] = {
    "m": 1.0,
    "mm": 1e-3,
    "cm": 1e-2,
    "km": 1e3,
    "in": 0.0254,
    "inch": 0.0254,
    "ft": 0.3048,
    "mi": 1609.344,
    "sm": 1609.344,
}
"""Metres per unit of length (``sm`` = statute mile, as in METAR ``10SM``)."""

SPEED_M_PER_S: dict[str, float] = {
    "m/s": 1.0,
    "ms": 1.0,
    "mps": 1.0,
    "kt": 1852.0 / 3600.0,
    "kn": 1852.0 / 3600.0,
    "knot": 1852.0 / 3600.0,
    "km/h": 1.0 / 3.6,
    "kmh": 1.0 / 3.6,
    "kph": 1.0 / 3.6,
    "mph": 0.44704,
    "mp/h": 0.44704,
}
"""Metres per second per unit of speed (``mp/h`` is Open-Meteo's spelling of mph)."""

DURATION_S: dict[str, float] = {
    "s": 1.0,
    "sec": 1.0,
    "min": 60.0,
    "m": 60.0,
    "h": 3600.0,
    "hr": 3600.0,
    "d": 86400.0,
}
"""Seconds per unit of duration (``m`` means minutes in a duration such as ``30m``)."""

_ALIASES = {
    "millimetre": "mm",
    "millimeter": "mm",
    "millimetres": "mm",
    "millimeters": "mm",
    "centimetre": "cm",
    "centimeter": "cm",
    "metre": "m",
    "meter": "m",
    "metres": "m",
    "meters": "m",
    "kilometre": "km",
    "kilometer": "km",
    "inches": "in",
    "feet": "ft",
    "mile": "mi",
    "miles": "mi",
    "knots": "kt",
    "kts": "kt",
    "m s-1": "m/s",
    "m s^-1": "m/s",
    "km h-1": "km/h",
}


class UnitError(ConfigError):
    """A unit name that does not exist (or belongs to another quantity)."""


def _normalise(unit: str) -> str:
    key = unit.strip().lower()
    return _ALIASES.get(key, key)


def _factor(table: dict[str, float], unit: str, quantity: str) -> float:
    key = _normalise(unit)
    if key not in table:
        raise UnitError(f"unknown {quantity} unit {unit!r}; known: {', '.join(sorted(table))}")
    return table[key]


def length_factor_m(unit: str) -> float:
    """Metres per ``unit`` of length; UnitError names the known units."""
    return _factor(LENGTH_M, unit, "length")


def speed_factor_m_per_s(unit: str) -> float:
    """Metres per second per ``unit`` of speed; UnitError names the known units."""
    return _factor(SPEED_M_PER_S, unit, "speed")


def to_mm(value: float, unit: str) -> float:
    """A precipitation depth (or a rate per hour) in ``unit`` (mm, cm, in, m) converted to mm."""
    return value * length_factor_m(unit) * 1e3


def to_m(value: float, unit: str) -> float:
    """A length (visibility) in ``unit`` (m, km, mi/sm, ft) converted to metres."""
    return value * length_factor_m(unit)


def to_m_per_s(value: float, unit: str) -> float:
    """A speed in ``unit`` (m/s, kt, km/h, mph) converted to m/s."""
    return value * speed_factor_m_per_s(unit)


def check_length_unit(unit: str) -> str:
    """``unit`` if it is a known length unit, else UnitError (used to validate options up front)."""
    length_factor_m(unit)
    return unit


def check_speed_unit(unit: str) -> str:
    """``unit`` if it is a known speed unit, else UnitError."""
    speed_factor_m_per_s(unit)
    return unit


def parse_duration_s(text: str | float | int) -> float:
    """Seconds in a duration such as ``"1h"``, ``"30min"``, ``"1h30min"``, ``"2d"``, or a plain number of seconds."""
    if isinstance(text, (int, float)):
        seconds = float(text)
    else:
        compact = re.sub(r"\s+", "", str(text)).lower()
        if re.fullmatch(r"\d+(\.\d+)?", compact):
            seconds = float(compact)
        elif re.fullmatch(r"(\d+(\.\d+)?[a-z]+)+", compact):
            seconds = 0.0
            for number, _, unit in re.findall(r"(\d+(\.\d+)?)([a-z]+)", compact):
                seconds += float(number) * _factor(DURATION_S, unit, "duration")
        else:
            raise ConfigError(f"cannot read duration {text!r}; write e.g. 1h, 30min, 90s, 1h30min")
    if not math.isfinite(seconds) or seconds < 0:
        raise ConfigError(f"duration {text!r} must be a finite, non-negative time")
    return seconds


COMPASS_POINTS = tuple("N NNE NE ENE E ESE SE SSE S SSW SW WSW W WNW NW NNW".split())
"""The 16 compass points, clockwise from north, 22.5° apart."""


def compass_to_deg(point: str) -> float:
    """Degrees (from north, clockwise) of a compass point such as ``"NNE"``; ``C``/``CALM`` is NaN."""
    key = point.strip().upper()
    if key in ("C", "CALM", "CLM"):
        return math.nan
    if key not in COMPASS_POINTS:
        raise ConfigError(f"unknown compass direction {point!r}; expected one of {' '.join(COMPASS_POINTS)}")
    return COMPASS_POINTS.index(key) * 22.5


def wind_to_deg(dir_from_deg: float) -> float:
    """The direction the wind blows *towards* (deg) from the reported direction it blows *from*."""
    return (dir_from_deg + 180.0) % 360.0
