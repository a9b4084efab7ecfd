"""Every reader on its real file from ../shared/data/meteo, with hand-checked records named below.

Expected values were computed by hand from the raw lines quoted in each test.
"""

from __future__ import annotations

from datetime import datetime, timezone

import pytest

from metegs.meteo import MeteoWarning, detect_reader, read_observations
from metegs.meteo.storm import STORM_READER_OPTIONS
from metegs.registry import registry

from .conftest import shared_file

pytestmark = pytest.mark.data

UTC = timezone.utc


def by_line(table, line):
    matches = [r for r in table if r.line == line]
    assert len(matches) == 1, f"no single record from line {line}"
    return matches[0]


def test_readers_are_registered():
    names = registry("meteo_reader").names()
    for name in ("csv", "metar", "ghcnh", "isd", "open-meteo"):
        assert name in names
        assert registry("meteo_reader").get(name).name == name


@pytest.fixture(scope="module")
def beijing():
    path = shared_file("beijing-prsa", "PRSA_Data_Aotizhongxin_20130301-20170228.csv")
    return read_observations(path, reader="csv", **STORM_READER_OPTIONS)


def test_csv_reads_beijing_with_options_alone(beijing):
    assert len(beijing) == 35064 and beijing.stations == ["Aotizhongxin"]
    # line 2: 1,2013,3,1,0,...,RAIN 0,"NNW",4.4 -> 2013-03-01 00:00 Beijing = 2013-02-28 16:00 UTC
    r = by_line(beijing, 2)
    assert r.time_utc == datetime(2013, 2, 28, 16, 0, tzinfo=UTC)
    assert r.precip_accum_mm == 0.0 and r.precip_period_h == 1.0
    assert r.wind_speed_m_per_s == 4.4 and r.wind_dir_deg_from == 337.5
    # line 3929: 3928,2013,8,11,15,...,RAIN 72.5,"NNE",3.9 (the violent hour of the shipped storm)
    r = by_line(beijing, 3929)
    assert r.time_utc == datetime(2013, 8, 11, 7, 0, tzinfo=UTC)
    assert r.precip_accum_mm == 72.5 and r.wind_dir_deg_from == 22.5 and r.wind_speed_m_per_s == 3.9
    # line 31049: 31048,2016,9,14,15,...,RAIN NA,"SW",3.1 -> a gap, not a zero
    r = by_line(beijing, 31049)
    assert r.time_utc == datetime(2016, 9, 14, 7, 0, tzinfo=UTC)
    assert r.precip_accums == () and r.precip_accum_mm is None
    assert r.wind_dir_deg_from == 225.0 and r.wind_speed_m_per_s == 3.1


def test_metar_reads_a_real_collective():
    path = shared_file("metar-pyiem", "collective.txt")
    assert detect_reader(path) == "metar"
    with pytest.warns(MeteoWarning, match=r"skipped 4 of 14 records.*QQQQ"):
        table = read_observations(path, year=2024, month=6)
    # line 5: KSPS 081352Z 10015KT 10SM TSGRRA ... RMK ... P0000
    r = by_line(table, 5)
    assert (r.station, r.time_utc) == ("KSPS", datetime(2024, 6, 8, 13, 52, tzinfo=UTC))
    assert r.wind_dir_deg_from == 100 and r.wind_speed_m_per_s == pytest.approx(15 * 1852 / 3600)
    assert r.visibility_m == pytest.approx(16093.44) and r.visibility_at_least
    assert [w.code for w in r.weather] == ["TSGRRA"]
    assert r.precip_accums[0].trace and r.precip_accums[0].amount_mm == 0
    # line 7: KMIA 081403Z 16032G45KT 1/2SM +FC +TSRA BR ... P0046
    r = by_line(table, 7)
    assert r.wind_dir_deg_from == 160 and r.wind_gust_m_per_s == pytest.approx(45 * 1852 / 3600)
    assert r.visibility_m == pytest.approx(804.672) and not r.visibility_at_least
    assert [w.code for w in r.weather] == ["+FC", "+TSRA", "BR"]
    assert r.precip_accum_mm == pytest.approx(11.684) and r.precip_period_h == 1.0
    # line 27: KALO 081354Z AUTO 18016KT 4SM RA BR ... P0009
    r = by_line(table, 27)
    assert r.wind_speed_m_per_s == pytest.approx(16 * 1852 / 3600) and r.wind_dir_deg_from == 180
    assert r.visibility_m == pytest.approx(4 * 1609.344)
    assert [(w.code, w.intensity) for w in r.weather] == [("RA", "moderate"), ("BR", "")]
    assert r.precip_accum_mm == pytest.approx(2.286)


