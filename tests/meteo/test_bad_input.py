"""Bad input: a DataError naming file, line and field, or one warning that counts the skipped records."""

from __future__ import annotations

import json

import pytest

from metegs.errors import ConfigError, DataError
from metegs.meteo import MeteoWarning, read_observations

from .conftest import shared_file

CSV_OPTS = {"time_columns": ("time",), "precip_column": "rain", "visibility_column": "vis"}


def write_csv(tmp_path, rows: list[str], header: str = "time,rain,vis") -> object:
    path = tmp_path / "station.csv"
    path.write_text("\n".join([header, *rows]) + "\n")
    return path


def test_negative_rain_names_file_line_field(tmp_path):
    path = write_csv(tmp_path, ["2024-01-01T00:00Z,0.5,9000", "2024-01-01T01:00Z,-1.2,9000"])
    with pytest.raises(DataError, match=r"station\.csv: line 3, field 'rain': negative precipitation -1\.2"):
        read_observations(path, reader="csv", **CSV_OPTS)


def test_nan_is_bad_input(tmp_path):
    path = write_csv(tmp_path, ["2024-01-01T00:00Z,NaN,9000"])
    with pytest.raises(DataError, match=r"line 2, field 'rain': 'NaN' is not a finite number"):
        read_observations(path, reader="csv", **CSV_OPTS)


def test_nan_can_be_declared_missing(tmp_path):
    path = write_csv(tmp_path, ["2024-01-01T00:00Z,NaN,9000", "2024-01-01T01:00Z,1.0,9000"])
    table = read_observations(path, reader="csv", missing=("", "NaN"), precip_period="1h", **CSV_OPTS)
    assert table[0].precip_accums == () and table[1].precip_accum_mm == 1.0


def test_visibility_slashes_in_a_table(tmp_path):
    path = write_csv(tmp_path, ["2024-01-01T00:00Z,0,////"])
    with pytest.raises(DataError, match=r"line 2, field 'vis': '////' is not a number"):
        read_observations(path, reader="csv", precip_period="1h", **CSV_OPTS)


def test_skip_mode_counts_in_one_warning(tmp_path):
    rows = [
        "2024-01-01T00:00Z,0.5,9000",
        "2024-01-01T01:00Z,-1,9000",
        "2024-01-01T02:00Z,NaN,9000",
        "2024-01-01T03:00Z,1,////",
    ]
    path = write_csv(tmp_path, rows)
    with pytest.warns(
        MeteoWarning, match=r"skipped 3 of 4 records \(line 3, field 'rain'.*line 4.*line 5, field 'vis'"
    ) as rec:
        table = read_observations(path, reader="csv", on_error="skip", precip_period="1h", **CSV_OPTS)
    assert len(rec) == 1 and len(table) == 1 and table.skipped == 3


def test_unknown_unit_names_the_option(tmp_path):
    path = write_csv(tmp_path, ["2024-01-01T00:00Z,0.5,9000"])
    with pytest.raises(DataError, match=r"station\.csv: option error: unknown length unit 'furlong'"):
        read_observations(path, reader="csv", precip_unit="furlong", **CSV_OPTS)


def test_units_are_converted(tmp_path):
    path = write_csv(tmp_path, ["2024-01-01T00:00Z,0.1,2", "2024-01-01T01:00Z,0.2,1.5"])
    table = read_observations(path, reader="csv", precip_unit="in", visibility_unit="mi", **CSV_OPTS)
    assert table[1].precip_accum_mm == pytest.approx(5.08) and table[1].visibility_m == pytest.approx(2414.016)
    assert table.notes == ["precipitation period taken as the median time step, 1 h"]


def test_time_going_backwards(tmp_path):
    path = write_csv(tmp_path, ["2024-01-01T02:00Z,0,9000", "2024-01-01T01:00Z,0,9000"])
    with pytest.raises(DataError, match=r"line 3, field 'time': time 2024-01-01 01:00Z goes backwards \(line 2"):
        read_observations(path, reader="csv", precip_period="1h", **CSV_OPTS)
    table = read_observations(path, reader="csv", precip_period="1h", time_order="sort", **CSV_OPTS)
    assert [r.line for r in table] == [3, 2]


def test_bad_time_and_short_row(tmp_path):
    path = write_csv(tmp_path, ["yesterday,0,9000"])
    with pytest.raises(DataError, match=r"line 2, field 'time': cannot read time 'yesterday'"):
        read_observations(path, reader="csv", precip_period="1h", **CSV_OPTS)
    path = write_csv(tmp_path, ["2024-01-01T00:00Z,0"])
    with pytest.raises(DataError, match=r"none of its 1 records can be used \(line 2: 2 fields, the header has 3\)"):
        read_observations(path, reader="csv", precip_period="1h", **CSV_OPTS)


