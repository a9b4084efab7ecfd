"""Corrupt records: encodings, binary files, stray line ends, files without records and implausible values."""

from __future__ import annotations

import codecs
import json
import random

import pytest

from metegs.errors import DataError
from metegs.meteo import MeteoWarning, detect_reader, read_observations
from metegs.meteo.limits import MAX_PRECIP_RATE_MM_H, max_precip_rate_mm_h

CSV_OPTS = {"precip_column": "rain", "visibility_column": "vis", "precip_period": "1h"}
ROWS = ["time,rain,vis", "2024-01-01T00:00Z,0.5,9000", "2024-01-01T01:00Z,1.2,4000", "2024-01-01T02:00Z,0,8000"]


def write(tmp_path, data: bytes | str, name: str = "station.csv"):
    path = tmp_path / name
    path.write_bytes(data.encode() if isinstance(data, str) else data)
    return path


def values(table) -> list[tuple]:
    return [(r.time_utc, r.precip_accum_mm, r.visibility_m, r.line) for r in table]


@pytest.mark.parametrize(
    "encode",
    [
        lambda t: codecs.BOM_UTF8 + t.encode(),
        lambda t: t.encode("utf-16"),  # with its byte-order mark
        lambda t: codecs.BOM_UTF16_BE + t.encode("utf-16-be"),
        lambda t: t.replace("\n", "\r\n").encode(),
        lambda t: t.replace("\n", "\r").encode(),  # classic Mac line ends
    ],
    ids=["utf8-bom", "utf16", "utf16-be", "crlf", "cr"],
)
def test_encodings_and_line_ends_read_the_same(tmp_path, encode):
    text = "\n".join(ROWS) + "\n"
    plain = read_observations(write(tmp_path, text, "plain.csv"), reader="csv", **CSV_OPTS)
    other = read_observations(write(tmp_path, encode(text)), **CSV_OPTS)
    assert values(other) == values(plain) and len(plain) == 3


def test_spreadsheet_unicode_text_is_read(tmp_path):
    """A spreadsheet's "Unicode text": UTF-16 with a byte-order mark, tab-separated, CRLF."""
    path = write(tmp_path, "\r\n".join(r.replace(",", "\t") for r in ROWS).encode("utf-16"), "station.tsv")
    assert [r.precip_accum_mm for r in read_observations(path, **CSV_OPTS)] == [0.5, 1.2, 0.0]


@pytest.mark.parametrize(
    ("data", "problem"),
    [
        ("\n".join(ROWS).encode("utf-16-le"), "looks like UTF-16 text without a byte-order mark"),
        (b"\x89PNG\r\n\x1a\n" + bytes(200), "is a PNG image, not a text record"),
        (b"PK\x03\x04" + bytes(200), "is a ZIP archive"),
        (random.Random(0).randbytes(4000), "is a binary file, not a text record"),
        ("\n".join(ROWS).replace("9000", "9000 \xe9").encode("latin-1"), "line 2: byte 0xe9 is not UTF-8 text"),
        (b"", "file is empty"),
        (b" \n\r\n", "file is empty"),
    ],
    ids=["utf16-no-bom", "png", "zip", "random", "latin1", "empty", "blank"],
)
def test_files_that_are_not_text_records(tmp_path, data, problem):
    path = write(tmp_path, data)
    with pytest.raises(DataError, match=rf"station\.csv: {problem}"):
        read_observations(path, **CSV_OPTS)
    if problem != "line 2: byte 0xe9 is not UTF-8 text":  # detection only reads the head, leniently
        with pytest.raises(DataError, match=rf"station\.csv: {problem}"):
            detect_reader(path)


def test_a_stray_carriage_return_names_the_line(tmp_path):
    rows = [*ROWS[:2], "2024-01-01T01:00Z,1.2\r,4000", ROWS[3]]
    path = write(tmp_path, "\n".join(rows) + "\n")
    with pytest.raises(DataError, match=r"station\.csv: line 3: a stray carriage return \(CR\) inside the line"):
        read_observations(path, **CSV_OPTS)
    with pytest.warns(MeteoWarning, match=r"skipped 1 .*line 3: a stray carriage return"):
        table = read_observations(path, on_error="skip", **CSV_OPTS)
    assert [r.line for r in table] == [2, 4]


