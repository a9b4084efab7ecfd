"""The csv reader finds the time, precipitation, visibility and wind columns from the header by itself."""

import json

import pytest

from metegs.cli.meteo import main
from metegs.errors import DataError
from metegs.meteo import read_observations
from metegs.meteo.readers.csv_reader import csv_options, detect_columns
from metegs.meteo.storm import default_storm_path
from metegs.meteo.theta_plan import load_record


def write(tmp_path, text: str, name: str = "station.csv"):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_iem_metar_csv_with_units_from_the_names(tmp_path):
    path = write(
        tmp_path,
        "station,valid,tmpf,sknt,drct,p01i,vsby\n"
        "KXYZ,2024-01-01 00:53,40.0,10,270,0.10,2.00\n"
        "KXYZ,2024-01-01 01:53,39.0,M,VRB,T,10.00\n",
        "iem.csv",
    )
    table = read_observations(path)
    first, second = table.records
    assert table.reader == "csv" and first.station == "KXYZ"
    assert first.time_utc.isoformat() == "2024-01-01T00:53:00+00:00"
    assert first.precip_accums[0].amount_mm == pytest.approx(2.54)  # inches -> mm
    assert first.visibility_m == pytest.approx(2 * 1609.344)  # statute miles -> m
    assert first.wind_speed_m_per_s == pytest.approx(10 * 1852 / 3600)  # knots -> m/s
    assert first.wind_dir_deg_from == 270.0
    assert second.precip_accums[0].amount_mm == 0.0  # T: trace
    assert second.wind_speed_m_per_s is None and second.wind_dir_deg_from is None  # M: missing, VRB
    assert "precip_column=p01i (in)" in table.notes[0] and "visibility_column=vsby (mi)" in table.notes[0]


def test_daily_csv_with_slashed_dates(tmp_path):
    path = write(tmp_path, "date,prcp\n2012/01/01,3.5\n2012/01/02,0\n2012/01/04,12.0\n", "daily.csv")
    table = read_observations(path)
    assert [r.time_utc.date().isoformat() for r in table] == ["2012-01-01", "2012-01-02", "2012-01-04"]
    assert all(r.precip_accums[0].period_h == 24.0 for r in table)
    assert any("daily record" in n for n in table.notes)


def test_capitalised_names_and_date_plus_time(tmp_path):
    table = read_observations(
        write(tmp_path, "Date,Rain,Visibility\n2024-05-01 10:00,1.0,5000\n2024-05-01 11:00,2.0,800\n")
    )
    assert table.records[1].visibility_m == 800.0 and table.records[1].precip_accums[0].amount_mm == 2.0
    split = write(tmp_path, "date,time,Rain (in),Wind Speed (km/h)\n01/02/2024,13:00,0.5,36\n", "split.csv")
    table = read_observations(split, precip_period="1h")
    r = table.records[0]
    assert r.time_utc.isoformat() == "2024-01-02T13:00:00+00:00"  # month first unless dayfirst=true
    assert r.precip_accums[0].amount_mm == pytest.approx(12.7) and r.wind_speed_m_per_s == pytest.approx(10.0)
    assert read_observations(split, precip_period="1h", dayfirst=True).records[0].time_utc.month == 2


def test_prsa_summary_without_options(tmp_path, capsys):
    out = main(["summary", str(default_storm_path()), "--plot", str(tmp_path / "p.png")])
    assert out.is_file()
    text = " ".join(capsys.readouterr().out.split())
    assert "28 records 2013-08-10 16:00Z" in text and "PRSA" in text


def test_the_same_options_for_every_command():
    table, used = load_record(default_storm_path())
    assert used["timezone"] == "Asia/Shanghai" and used["precip_column"] == "RAIN"
    assert tuple(used["time_columns"]) == ("year", "month", "day", "hour")
    assert used == csv_options(default_storm_path())
    assert len(table) == len(read_observations(default_storm_path()))


def test_load_record_detects_a_plain_csv(tmp_path):
    path = write(tmp_path, "valid,p01m\n2024-01-01T00:00Z,1.0\n2024-01-01T01:00Z,2.0\n")
    table, used = load_record(path)
    assert used["time_columns"] == ("valid",) and used["precip_column"] == "p01m" and used["precip_unit"] == "mm"
    assert table.records[1].precip_accums[0].amount_mm == 2.0


def test_undecidable_header_lists_the_columns_and_the_option(tmp_path):
    path = write(tmp_path, "when,rr\n2024-01-01T00:00Z,1.0\n")
    with pytest.raises(DataError) as info:
        read_observations(path)
    msg = str(info.value)
    assert "station.csv" in msg and "columns: when, rr" in msg
    assert "--set time_columns=" in msg and "--set precip_column=" in msg
    two = write(tmp_path, "time,prcp,rain\n2024-01-01T00:00Z,1.0,1.0\n", "two.csv")
    with pytest.raises(
        DataError, match=r"two\.csv: .*2 candidates for precip_column \(prcp, rain\).*--set precip_column=NAME"
    ):
        main(["summary", str(two)])
    with pytest.raises(DataError, match=r"2 candidates for the time"):
        detect_columns(["time", "timestamp", "rain"], {})


def test_explicit_options_win(tmp_path, capsys):
    path = write(tmp_path, "time,when,prcp,rain,vis\n2024-01-01T00:00Z,2024-01-01T05:00Z,1.0,4.0,900\n")
    table = read_observations(path, time_columns=("when",), precip_column="rain", precip_unit="in", precip_period="1h")
    r = table.records[0]
    assert r.time_utc.hour == 5 and r.precip_accums[0].amount_mm == pytest.approx(101.6)
    assert r.visibility_m == 900.0  # roles left open are still detected
    table = read_observations(
        path, time_columns="when", precip_column="rain", visibility_column="none", precip_period="1h"
    )
    assert table.records[0].visibility_m is None
    argv = ["at", str(path), "--time", "2024-01-01T05:00Z", "--window", "30min", "--json", "--set"]
    main([*argv, "time_columns=when", "precip_column=prcp", "precip_period=1h"])
    doc = json.loads(capsys.readouterr().out)
    assert doc["rain"]["precip_mm_per_h"] == 1.0 and doc["fog"]["visibility_m"] == 900.0