def test_unknown_column_and_option(tmp_path):
    path = write_csv(tmp_path, ["2024-01-01T00:00Z,0,9000"])
    with pytest.raises(DataError, match=r"option precip_column='RAIN' names no column; columns: time, rain, vis"):
        read_observations(path, reader="csv", time_columns=("time",), precip_column="RAIN")
    with pytest.raises(ConfigError, match=r"reader 'csv' has no option 'precip_colum'; options: .*precip_column"):
        read_observations(path, reader="csv", precip_colum="rain")
    with pytest.raises(ConfigError, match="no option"):
        read_observations(path, reader="metar", precip_column="rain")


def test_missing_file_and_undetectable_format(tmp_path):
    with pytest.raises(DataError, match="file does not exist"):
        read_observations(tmp_path / "nope.csv", reader="csv")
    odd = tmp_path / "odd.dat"
    odd.write_text("hello\n")
    with pytest.raises(DataError, match=r"cannot tell the format.*csv, ghcnh, isd, metar, open-meteo"):
        read_observations(odd)


def test_unparsable_metar_is_skipped_and_counted(tmp_path):
    path = tmp_path / "reports.txt"
    path.write_text(
        "KAAA 011253Z 27005KT 10SM CLR 18/10 A2992 RMK AO2 P0000=\n"
        "KAAA 01125 garbage here=\n"
        "KAAA 011353Z 27005KT 9SM -RA OVC040 18/12 A2990 RMK AO2 P0003=\n"
    )
    with pytest.warns(
        MeteoWarning, match=r"reports\.txt: skipped 1 of 3 records \(line 2: unreadable METAR: KAAA: no time group"
    ):
        table = read_observations(path, year=2024, month=5)
    assert [r.line for r in table] == [1, 3]


def test_metar_slashed_visibility_is_not_reported(tmp_path):
    path = tmp_path / "auto.txt"
    path.write_text("LFBA 020100Z AUTO 26009KT //// ///TCU 17/14 Q1013=\n")
    table = read_observations(path, year=2024, month=5)
    assert table[0].visibility_m is None and table[0].wind_speed_m_per_s > 0


def test_metar_needs_year_and_month(tmp_path):
    path = tmp_path / "one.txt"
    path.write_text("KAAA 011253Z 27005KT 10SM CLR 18/10 A2992=\n")
    with pytest.raises(DataError, match="pass year= and month="):
        read_observations(path)


@pytest.mark.data
def test_a_file_that_is_not_metar_at_all():
    path = shared_file("metar-pyiem", "sa.txt")  # Canadian SA format: nothing to read
    with pytest.raises(DataError, match=r"no METAR report could be read \(4 candidate"):
        read_observations(path, reader="metar", year=2024, month=1)


def write_open_meteo(tmp_path, **changes):
    doc = {
        "latitude": 52.52,
        "longitude": 13.42,
        "utc_offset_seconds": 3600,
        "hourly_units": {
            "time": "iso8601",
            "precipitation": "mm",
            "visibility": "m",
            "wind_speed_10m": "km/h",
            "wind_direction_10m": "°",
        },
        "hourly": {
            "time": ["2024-05-01T01:00", "2024-05-01T02:00", "2024-05-01T03:00"],
            "precipitation": [0.0, 2.4, None],
            "visibility": [24140.0, 900.0, 3100.0],
            "wind_speed_10m": [18.0, 36.0, 7.2],
            "wind_direction_10m": [270, 225, 180],
            "weather_code": [3, 63, 45],
        },
    }
    doc["hourly"].update(changes)
    path = tmp_path / "forecast.json"
    path.write_text(json.dumps(doc))
    return path


def test_open_meteo_hand_written_response(tmp_path):
    """No real Open-Meteo file is in ../shared; this is a response written by hand in the documented layout."""
    path = write_open_meteo(tmp_path)
    table = read_observations(path)
    assert table.reader == "open-meteo" and len(table) == 3
    r = table[1]
    assert r.time_utc.isoformat() == "2024-05-01T01:00:00+00:00"  # local 02:00 at UTC+1
    assert (r.precip_accum_mm, r.precip_period_h) == (2.4, 1.0)
    assert r.wind_speed_m_per_s == pytest.approx(10.0) and r.wind_dir_deg_from == 225
    assert r.visibility_m == 900 and [w.code for w in r.weather] == ["RA"]
    assert table[2].precip_accums == () and table[0].weather == ()


def test_open_meteo_bad_values(tmp_path):
    with pytest.raises(DataError, match=r"hourly\.precipitation\[1\].*negative precipitation"):
        read_observations(write_open_meteo(tmp_path, precipitation=[0.0, -2.0, 0.0]))
    with pytest.raises(DataError, match=r"field 'hourly\.visibility': expected a list of 3 values"):
        read_observations(write_open_meteo(tmp_path, visibility=[1.0]))
