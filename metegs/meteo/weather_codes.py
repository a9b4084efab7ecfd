"""Present weather: METAR tokens (WMO code table 4678) and SYNOP ``ww`` codes (table 4677) in one form.

Sources: WMO-No. 306 *Manual on Codes* tables 4677/4678; ICAO Annex 3 App. 3 §4.4 (FG/BR/HZ); the
representative rates per intensity qualifier are the geometric means of the WMO classes
(research note ``meteorology.md`` §1.5).
"""

from __future__ import annotations

import re
from dataclasses import dataclass

PRECIPITATION = ("DZ", "RA", "SN", "SG", "IC", "PL", "GR", "GS", "UP")
OBSCURATION = ("BR", "FG", "FU", "VA", "DU", "SA", "HZ", "PY")
OTHER = ("PO", "SQ", "FC", "SS", "DS")
DESCRIPTORS = ("MI", "PR", "BC", "DR", "BL", "SH", "TS", "FZ")

_KIND = {
    "RA": "rain",
    "DZ": "drizzle",
    "SN": "snow",
    "SG": "snow",
    "IC": "ice",
    "PL": "ice",
    "GR": "ice",
    "GS": "ice",
    "UP": "precipitation",
    "BR": "mist",
    "FG": "fog",
    "HZ": "haze",
    "FU": "smoke",
    "VA": "dust",
    "DU": "dust",
    "SA": "dust",
    "PY": "spray",
    "SH": "showers",
    "TS": "thunder",
}

_TOKEN = re.compile(
    r"^(?P<intensity>[-+]|VC)?(?P<descriptor>MI|PR|BC|DR|BL|SH|TS|FZ)?"
    r"(?P<phenomena>(?:DZ|RA|SN|SG|IC|PL|GR|GS|UP|BR|FG|FU|VA|DU|SA|HZ|PY|PO|SQ|FC|SS|DS)*)$"
)

INTENSITY_OF_SIGN = {"-": "light", "": "moderate", "+": "heavy"}

REPRESENTATIVE_RATE_MM_PER_H: dict[tuple[str, str], float] = {
    ("drizzle", "light"): 0.05,
    ("drizzle", "moderate"): 0.22,
    ("drizzle", "heavy"): 0.7,
    ("rain", "light"): 0.8,
    ("rain", "moderate"): 5.0,
    ("rain", "heavy"): 22.0,
    ("rain", "violent"): 75.0,
}
"""Rate (mm/h) to use when only an intensity qualifier is known: the geometric mean of each WMO class
(light rain: √(0.25·2.5) with a 0.25 mm/h floor); research note §1.5 [D]."""


@dataclass(frozen=True)
class PresentWeather:
    """One present-weather group, e.g. ``-SHRA`` (light rain showers) or ``BR`` (mist)."""

    code: str
    """The group as METAR writes it (``-SHRA``, ``+TSRA``, ``FZFG``, ``BR``); SYNOP codes are translated."""
    intensity: str = ""
    """``light``, ``moderate``, ``heavy`` or ``violent`` for precipitation; ``""`` for obscurations."""
    descriptor: str = ""
    """``SH`` showers, ``TS`` thunderstorm, ``FZ`` freezing, ``MI``/``BC``/``PR`` shallow/patches/partial, ..."""
    phenomena: tuple[str, ...] = ()
    """Two-letter phenomena in order (``RA``, ``DZ``, ``SN``, ``BR``, ``FG``, ``HZ``, ...)."""
    vicinity: bool = False
    """``VC``: seen in the vicinity (8-16 km), not at the station."""
    wmo_code: int | None = None
    """The SYNOP ``ww`` code (WMO table 4677) when the group came from one."""

    @property
    def kinds(self) -> frozenset[str]:
        """What it is: a subset of rain, drizzle, snow, ice, precipitation, showers, thunder, mist, fog, haze, smoke, dust, spray."""
        out = {_KIND[p] for p in self.phenomena if p in _KIND}
        if self.descriptor in _KIND:
            out.add(_KIND[self.descriptor])
        return frozenset(out)

    @property
    def at_station(self) -> bool:
        """False for vicinity (``VC``) groups, which say nothing about the air at the camera."""
        return not self.vicinity

    @property
    def is_precipitation(self) -> bool:
        return any(p in PRECIPITATION for p in self.phenomena)

    @property
    def is_obscuration(self) -> bool:
        return any(p in OBSCURATION for p in self.phenomena)

    @property
    def liquid_kind(self) -> str | None:
        """``rain`` (rain, showers of rain, thunderstorm with rain), ``drizzle`` or None."""
        if "RA" in self.phenomena or "UP" in self.phenomena:
            return "rain"
        if "DZ" in self.phenomena:
            return "drizzle"
        return None

    @property
    def representative_rate_mm_per_h(self) -> float | None:
        """A rate for this group when no amount is measured (§1.5), or None (snow, fog, vicinity)."""
        kind = self.liquid_kind
        if kind is None or self.vicinity:
            return None
        intensity = self.intensity or "moderate"
        if kind == "drizzle" and intensity == "violent":
            intensity = "heavy"
        if kind == "rain" and self.descriptor == "TS" and intensity == "heavy":
            intensity = "violent"  # +TSRA: cloud burst (§1.5)
        return REPRESENTATIVE_RATE_MM_PER_H[(kind, intensity)]