@pytest.mark.parametrize(
    ("name", "text"),
    [
        ("station.csv", ROWS[0] + "\n"),
        ("station.psv", "Station_ID|Station_name|Year|Month|Day|Hour|Minute|precipitation\n"),
        ("forecast.json", json.dumps({"hourly": {"time": [], "precipitation": []}})),
    ],
)
def test_a_file_without_records_says_so(tmp_path, name, text):
    with pytest.raises(DataError, match=rf"{name}: holds no records"):
        read_observations(write(tmp_path, text, name), **(CSV_OPTS if name.endswith(".csv") else {}))


def test_a_file_whose_records_are_all_skipped(tmp_path):
    path = write(tmp_path, "\n".join([ROWS[0], "2024-01-01T00:00Z,0.5", "2024-01-01T01:00Z"]) + "\n")
    with pytest.raises(DataError, match=r"none of its 2 records can be used \(line 2: 2 fields.*line 3: 1 fields"):
        read_observations(path, **CSV_OPTS)


def test_precipitation_bounds_follow_the_world_records():
    assert MAX_PRECIP_RATE_MM_H == max_precip_rate_mm_h(1 / 60) == pytest.approx(2400.0)
    assert max_precip_rate_mm_h(1.0) == pytest.approx(400.0)  # 305 mm in 60 min (Holt, 1947)
    assert max_precip_rate_mm_h(24.0) * 24 == pytest.approx(2000.0)  # 1825 mm in 24 h (Foc-Foc, 1966)
    assert max_precip_rate_mm_h(10 / 60) * 10 / 60 == pytest.approx(400.0)


@pytest.mark.parametrize(
    ("row", "match"),
    [
        ("2024-01-01T01:00Z,2540,4000", r"line 3, field 'rain': 2540 mm in 1 h is more rain than ever measured"),
        ("2024-01-01T01:00Z,1e9,4000", r"line 3, field 'rain': 1e\+09 mm in 1 h"),
        ("2024-01-01T01:00Z,1.2,0", r"line 3, field 'visibility': 0 m is below 1 m"),
        ("2024-01-01T01:00Z,1.2,0.5", r"line 3, field 'visibility': 0\.5 m is below 1 m"),
    ],
)
def test_implausible_values_name_file_line_and_field(tmp_path, row, match):
    path = write(tmp_path, "\n".join([*ROWS[:2], row, ROWS[3]]) + "\n")
    with pytest.raises(DataError, match=rf"station\.csv: {match}"):
        read_observations(path, **CSV_OPTS)
    with pytest.warns(MeteoWarning, match=rf"skipped 1 of 3 records \({match}"):
        assert [r.line for r in read_observations(path, on_error="skip", **CSV_OPTS)] == [2, 4]


def test_record_extremes_are_accepted(tmp_path):
    """The heaviest real rain (305 mm in an hour; 38 mm in a minute) and the strongest gust are not refused."""
    path = write(tmp_path, "time,rain,gust\n2024-01-01T00:00Z,38,20\n2024-01-01T00:01Z,12,113.3\n")
    table = read_observations(path, precip_column="rain", precip_period="1min", wind_gust_column="gust")
    assert [r.precip_accum_mm for r in table] == [38.0, 12.0]
    path = write(tmp_path, "time,rain\n2024-01-01T00:00Z,305\n2024-01-01T01:00Z,0\n")
    assert read_observations(path, precip_column="rain", precip_period="1h")[0].precip_accum_mm == 305.0


def test_wind_beyond_any_gust_and_rates_beyond_any_rain(tmp_path):
    path = write(tmp_path, "time,wind,rr\n2024-01-01T00:00Z,3,1\n2024-01-01T01:00Z,450,1\n")
    with pytest.raises(DataError, match=r"line 3, field 'wind speed': 450 m/s is above 120 m/s"):
        read_observations(path, wind_speed_column="wind")
    path = write(tmp_path, "time,rr\n2024-01-01T00:00Z,1\n2024-01-01T01:00Z,1e9\n")
    with pytest.raises(DataError, match=r"line 3, field 'precipitation rate': 1e\+09 mm/h is more rain than ever"):
        read_observations(path, precip_column="rr", precip_kind="rate")


METAR = "KAAA 011253Z 27005KT 10SM -RA OVC040 RMK AO2 P0002=\nKAAA 011353Z 27008KT 5SM +RA RMK AO2 {p}=\n"


