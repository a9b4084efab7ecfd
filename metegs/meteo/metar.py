"""A small METAR/SPECI decoder (no dependencies): what the weather mapping needs and nothing more.

Decodes station, day/time, wind (``dddffGggKT``/``MPS``/``KMH``, ``VRB``, calm), prevailing visibility
(metres, ``9999``, ``CAVOK``, ``NDV``, statute miles with fractions ``1 1/2SM``, ``M1/4SM``, ``P6SM``),
present weather with intensity, and the US remark groups ``Prrrr`` / ``6RRRR`` / ``7RRRR``
(hundredths of an inch; FMH-1). Trend groups (``TEMPO``, ``BECMG``, ``NOSIG``) are forecasts and are
not read. Why not a library: MetPy drops unparsable reports silently and needs the network on first
use; python-``metar`` is not installed here (research note §6.6).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from datetime import datetime, timezone

from metegs.meteo import limits, units
from metegs.meteo.weather_codes import PresentWeather, parse_weather_token


class MetarError(ValueError):
    """A report that cannot be decoded (the reader skips and counts it)."""


@dataclass
class MetarReport:
    """The decoded groups of one report (units in the names)."""

    station: str
    """ICAO identifier."""
    time_utc: datetime
    """Observation time (year and month given by the caller)."""
    report_type: str = "METAR"
    """``METAR`` or ``SPECI``."""
    wind_dir_deg_from: float | None = None
    """Direction the wind blows from, degrees; None for calm, ``VRB`` or missing."""
    wind_speed_m_per_s: float | None = None
    """Mean wind speed, m/s."""
    wind_gust_m_per_s: float | None = None
    """Gust speed, m/s."""
    visibility_m: float | None = None
    """Prevailing visibility, m."""
    visibility_at_least: bool = False
    """``9999``, ``CAVOK``, ``10SM``, ``P6SM``: a lower bound."""
    visibility_below: bool = False
    """``M1/4SM``, ``0000``: an upper bound."""
    weather: tuple[PresentWeather, ...] = ()
    """Present-weather groups of the body (not of the trend)."""
    precip_hourly_in: float | None = None
    """``Prrrr``: amount since the last routine report, inches (0 with ``precip_hourly_trace`` for ``P0000``)."""
    precip_hourly_trace: bool = False
    """``P0000``: a trace."""
    precip_3_6_hour_in: float | None = None
    """``6RRRR``: the 3-h (03/09/15/21 UTC) or 6-h (00/06/12/18 UTC) amount, inches."""
    precip_3_6_hour_trace: bool = False
    """``60000``: a trace."""
    precip_24_hour_in: float | None = None
    """``7RRRR``: the 24-h amount, inches."""
    unread: list[str] = field(default_factory=list)
    """Body groups that were not decoded (clouds, temperature, pressure are not needed)."""


_STATION = re.compile(r"^[A-Z][A-Z0-9]{3}$")
_TIME = re.compile(r"^(\d{2})(\d{2})(\d{2})Z$")
_WIND = re.compile(r"^(\d{3}|VRB|///)(\d{2,3}|//)(?:G(\d{2,3}))?(KT|MPS|KMH)$")
_WIND_VAR = re.compile(r"^\d{3}V\d{3}$")
_VIS_M = re.compile(r"^(\d{4})(NDV)?$")
_VIS_DIR = re.compile(r"^\d{4}(N|NE|E|SE|S|SW|W|NW)$")
_VIS_SM = re.compile(r"^([MP])?(\d+)?(?:(\d)/([1-9]\d?))?SM$")
_TREND = ("TEMPO", "BECMG", "NOSIG", "INTER", "PROB30", "PROB40")
_WHOLE = re.compile(r"^\d$")


def parse_metar(text: str, *, year: int, month: int, report_type: str = "METAR") -> MetarReport:
    """Decode one report (without the trailing ``=``); MetarError says why it cannot be read."""
    tokens = text.replace("=", " ").split()
    if not tokens:
        raise MetarError("empty report")
    while tokens and tokens[0] in ("METAR", "SPECI", "COR", "AMD"):
        if tokens[0] in ("METAR", "SPECI"):
            report_type = tokens[0]
        tokens.pop(0)
    if not tokens or not _STATION.match(tokens[0]):
        raise MetarError(f"no station identifier at the start ({' '.join(tokens[:3])!r})")
    station = tokens.pop(0)
    if not tokens or not (m := _TIME.match(tokens[0])):
        raise MetarError(f"{station}: no time group ddhhmmZ ({tokens[0] if tokens else 'end of report'!r})")
    tokens.pop(0)
    day, hour, minute = (int(g) for g in m.groups())
    try:
        time_utc = datetime(year, month, day, hour, minute, tzinfo=timezone.utc)
    except ValueError as exc:
        raise MetarError(f"{station}: impossible time {m.group(0)} in {year}-{month:02d} ({exc})") from None
    if tokens and tokens[0] == "NIL":
        raise MetarError(f"{station}: NIL report (no observation)")
    report = MetarReport(station, time_utc, report_type)
    if "RMK" in tokens:
        i = tokens.index("RMK")
        body, remarks = tokens[:i], tokens[i + 1 :]
    else:
        body, remarks = tokens, []
    decoded = _decode_body(body, report)
    decoded += _decode_remarks(remarks, report)
    if decoded == 0:
        raise MetarError(f"{station} {m.group(0)}: no wind, visibility, weather or precipitation group")
    return report


def _decode_body(body: list[str], r: MetarReport) -> int:
    decoded = 0
    weather: list[PresentWeather] = []
    i = 0
    while i < len(body):
        tok = body[i]
        i += 1
        if tok in _TREND or tok.startswith(("FM", "TL")) and tok[2:].isdigit():
            break  # trend forecast: not an observation
        if tok in ("AUTO", "COR"):
            continue
        if tok in ("KT", "MPS", "/////KT"):
            continue  # wind group present but missing
        if (m := _WIND.match(tok)) and r.wind_speed_m_per_s is None:
            direction, speed, gust, unit = m.groups()
            if speed != "//":
                r.wind_speed_m_per_s = units.to_m_per_s(float(speed), unit)
                if gust:
                    r.wind_gust_m_per_s = units.to_m_per_s(float(gust), unit)
                if direction not in ("VRB", "///") and float(speed) > 0:
                    r.wind_dir_deg_from = float(direction) % 360.0
                decoded += 1
            continue
        if _WIND_VAR.match(tok):
            continue
        if tok == "CAVOK" and r.visibility_m is None:
            r.visibility_m, r.visibility_at_least = 10000.0, True
            decoded += 1
            continue
        if (m := _VIS_M.match(tok)) and r.visibility_m is None:
            metres = float(m.group(1))
            if metres >= 9999:
                r.visibility_m, r.visibility_at_least = 10000.0, True
            elif metres == 0:
                r.visibility_m, r.visibility_below = limits.ZERO_VISIBILITY_M, True
            else:
                r.visibility_m = metres
            decoded += 1
            continue
        if _VIS_DIR.match(tok):
            if r.visibility_m is None:
                r.visibility_m = float(tok[:4])
                decoded += 1
            continue
        if _WHOLE.match(tok) and i < len(body) and (m := _VIS_SM.match(body[i])) and m.group(2) is None and m.group(3):
            # "1 1/2SM": whole miles, then the fraction
            miles = float(tok) + float(m.group(3)) / float(m.group(4))
            i += 1
            _set_vis_sm(r, miles, m.group(1))
            decoded += 1
            continue
        if (m := _VIS_SM.match(tok)) and r.visibility_m is None:
            prefix, whole, num, den = m.groups()
            if whole is None and num is None:
                continue
            miles = float(whole or 0) + (float(num) / float(den) if num else 0.0)
            _set_vis_sm(r, miles, prefix)
            decoded += 1
            continue
        if tok.startswith("R") and "/" in tok:
            continue  # runway visual range
        if tok.strip("/") == "":
            continue  # ////// : not available
        wx = parse_weather_token(tok)
        if wx is not None:
            weather.append(wx)
            decoded += 1
            continue
        if tok == "NSW":
            continue
        r.unread.append(tok)
    r.weather = tuple(weather)
    return decoded


def _set_vis_sm(r: MetarReport, miles: float, prefix: str | None) -> None:
    r.visibility_m = units.to_m(miles, "sm")
    if prefix == "P" or (prefix is None and miles >= 10):
        r.visibility_at_least = True  # US reports stop at 10SM
    elif prefix == "M":
        r.visibility_below = True


_P_GROUP = re.compile(r"^P(\d{4}|////)$")
_6_GROUP = re.compile(r"^6(\d{4}|////)$")
_7_GROUP = re.compile(r"^7(\d{4}|////)$")


def _decode_remarks(remarks: list[str], r: MetarReport) -> int:
    decoded = 0
    for tok in remarks:
        if (m := _P_GROUP.match(tok)) and r.precip_hourly_in is None:
            if m.group(1) != "////":
                r.precip_hourly_in = int(m.group(1)) / 100.0
                r.precip_hourly_trace = r.precip_hourly_in == 0
                decoded += 1
        elif (m := _6_GROUP.match(tok)) and r.precip_3_6_hour_in is None:
            if m.group(1) != "////":
                r.precip_3_6_hour_in = int(m.group(1)) / 100.0
                r.precip_3_6_hour_trace = r.precip_3_6_hour_in == 0
                decoded += 1
        elif (m := _7_GROUP.match(tok)) and r.precip_24_hour_in is None:
            if m.group(1) != "////":
                r.precip_24_hour_in = int(m.group(1)) / 100.0
                decoded += 1
    return decoded


_HEADING = re.compile(r"^[A-Z]{4}\d{0,2} [A-Z]{4} \d{6}( [A-Z]{3})?$")
_SEQUENCE = re.compile(r"^\d{3,4}$")


def split_bulletin(text: str) -> list[tuple[int, str, str]]:
    """The reports of a bulletin or collective as (first line number, report type, report text).

    Control characters (SOH/ETX, NUL), carriage returns and non-ASCII bytes are dropped; WMO headings,
    sequence numbers and bare ``METAR``/``SPECI`` lines are not reports; an indented line continues the
    report above it; ``=`` ends a report.
    """
    cleaned = "".join(ch if (ch == "\n" or 32 <= ord(ch) < 127) else " " for ch in text.replace("\r", ""))
    reports: list[tuple[int, str, str]] = []
    current: list[str] = []
    start_line = 0
    kind = "METAR"
    current_kind = kind

    def flush() -> None:
        nonlocal current
        joined = " ".join(current).strip()
        if joined:
            reports.append((start_line, current_kind, joined))
        current = []

    for number, raw in enumerate(cleaned.split("\n"), start=1):
        line = raw.rstrip()
        stripped = line.strip()
        if not stripped:
            continue
        if stripped in ("METAR", "SPECI") and not current:
            kind = stripped
            continue
        if not current and (
            _SEQUENCE.match(stripped) or _HEADING.match(stripped) or re.fullmatch(r"[A-Z0-9]{4,6}", stripped)
        ):
            continue
        continuation = line[:1].isspace() and current
        if not continuation and current:
            flush()
        if not current:
            start_line, current_kind = number, kind
        current.append(stripped)
        if stripped.endswith("="):
            flush()
    flush()
    return reports
