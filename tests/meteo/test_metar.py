"""The METAR decoder on hand-written reports (research note §8.5 fixtures and the awkward tokens)."""

from __future__ import annotations

import pytest

from metegs.meteo import physics
from metegs.meteo.metar import MetarError, parse_metar, split_bulletin
from metegs.meteo.weather_codes import parse_weather_token, weather_from_synop


def metar(text: str):
    return parse_metar(text, year=2024, month=7)


def test_p_group_is_hundredths_of_an_inch():
    r = metar("KXYZ 011253Z 27005KT 3SM RA BR OVC008 18/17 A2992 RMK AO2 P0025 T01830172")
    assert r.precip_hourly_in == pytest.approx(0.25)
    assert r.precip_hourly_in * 25.4 == pytest.approx(6.35)  # §8.5: P0025 -> 6.35 mm/h
    assert not r.precip_hourly_trace


def test_trace_and_six_hour_groups():
    r = metar("KXYZ 312354Z 24008KT 10SM OVC025 01/M02 A2958 RMK AO2 P0000 60012 70034")
    assert r.precip_hourly_in == 0 and r.precip_hourly_trace
    assert r.precip_3_6_hour_in == pytest.approx(0.12)
    assert r.precip_24_hour_in == pytest.approx(0.34)


def test_quarter_mile_fog():
    r = metar("KXYZ 011253Z 00000KT 1/4SM FG VV002 12/12 A3001")
    assert r.visibility_m == pytest.approx(402.336)
    assert physics.beta_from_visibility_per_m(r.visibility_m) == pytest.approx(0.00745, abs=1e-5)  # §8.5
    assert [w.code for w in r.weather] == ["FG"]
    assert r.wind_speed_m_per_s == 0 and r.wind_dir_deg_from is None


@pytest.mark.parametrize("vis", ["9999", "CAVOK"])
def test_at_least_visibility_means_no_fog(vis):
    r = metar(f"EDDF 011250Z 24010KT {vis} 22/12 Q1015")
    assert r.visibility_at_least and r.visibility_m == 10000


def test_statute_mile_forms():
    assert metar("KXYZ 011253Z 18010KT 1 1/2SM -RA BR OVC010 A2992").visibility_m == pytest.approx(1.5 * 1609.344)
    low = metar("KXYZ 011253Z 18010KT M1/4SM +RA FG OVC001 A2992")
    assert low.visibility_below and low.visibility_m == pytest.approx(402.336)
    assert metar("KXYZ 011253Z 18010KT P6SM SKC A2992").visibility_at_least
    assert metar("KXYZ 011253Z 18010KT 10SM SKC A2992").visibility_at_least


def test_wind_forms():
    r = metar("EGLL 011250Z 27012G25KT 9999 FEW030 20/10 Q1012")
    assert r.wind_dir_deg_from == 270
    assert r.wind_speed_m_per_s == pytest.approx(12 * 0.514444, rel=1e-4)
    assert r.wind_gust_m_per_s == pytest.approx(25 * 0.514444, rel=1e-4)
    assert metar("UUEE 011230Z 09005MPS 9999 15/10 Q1015").wind_speed_m_per_s == 5.0
    vrb = metar("KXYZ 011253Z VRB03KT 10SM CLR A2992")
    assert vrb.wind_dir_deg_from is None and vrb.wind_speed_m_per_s > 0


def test_present_weather_intensity_and_trend_not_read():
    r = metar("LFBD 020100Z AUTO 26006KT 4000 -SHRA BR BKN019 15/14 Q1013 TEMPO 2000 +TSRA")
    assert [(w.code, w.intensity) for w in r.weather] == [("-SHRA", "light"), ("BR", "")]
    assert r.visibility_m == 4000  # the TEMPO group is a forecast


def test_intensity_tokens():
    heavy = parse_weather_token("+TSRA")
    assert heavy.descriptor == "TS" and heavy.phenomena == ("RA",) and heavy.intensity == "heavy"
    assert heavy.representative_rate_mm_per_h == 75.0  # +TSRA: cloud burst
    assert parse_weather_token("+RA").representative_rate_mm_per_h == 22.0  # §8.5: +RA -> 22 mm/h
    assert parse_weather_token("-DZ").representative_rate_mm_per_h == 0.05
    vc = parse_weather_token("VCSH")
    assert vc.vicinity and not vc.at_station and vc.representative_rate_mm_per_h is None
    assert parse_weather_token("BKN020") is None and parse_weather_token("RERA") is None
    assert weather_from_synop(63).code == "RA" and weather_from_synop(82).intensity == "violent"
    assert weather_from_synop(45).kinds == {"fog"} and weather_from_synop(2) is None


@pytest.mark.parametrize(
    "text",
    [
        "QQQQ O81354Z AUTO 17027G37KT",
        "1QQQ 081354Z AUTO 17027G37KT",
        "QQQQ 081354Z",
        "KXYZ 011253Z NIL",
        "KXYZ 321253Z 18010KT 10SM",
    ],
)
def test_unreadable_reports_raise(text):
    with pytest.raises(MetarError):
        metar(text)


def test_split_bulletin_handles_headers_continuations_and_junk():
    text = "\x01\r\r\n776 \r\r\nSAUS70 KWBC 081400\r\r\nMETAR\r\r\nKAAA 081352Z 10015KT 10SM RMK AO2\r\r\n     P0003=\r\r\nSPECI KBBB 081401Z AUTO 17004KT 5SM BR RMK\x00A)&H $\n\x03"
    reports = split_bulletin(text)
    assert [(line, kind) for line, kind, _ in reports] == [(5, "METAR"), (7, "METAR")]
    assert reports[0][2].endswith("P0003=")
    assert parse_metar(reports[1][2], year=2024, month=1, report_type=reports[1][1]).report_type == "SPECI"