def parse_weather_token(token: str) -> PresentWeather | None:
    """A METAR present-weather group, or None if ``token`` is not one (``NSW`` gives None as well)."""
    token = token.strip().upper()
    if not token or token.startswith("RE") or token == "NSW":
        return None
    m = _TOKEN.match(token)
    if m is None:
        return None
    descriptor = m.group("descriptor") or ""
    phen_text = m.group("phenomena")
    phenomena = tuple(phen_text[i : i + 2] for i in range(0, len(phen_text), 2))
    if not descriptor and not phenomena:
        return None
    sign = m.group("intensity") or ""
    vicinity = sign == "VC"
    has_precip = any(p in PRECIPITATION for p in phenomena)
    intensity = INTENSITY_OF_SIGN.get("" if vicinity else sign, "") if has_precip else ""
    return PresentWeather(token, intensity, descriptor, phenomena, vicinity)


def _pw(code: str, ww: int, intensity: str | None = None) -> PresentWeather:
    base = parse_weather_token(code)
    assert base is not None, code
    return PresentWeather(
        base.code,
        intensity if intensity is not None else base.intensity,
        base.descriptor,
        base.phenomena,
        base.vicinity,
        ww,
    )


def _synop_table() -> dict[int, PresentWeather]:
    t: dict[int, PresentWeather] = {}
    t[4] = _pw("FU", 4)
    t[5] = _pw("HZ", 5)
    for ww in (6, 7, 8, 9):
        t[ww] = _pw("DU", ww)
    t[10] = _pw("BR", 10)
    t[11] = _pw("BCFG", 11)
    t[12] = _pw("MIFG", 12)
    t[17] = _pw("TS", 17)
    t[18] = _pw("SQ", 18)
    t[19] = _pw("FC", 19)
    for ww in range(30, 36):
        t[ww] = _pw("DS", ww)
    for ww in (36, 37):
        t[ww] = _pw("DRSN", ww)
    for ww in (38, 39):
        t[ww] = _pw("BLSN", ww)
    t[40] = _pw("VCFG", 40)
    t[41] = _pw("BCFG", 41)
    for ww in range(42, 48):
        t[ww] = _pw("FG", ww)
    for ww in (48, 49):
        t[ww] = _pw("FZFG", ww)
    for ww, code in ((50, "-DZ"), (51, "-DZ"), (52, "DZ"), (53, "DZ"), (54, "+DZ"), (55, "+DZ")):
        t[ww] = _pw(code, ww)
    t[56], t[57] = _pw("-FZDZ", 56), _pw("FZDZ", 57)
    t[58], t[59] = _pw("-RADZ", 58), _pw("RADZ", 59)
    for ww, code in ((60, "-RA"), (61, "-RA"), (62, "RA"), (63, "RA"), (64, "+RA"), (65, "+RA")):
        t[ww] = _pw(code, ww)
    t[66], t[67] = _pw("-FZRA", 66), _pw("FZRA", 67)
    t[68], t[69] = _pw("-RASN", 68), _pw("RASN", 69)
    for ww, code in ((70, "-SN"), (71, "-SN"), (72, "SN"), (73, "SN"), (74, "+SN"), (75, "+SN")):
        t[ww] = _pw(code, ww)
    t[76], t[77], t[78], t[79] = _pw("IC", 76), _pw("SG", 77), _pw("SN", 78), _pw("PL", 79)
    t[80], t[81], t[82] = _pw("-SHRA", 80), _pw("SHRA", 81), _pw("+SHRA", 82, "violent")
    t[83], t[84] = _pw("-SHRASN", 83), _pw("SHRASN", 84)
    t[85], t[86] = _pw("-SHSN", 85), _pw("SHSN", 86)
    t[87], t[88], t[89], t[90] = _pw("-SHGS", 87), _pw("SHGS", 88), _pw("-SHGR", 89), _pw("SHGR", 90)
    t[91], t[92] = _pw("-RA", 91), _pw("RA", 92)
    t[93], t[94] = _pw("-SN", 93), _pw("SN", 94)
    t[95], t[96], t[97] = _pw("TSRA", 95), _pw("TSGR", 96), _pw("+TSRA", 97)
    t[98], t[99] = _pw("TSDS", 98), _pw("+TSGR", 99)
    return t


SYNOP_WW: dict[int, PresentWeather] = _synop_table()
"""WMO table 4677 ``ww`` → present weather. Codes 00-03 (cloud development), 13-16 (lightning,
precipitation in sight) and 20-29 (weather of the past hour, not at observation time) carry no present
weather at the station and are absent."""


def weather_from_synop(ww: int) -> PresentWeather | None:
    """The present weather of a SYNOP ``ww`` code (0-99), or None if the code reports none at the station."""
    if not 0 <= ww <= 99:
        raise ValueError(f"SYNOP ww code {ww} is outside 00-99")
    return SYNOP_WW.get(ww)