def test_metar_six_hour_group_in_a_00_utc_report():
    path = shared_file("metar-pyiem", "collective2.txt")
    with pytest.warns(MeteoWarning, match="skipped 1 of 35"):  # KDMH: no group we can use
        table = read_observations(path, year=2024, month=1)
    r = table.for_station("KSYR").records[0]  # line 62: KSYR 312354Z ... 60006
    assert r.line == 62 and r.precip_accums[0].label == "6"
    assert r.precip_accums[0].period_h == 6.0 and r.precip_accums[0].amount_mm == pytest.approx(1.524)


def test_ghcnh_reads_real_psv():
    path = shared_file("ghcnh-pyiem", "GHCNh_USW00024135_por.psv")
    assert detect_reader(path) == "ghcnh"
    table = read_observations(path)
    # line 3: 2025-01-05 21:53 METAR KBTM 2SM -SN BR; precipitation 0.0 "2-Trace"; visibility 3.219 km; 300 deg 1.5 m/s
    r = by_line(table, 3)
    assert r.time_utc == datetime(2025, 1, 5, 21, 53, tzinfo=UTC)
    assert r.visibility_m == pytest.approx(3219.0) and r.wind_dir_deg_from == 300 and r.wind_speed_m_per_s == 1.5
    assert {w.code for w in r.weather} == {"-SN", "BR"}
    assert r.precip_accums[0].trace and r.precip_period_h == 1.0
    # line 5: SPECI KBTM 011820Z 1/2SM SN FZFG, precipitation 0.2 mm (P0001) since the 17:53 routine report
    r = by_line(table, 5)
    assert r.report_type == "SPECI" and r.visibility_m == pytest.approx(805.0)
    assert r.precip_accum_mm == 0.2 and r.precip_period_h == pytest.approx(27 / 60)
    assert {"SN", "FZFG"} <= {w.code for w in r.weather}
    # line 6: wind fields empty, precipitation 0.0 marked "9-Missing" -> not reported
    r = by_line(table, 6)
    assert r.precip_accums == () and r.wind_speed_m_per_s is None and r.visibility_at_least


def test_ghcnh_missing_code_and_short_line():
    path = shared_file("ghcnh-pyiem", "GHCNh_USW00013967_por.psv")
    with pytest.warns(MeteoWarning, match="skipped 1 of 5 records.*line 6"):
        table = read_observations(path)
    # line 3: precipitation 0.0 "9-Missing" but precipitation_24_hour 1.7 "3-Measurab"
    r = by_line(table, 3)
    assert [(a.amount_mm, a.period_h) for a in r.precip_accums] == [(1.7, 24.0)]
    assert [r.line for r in table] == [5, 3, 2, 4]  # sorted by time (the file is not)


def test_ghcnh_implausible_visibility_is_counted():
    path = shared_file("ghcnh-pyiem", "GHCNh_FPI0000NTAT_por.psv")
    with pytest.warns(MeteoWarning, match="implausible.*20000 km"):
        table = read_observations(path)
    assert table[0].visibility_m is None and table[0].precip_accums[1].period_h == 3.0


def test_isd_reads_real_ds3505():
    path = shared_file("isd-janmayen-1988", "DS3505.txt")
    assert detect_reader(path) == "isd"
    table = read_observations(path)
    assert len(table) == 2907 and table.stations == ["010010-99999"]
    # line 1: 19880101 0000 ... wind 330,1,N,0185 vis 003000 ... AA1 06 0000 9 1 ... MW1 38 (blowing snow)
    r = by_line(table, 1)
    assert r.time_utc == datetime(1988, 1, 1, 0, 0, tzinfo=UTC)
    assert r.wind_dir_deg_from == 330 and r.wind_speed_m_per_s == 18.5 and r.visibility_m == 3000
    assert (r.precip_accum_mm, r.precip_period_h) == (0.0, 6.0)
    assert [(w.code, w.wmo_code) for w in r.weather] == [("BLSN", 38)]
    # line 352: 19880214 0000 ... 140,1,N,0021 vis 003000 ... AA1 06 0030 9 1 ... MW1 63 (moderate rain)
    r = by_line(table, 352)
    assert r.wind_speed_m_per_s == 2.1 and r.wind_dir_deg_from == 140 and r.visibility_m == 3000
    assert (r.precip_accum_mm, r.precip_period_h) == (3.0, 6.0)
    assert [(w.code, w.intensity) for w in r.weather] == [("RA", "moderate")]
    # line 928: 19880426 1500 ... 150,1,N,0010 vis 000300 ... MW1 45 (fog), no AA group
    r = by_line(table, 928)
    assert r.visibility_m == 300 and r.wind_speed_m_per_s == 1.0 and r.precip_accums == ()
    assert [w.kinds for w in r.weather] == [frozenset({"fog"})]