def test_metar_p9999_is_not_violent_rain(tmp_path):
    path = write(tmp_path, METAR.format(p="P9999"), "reports.txt")
    with pytest.raises(DataError, match=r"reports\.txt: line 2, field 'P': 2539\.75 mm in 1 h is more rain"):
        read_observations(path, year=2024, month=5)
    path = write(tmp_path, METAR.format(p="P0150"), "reports.txt")  # 38 mm in an hour: heavy, real
    assert read_observations(path, year=2024, month=5)[1].precip_accum_mm == pytest.approx(38.1)


def test_metar_noise_is_dropped_and_a_zero_denominator_is_not_read(tmp_path):
    text = METAR.format(p="P0015").replace("5SM", "1/0SM").encode()
    path = write(tmp_path, b"\x01\r\r\n" + text.replace(b"-RA", b"-RA \xff\x00"), "reports.txt")
    table = read_observations(path, year=2024, month=5)
    assert len(table) == 2 and table[1].visibility_m is None and table[0].visibility_m > 16000


GHCNH = "Station_ID|Year|Month|Day|Hour|Minute|precipitation|precipitation_Report_Type|visibility\n"


def test_ghcnh_garbage_minute_and_zero_visibility(tmp_path):
    path = write(tmp_path, GHCNH + "X|2023|01|03|05|5a|0.0|FM15-METAR|9.6\n", "station.psv")
    with pytest.raises(DataError, match=r"station\.psv: line 2, field 'Year\.\.Minute': cannot read the time"):
        read_observations(path)
    path = write(tmp_path, GHCNH + "X|2023|01|03|05|52|0.0|FM15-METAR|0.0\n", "station.psv")
    r = read_observations(path)[0]
    assert r.visibility_m == 50.0 and r.visibility_below  # below the smallest reportable, like METAR 0000


ISD = (
    "0050010010999991988011309004+70933-008667FM-12+0009ENJA V0203401N00361220001CN0750001N9-00931-01321100711"
    "ADDAA101000591"
)


@pytest.mark.parametrize(
    ("at", "value", "match"),
    [
        (65, "00x6", r"field 'wind speed \(columns 66-69\)': '00x6' is not a number"),
        (78, "0a5000", r"field 'visibility \(columns 79-84\)': '0a5000' is not a number"),
        (65, "9000", r"field 'wind speed': 900 m/s is above 120 m/s"),
        (108, "AA101999891", r"field 'AA': 999\.8 mm in 1 h is more rain than ever measured"),
    ],
)
def test_isd_bad_columns(tmp_path, at, value, match):
    path = write(tmp_path, ISD[:at] + value + ISD[at + len(value) :] + "\n", "isd.txt")
    with pytest.raises(DataError, match=rf"isd\.txt: line 1, {match}"):
        read_observations(path)


def test_isd_zero_visibility_is_an_upper_bound(tmp_path):
    path = write(tmp_path, ISD[:78] + "000000" + ISD[84:] + "\n", "isd.txt")
    r = read_observations(path)[0]
    assert r.visibility_m == 50.0 and r.visibility_below


def test_open_meteo_bad_offset_and_units(tmp_path):
    doc = {"utc_offset_seconds": "+8h", "hourly": {"time": ["2024-05-01T01:00"], "precipitation": [0.0]}}
    with pytest.raises(DataError, match=r"forecast\.json: field 'utc_offset_seconds': '\+8h' is not a number"):
        read_observations(write(tmp_path, json.dumps(doc), "forecast.json"))
    doc = {"hourly_units": ["mm"], "hourly": {"time": ["2024-05-01T01:00"], "precipitation": [0.0]}}
    with pytest.raises(DataError, match=r"forecast\.json: field 'hourly_units': expected an object"):
        read_observations(write(tmp_path, json.dumps(doc), "forecast.json"))
    doc = {"hourly": {"time": ["2024-05-01T01:00", "2024-05-01T02:00"], "precipitation": [0.0, 400.5]}}
    with pytest.raises(DataError, match=r"field 'precipitation': 2024-05-01 02:00Z: 400\.5 mm in 1 h is more rain"):
        read_observations(write(tmp_path, json.dumps(doc), "forecast.json"))
