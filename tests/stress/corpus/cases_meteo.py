"""Meteorological records and weather values: every reader × bad file, METAR oddities, `--conditions.*` values.

Commands: metegs-meteo summary / at, metegs-train (--conditions.record / explicit values) and metegs-synth.
The records are built from the storm excerpt shipped with metegs (a UCI Beijing PRSA csv) or written by hand in
each format's documented layout.
"""

from __future__ import annotations

import codecs
import json
import random
from pathlib import Path

from corpus.harness import QUIET_RUN, TINY_SCENE, Case, Result
from metegs.meteo import default_storm_path
from metegs.meteo.storm import DEFAULT_CAPTURE_TIME

STORM_TIME = DEFAULT_CAPTURE_TIME.strftime("%Y-%m-%dT%H:%MZ")
PRSA_SET = [
    "--set", "time_columns=year,month,day,hour", "timezone=Asia/Shanghai", "precip_column=RAIN", "precip_period=1h",
    "wind_speed_column=WSPM", "wind_dir_column=wd", "station_column=station",
]  # fmt: skip
"""metegs-meteo reader options of a PRSA csv (metegs-train and metegs-synth find them alone)."""
PRSA_COLUMNS = {"year": 1, "hour": 4, "RAIN": 14, "wd": 15, "WSPM": 16}
STORM_SUMMARY = "28 records 2013-08-10 16:00Z .. 2013-08-11 19:00Z; precipitation 87.7 mm"
"""What `metegs-meteo summary` says of the shipped storm."""
PNG = b"\x89PNG\r\n\x1a\n" + random.Random(0).randbytes(600)
NOISE = random.Random(1).randbytes(3000)


def _write(folder: Path, name: str, data: str | bytes) -> Path:
    path = folder / name
    path.write_bytes(data.encode() if isinstance(data, str) else data)
    return path


def _prsa_lines(column: str | None = None, value: str = "", line: int = 17) -> list[str]:
    """The storm's lines, with ``column`` of file line ``line`` (1-based; 17 is 15:00 local) set to ``value``."""
    lines = default_storm_path().read_text().splitlines()
    if column is not None:
        cells = lines[line - 1].split(",")
        cells[PRSA_COLUMNS[column]] = value
        lines[line - 1] = ",".join(cells)
    return lines


def _prsa(folder: Path, column: str | None = None, value: str = "", name: str = "storm.csv") -> Path:
    return _write(folder, name, "\n".join(_prsa_lines(column, value)) + "\n")


def _summary(path: Path, *extra: str) -> list:
    return ["summary", path, "--plot", path.parent / "plot.png", *extra]


def _at(path: Path, *extra: str) -> list:
    return ["at", path, "--time", STORM_TIME, *extra]


def _storm_summary(result: Result) -> None:
    text = " ".join(result.stdout.split())
    assert STORM_SUMMARY in text and "max 72.5 mm/h" in text, text


def _storm_theta(result: Result) -> None:
    """`at --json` of a re-encoded storm gives the θ of the shipped one."""
    from metegs.meteo import default_theta

    theta = json.loads(result.stdout)
    assert theta["rain"]["precip_mm_per_h"] == default_theta().rain.precip_mm_per_h == 6.8
    assert theta["conditions"]["wind_speed_m_per_s"] == default_theta().conditions.wind_speed_m_per_s


def _records(n: int):
    def check(result: Result) -> None:
        assert f" {n} records " in " ".join(result.stdout.split()), result.stdout

    return check


# --- GHCNh (pipe-separated, UTC, mm, km, m/s) ---------------------------------------------------------------
GHCNH_HEADER = (
    "Station_ID|Station_name|Year|Month|Day|Hour|Minute|precipitation|precipitation_Report_Type|visibility|wind_speed|"
    "wind_direction"
)
GHCNH_ROWS = [
    "USW00013967|OKC|2023|01|03|05|52|0.0|FM15-METAR|9.656|3.6|210",
    "USW00013967|OKC|2023|01|03|06|52|1.5|FM15-METAR|4.8|5.1|220",
    "USW00013967|OKC|2023|01|03|07|52|2.3|FM15-METAR|3.2|6.2|230",
]


def _ghcnh(folder: Path, row: int | None = None, field: int = 7, value: str = "", tail: str = "") -> Path:
    """A GHCNh file; ``field`` of data row ``row`` (0-based) set to ``value``; ``tail`` appended as-is."""
    rows = [r.split("|") for r in GHCNH_ROWS]
    if row is not None:
        rows[row][field] = value
    return _write(folder, "station.psv", "\n".join([GHCNH_HEADER, *("|".join(r) for r in rows)]) + "\n" + tail)


# --- ISD (fixed width; wind 61-70, visibility 79-85, ADD 106-108) ---------------------------------------------
ISD_LINE = (
    "0050010010999991988011309004+70933-008667FM-12+0009ENJA V0203401N00361220001CN0750001N9-00931-01321100711"
    "ADDAA101000591"
)


def _isd_line(hour: int = 9, at: int | None = None, value: str = "") -> str:
    line = ISD_LINE[:23] + f"{hour:02d}" + ISD_LINE[25:]
    return line if at is None else line[:at] + value + line[at + len(value) :]


def _isd(folder: Path, at: int | None = None, value: str = "", tail: str = "") -> Path:
    lines = [_isd_line(9), _isd_line(10, at, value), _isd_line(11)]
    return _write(folder, "isd.txt", "\n".join(lines) + "\n" + tail)


# --- METAR (US remarks: P group in hundredths of an inch) -----------------------------------------------------
METAR = [
    "KAAA 011253Z 27005KT 10SM -RA OVC040 18/10 A2992 RMK AO2 P0002=",
    "KAAA 011353Z 27008KT 5SM RA OVC030 17/12 A2990 RMK AO2 P0015=",
    "KAAA 011453Z 28006KT 8SM -RA OVC035 17/12 A2990 RMK AO2 P0004=",
]
METAR_SET = ["--set", "year=2024", "month=5"]


def _metar(folder: Path, middle: str | None = None, name: str = "reports.txt") -> Path:
    lines = [METAR[0], METAR[1] if middle is None else middle, METAR[2]]
    return _write(folder, name, "\n".join(lines) + "\n")


# --- Open-Meteo JSON ----------------------------------------------------------------------------------------
def _open_meteo_doc(**hourly) -> dict:
    doc = {
        "latitude": 52.52,
        "longitude": 13.42,
        "utc_offset_seconds": 0,
        "hourly_units": {"time": "iso8601", "precipitation": "mm", "visibility": "m", "wind_speed_10m": "km/h"},
        "hourly": {
            "time": ["2024-05-01T01:00", "2024-05-01T02:00", "2024-05-01T03:00"],
            "precipitation": [0.0, 2.4, 0.5],
            "visibility": [24140.0, 900.0, 3100.0],
            "wind_speed_10m": [18.0, 36.0, 7.2],
            "weather_code": [3, 63, 61],
        },
    }
    doc["hourly"].update(hourly)
    return doc


def _open_meteo(folder: Path, text: str | None = None, **hourly) -> Path:
    return _write(folder, "forecast.json", json.dumps(_open_meteo_doc(**hourly)) if text is None else text)


def _case(id: str, command: str, argv, match: str) -> Case:
    return Case(id, command, argv, "clear", match=match)


READER_CASES = [
    # csv (the shipped PRSA storm and variants)
    _case("meteo-csv-empty", "metegs-meteo", lambda f: _summary(_write(f, "storm.csv", "")), r"storm\.csv: file is empty"),
    _case("meteo-csv-header-only", "metegs-meteo", lambda f: _summary(_write(f, "storm.csv", _prsa_lines()[0] + "\n"), *PRSA_SET), r"storm\.csv: holds no records"),
    _case("meteo-csv-png", "metegs-meteo", lambda f: _summary(_write(f, "storm.csv", PNG), *PRSA_SET), r"storm\.csv: is a PNG image"),
    _case("meteo-csv-binary", "metegs-meteo", lambda f: _summary(_write(f, "storm.csv", NOISE), *PRSA_SET), r"storm\.csv: is a binary file"),
    _case("meteo-csv-xlsx", "metegs-meteo", lambda f: _summary(_write(f, "storm.csv", b"PK\x03\x04" + NOISE), *PRSA_SET), r"storm\.csv: is a ZIP archive.*export"),
    Case("meteo-csv-utf16-bom", "metegs-meteo", lambda f: _summary(_write(f, "storm.csv", codecs.BOM_UTF16_LE + "\r\n".join(_prsa_lines()).replace(",", "\t").encode("utf-16-le")), *PRSA_SET), "correct", check=_storm_summary),
    Case("meteo-csv-utf16-be-at", "metegs-meteo", lambda f: _at(_write(f, "storm.csv", "\n".join(_prsa_lines()).encode("utf-16")), "--json", *PRSA_SET), "correct", check=_storm_theta),
    Case("meteo-csv-utf8-bom", "metegs-meteo", lambda f: _summary(_write(f, "storm.csv", codecs.BOM_UTF8 + "\n".join(_prsa_lines()).encode()), *PRSA_SET), "correct", check=_storm_summary),
    _case("meteo-csv-utf16-no-bom", "metegs-meteo", lambda f: _summary(_write(f, "storm.csv", "\n".join(_prsa_lines()).encode("utf-16-le")), *PRSA_SET), r"storm\.csv: looks like UTF-16"),
    _case("meteo-csv-latin1", "metegs-meteo", lambda f: _summary(_write(f, "storm.csv", "\n".join(_prsa_lines()).replace("Aotizhongxin", "Aotizh\xf4ngxin").encode("latin-1")), *PRSA_SET), r"storm\.csv: line 2: byte 0xf4 is not UTF-8"),
    _case("meteo-csv-stray-cr", "metegs-meteo", lambda f: _summary(_prsa(f, "WSPM", "1\r.5"), *PRSA_SET), r"storm\.csv: line 17: a stray carriage return"),
    Case("meteo-csv-cr-line-ends", "metegs-meteo", lambda f: _summary(_write(f, "storm.csv", "\r".join(_prsa_lines()) + "\r"), *PRSA_SET), "correct", check=_storm_summary),
    Case("meteo-csv-crlf-at", "metegs-meteo", lambda f: _at(_write(f, "storm.csv", "\r\n".join(_prsa_lines()) + "\r\n"), "--json", *PRSA_SET), "correct", check=_storm_theta),
    Case("meteo-csv-truncated-line", "metegs-meteo", lambda f: _summary(_write(f, "storm.csv", "\n".join(_prsa_lines()) + "\n3941,2013,8,12,4,5"), *PRSA_SET), "correct", check=_storm_summary),
    _case("meteo-csv-nan-rain", "metegs-meteo", lambda f: _summary(_prsa(f, "RAIN", "NaN"), *PRSA_SET), r"storm\.csv: line 17, field 'RAIN': 'NaN' is not a finite number"),
    _case("meteo-csv-negative-rain-at", "metegs-meteo", lambda f: _at(_prsa(f, "RAIN", "-3"), *PRSA_SET), r"storm\.csv: line 17, field 'RAIN': negative precipitation"),
    _case("meteo-csv-absurd-rain", "metegs-meteo", lambda f: _summary(_prsa(f, "RAIN", "1e9"), *PRSA_SET), r"storm\.csv: line 17, field 'RAIN': 1e\+09 mm in 1 h is more rain than ever measured"),
    _case("meteo-csv-absurd-rain-at", "metegs-meteo", lambda f: _at(_prsa(f, "RAIN", "2540"), *PRSA_SET), r"storm\.csv: line 17, field 'RAIN': 2540 mm in 1 h"),
    _case("meteo-csv-bad-time", "metegs-meteo", lambda f: _summary(_prsa(f, "hour", "25"), *PRSA_SET), r"storm\.csv: line 17, field 'year\+month\+day\+hour': cannot read time"),
    _case("meteo-csv-negative-wind", "metegs-meteo", lambda f: _summary(_prsa(f, "WSPM", "-2"), *PRSA_SET), r"storm\.csv: line 17, field 'WSPM': negative value"),
    _case("meteo-csv-absurd-wind", "metegs-meteo", lambda f: _summary(_prsa(f, "WSPM", "450"), *PRSA_SET), r"storm\.csv: line 17, field 'wind speed': 450 m/s is above 120 m/s"),
    _case("meteo-csv-bad-wind-dir", "metegs-meteo", lambda f: _summary(_prsa(f, "wd", "XNW"), *PRSA_SET), r"storm\.csv: line 17, field 'wd': unknown compass direction"),
    _case("meteo-csv-zero-visibility", "metegs-meteo", lambda f: _at(_write(f, "vis.csv", "time,vis\n2013-08-11T07:00Z,8000\n2013-08-11T08:00Z,0\n"), "--set", "visibility_column=vis"), r"vis\.csv: line 3, field 'visibility': 0 m is below 1 m"),
    _case("meteo-csv-inf-visibility", "metegs-meteo", lambda f: _at(_write(f, "vis.csv", "time,vis\n2013-08-11T07:00Z,8000\n2013-08-11T08:00Z,inf\n"), "--set", "visibility_column=vis"), r"vis\.csv: line 3, field 'vis': 'inf' is not a finite number"),
    _case("meteo-csv-absurd-rate", "metegs-meteo", lambda f: _summary(_write(f, "rate.csv", "time,rr\n2013-08-11T07:00Z,2\n2013-08-11T08:00Z,1e9\n"), "--set", "precip_column=rr", "precip_kind=rate", "precip_period=10min"), r"rate\.csv: line 3, field 'precipitation rate': 1e\+09 mm/h is more rain than ever measured"),
    # GHCNh
    _case("meteo-ghcnh-empty", "metegs-meteo", lambda f: _summary(_write(f, "station.psv", ""), "--reader", "ghcnh"), r"station\.psv: file is empty"),
    _case("meteo-ghcnh-header-only", "metegs-meteo", lambda f: _summary(_write(f, "station.psv", GHCNH_HEADER + "\n")), r"station\.psv: holds no records"),
    _case("meteo-ghcnh-header-only-at", "metegs-meteo", lambda f: _at(_write(f, "station.psv", GHCNH_HEADER + "\n")), r"station\.psv: holds no records"),
    _case("meteo-ghcnh-binary", "metegs-meteo", lambda f: _summary(_write(f, "station.psv", NOISE), "--reader", "ghcnh"), r"station\.psv: is a binary file"),
    Case("meteo-ghcnh-utf16", "metegs-meteo", lambda f: _summary(_write(f, "station.psv", _ghcnh(f).read_text().encode("utf-16"))), "correct", check=_records(3)),
    _case("meteo-ghcnh-stray-cr", "metegs-meteo", lambda f: _summary(_ghcnh(f, 1, 7, "1.\r5")), r"station\.psv: line 3, field 'precipitation': '1\.\\r5' is not a number"),
    Case("meteo-ghcnh-truncated-line", "metegs-meteo", lambda f: _summary(_ghcnh(f, tail="USW00013967|OKC|2023|01|03|08|5")), "correct", check=_records(3)),
    _case("meteo-ghcnh-nan-rain", "metegs-meteo", lambda f: _summary(_ghcnh(f, 1, 7, "nan")), r"station\.psv: line 3, field 'precipitation': 'nan' is not a finite number"),
    _case("meteo-ghcnh-negative-visibility", "metegs-meteo", lambda f: _summary(_ghcnh(f, 2, 9, "-1")), r"station\.psv: line 4, field 'visibility': negative value"),
    _case("meteo-ghcnh-absurd-rain", "metegs-meteo", lambda f: _summary(_ghcnh(f, 1, 7, "999.9")), r"station\.psv: line 3, field 'precipitation': 999\.9 mm in 1 h is more rain than ever measured"),
    _case("meteo-ghcnh-absurd-wind-at", "metegs-meteo", lambda f: ["at", _ghcnh(f, 1, 10, "999"), "--time", "2023-01-03T06:52Z"], r"station\.psv: line 3, field 'wind speed': 999 m/s is above 120 m/s"),
    _case("meteo-ghcnh-bad-time", "metegs-meteo", lambda f: _summary(_ghcnh(f, 0, 3, "13")), r"station\.psv: line 2, field 'Year\.\.Minute': cannot read the time"),
    _case("meteo-ghcnh-bad-minute", "metegs-meteo", lambda f: _summary(_ghcnh(f, 0, 6, "5a")), r"station\.psv: line 2, field 'Year\.\.Minute'"),
    # ISD
    _case("meteo-isd-empty", "metegs-meteo", lambda f: _summary(_write(f, "isd.txt", "\n\n"), "--reader", "isd"), r"isd\.txt: file is empty"),
    _case("meteo-isd-binary", "metegs-meteo", lambda f: _summary(_write(f, "isd.txt", NOISE), "--reader", "isd"), r"isd\.txt: is a binary file"),
    _case("meteo-isd-no-records", "metegs-meteo", lambda f: _summary(_write(f, "isd.txt", "USAF WBAN DATE\nnot a record\n"), "--reader", "isd"), r"isd\.txt: none of its 2 records can be used \(line 1: not an ISD record"),
    _case("meteo-isd-garbage-wind", "metegs-meteo", lambda f: _summary(_isd(f, 65, "00x6")), r"isd\.txt: line 2, field 'wind speed \(columns 66-69\)': '00x6' is not a number"),
    _case("meteo-isd-absurd-wind", "metegs-meteo", lambda f: _summary(_isd(f, 65, "9000")), r"isd\.txt: line 2, field 'wind speed': 900 m/s is above 120 m/s"),
    _case("meteo-isd-absurd-rain", "metegs-meteo", lambda f: _summary(_isd(f, 108, "AA101999891")), r"isd\.txt: line 2, field 'AA': 999\.8 mm in 1 h is more rain than ever measured"),
    _case("meteo-isd-bad-date", "metegs-meteo", lambda f: _summary(_isd(f, 19, "13")), r"isd\.txt: line 2, field 'date/time \(columns 16-27\)'"),
    Case("meteo-isd-truncated-line", "metegs-meteo", lambda f: _summary(_isd(f, tail=_isd_line(12)[:80])), "correct", check=_records(3)),
    Case("meteo-isd-utf16", "metegs-meteo", lambda f: _summary(_write(f, "isd.txt", "\n".join(_isd_line(h) for h in (9, 10, 11)).encode("utf-16"))), "correct", check=_records(3)),
    # METAR
    _case("meteo-metar-empty", "metegs-meteo", lambda f: _summary(_write(f, "reports.txt", " \n"), "--reader", "metar", *METAR_SET), r"reports\.txt: file is empty"),
    _case("meteo-metar-binary", "metegs-meteo", lambda f: _summary(_write(f, "reports.txt", NOISE), "--reader", "metar", *METAR_SET), r"reports\.txt: is a binary file"),
    _case("meteo-metar-p9999", "metegs-meteo", lambda f: _summary(_metar(f, "KAAA 011353Z 27008KT 5SM +RA OVC030 RMK AO2 P9999="), *METAR_SET), r"reports\.txt: line 2, field 'P': 2539\.75 mm in 1 h is more rain than ever measured"),
    _case("meteo-metar-p9999-at", "metegs-meteo", lambda f: ["at", _metar(f, "KAAA 011353Z 27008KT 5SM +RA OVC030 RMK AO2 P9999="), "--time", "2024-05-01T13:53Z", *METAR_SET], r"reports\.txt: line 2, field 'P'"),
    _case("meteo-metar-6-group-absurd", "metegs-meteo", lambda f: _summary(_metar(f, "KAAA 011153Z 27008KT 5SM RA OVC030 RMK AO2 P0010 69999="), *METAR_SET), r"reports\.txt: line 2, field '6': 2539\.75 mm in 6 h"),
    _case("meteo-metar-absurd-wind", "metegs-meteo", lambda f: _summary(_metar(f, "KAAA 011353Z 270999KT 5SM RA OVC030 RMK AO2 P0015="), *METAR_SET), r"reports\.txt: line 2, field 'wind speed'"),
    _case("meteo-metar-garbage-only", "metegs-meteo", lambda f: _summary(_write(f, "reports.txt", "hello world\nthis is not a METAR\n"), "--reader", "metar", *METAR_SET), r"reports\.txt: no METAR report could be read"),
    _case("meteo-metar-missing-groups", "metegs-meteo", lambda f: _summary(_write(f, "reports.txt", "KAAA 011253Z=\nKAAA 011353Z AUTO=\n"), "--reader", "metar", *METAR_SET), r"reports\.txt: no METAR report could be read.*no wind, visibility, weather or precipitation group"),
    _case("meteo-metar-impossible-day", "metegs-meteo", lambda f: _summary(_write(f, "reports.txt", "KAAA 311253Z 27005KT 10SM RA=\n"), "--reader", "metar", "--set", "year=2024", "month=2"), r"reports\.txt: no METAR report could be read.*impossible time 311253Z"),
    _case("meteo-metar-no-year", "metegs-meteo", lambda f: _summary(_metar(f)), r"reports\.txt: METAR reports give only day and time: pass year= and month="),
    Case("meteo-metar-garbage-line", "metegs-meteo", lambda f: _summary(_metar(f, "KAAA 01135 garbage here ###="), *METAR_SET), "correct", check=_records(2)),
    Case("meteo-metar-zero-denominator", "metegs-meteo", lambda f: _summary(_metar(f, "KAAA 011353Z 27008KT 1/0SM RA OVC030 RMK AO2 P0015="), *METAR_SET), "correct", check=_records(3)),
    Case("meteo-metar-utf16", "metegs-meteo", lambda f: _summary(_write(f, "reports.txt", "\r\n".join(METAR).encode("utf-16")), "--reader", "metar", *METAR_SET), "correct", check=_records(3)),
    # Open-Meteo
    _case("meteo-open-meteo-empty", "metegs-meteo", lambda f: _summary(_open_meteo(f, ""), "--reader", "open-meteo"), r"forecast\.json: file is empty"),
    _case("meteo-open-meteo-truncated", "metegs-meteo", lambda f: _summary(_open_meteo(f, json.dumps(_open_meteo_doc())[:-40])), r"forecast\.json: line 1: not valid JSON"),
    _case("meteo-open-meteo-no-hours", "metegs-meteo", lambda f: _summary(_open_meteo(f, time=[], precipitation=[], visibility=[], wind_speed_10m=[], weather_code=[])), r"forecast\.json: holds no records"),
    _case("meteo-open-meteo-nan", "metegs-meteo", lambda f: _summary(_open_meteo(f, precipitation=[0.0, float("nan"), 0.5])), r"forecast\.json: field .hourly\.precipitation\[1\].*not a finite number"),
    _case("meteo-open-meteo-absurd-rain", "metegs-meteo", lambda f: _summary(_open_meteo(f, precipitation=[0.0, 5000.0, 0.5])), r"forecast\.json: field 'precipitation': 2024-05-01 02:00Z: 5000 mm in 1 h is more rain"),
    _case("meteo-open-meteo-absurd-wind", "metegs-meteo", lambda f: _summary(_open_meteo(f, wind_speed_10m=[18.0, 1000.0, 7.2])), r"forecast\.json: field 'wind speed': .*above 120 m/s"),
    _case("meteo-open-meteo-zero-visibility-at", "metegs-meteo", lambda f: ["at", _open_meteo(f, visibility=[24140.0, 0.0, 3100.0]), "--time", "2024-05-01T02:00Z"], r"forecast\.json: field 'visibility': .*0 m is below 1 m"),
    _case("meteo-open-meteo-bad-time", "metegs-meteo", lambda f: _summary(_open_meteo(f, time=["2024-05-01T01:00", "yesterday", "2024-05-01T03:00"])), r"forecast\.json: field 'hourly\.time\[1\]': cannot read time 'yesterday'"),
    _case("meteo-open-meteo-bad-offset", "metegs-meteo", lambda f: _summary(_open_meteo(f, json.dumps({**_open_meteo_doc(), "utc_offset_seconds": "+8h"}))), r"forecast\.json: field 'utc_offset_seconds'"),
    Case("meteo-open-meteo-utf8-bom", "metegs-meteo", lambda f: _summary(_write(f, "forecast.json", codecs.BOM_UTF8 + json.dumps(_open_meteo_doc()).encode())), "correct", check=_records(3)),
]  # fmt: skip


# --- metegs-train: a record's problems reach the same clear errors; explicit values fail at parse time ----------
def _train(folder: Path, *extra) -> list:
    return ["3dgs", *TINY_SCENE, *QUIET_RUN, "--output-dir", folder / "out", "--experiment-name", "run", *extra]


def _train_record(folder: Path, record: Path, *extra) -> list:
    return _train(folder, "--degrade", "rain", "--conditions.record", record, "--conditions.time", STORM_TIME, *extra)


def _theta_of_storm(result: Result) -> None:
    """The run's θ from a re-encoded storm record is the θ of the shipped one."""
    from metegs.meteo import default_theta

    theta = json.loads((result.folder / "out/synthetic/3dgs/run/decisions.json").read_text())["theta"]
    assert theta["rain"]["precip_mm_per_h"] == default_theta().rain.precip_mm_per_h == 6.8
    assert theta["rain"]["active"] and theta["rain"]["count"] > 0


def _no_run(flag: str, value: str) -> Case:
    """An explicit --conditions value metegs-train refuses while parsing, naming the flag."""
    name = flag.removeprefix("--conditions.")
    return Case(
        f"train-conditions-{name}-{value}", "metegs-train", lambda f: _train(f, flag, value), "clear", match=rf"{flag} "
    )


TRAIN_CASES = [
    _case("train-record-png", "metegs-train", lambda f: _train_record(f, _write(f, "storm.csv", PNG)), r"storm\.csv: is a PNG image"),
    _case("train-record-header-only", "metegs-train", lambda f: _train_record(f, _write(f, "storm.csv", _prsa_lines()[0] + "\n")), r"storm\.csv: holds no records"),
    _case("train-record-absurd-rain", "metegs-train", lambda f: _train_record(f, _prsa(f, "RAIN", "1e9")), r"storm\.csv: line 17, field 'RAIN'.*more rain than ever measured"),
    _case("train-record-stray-cr", "metegs-train", lambda f: _train_record(f, _prsa(f, "WSPM", "1\r.5")), r"storm\.csv: line 17: a stray carriage return"),
    _case("train-record-metar-p9999", "metegs-train", lambda f: _train(f, "--degrade", "rain", "--conditions.record", _metar(f, "KAAA 011353Z 27008KT 5SM +RA RMK AO2 P9999="), "--conditions.time", "2024-05-01T13:53Z", "--conditions.set", "year=2024", "month=5"), r"reports\.txt: line 2, field 'P'"),
    Case("train-record-utf8-bom-crlf", "metegs-train", lambda f: _train_record(f, _write(f, "storm.csv", codecs.BOM_UTF8 + "\r\n".join(_prsa_lines()).encode())), "correct", check=_theta_of_storm),
    _case("train-conditions-time-unreadable", "metegs-train", lambda f: _train(f, "--conditions.time", "yesterday"), r"--conditions\.time: cannot read time 'yesterday'"),
    _case("train-conditions-window-negative", "metegs-train", lambda f: _train(f, "--conditions.window", "-1h"), r"--conditions\.window: cannot read duration '-1h'"),
    _case("train-conditions-wind-without-rate", "metegs-train", lambda f: _train(f, "--conditions.wind-speed-m-s", "3"), r"--conditions\.wind-\* go with --conditions\.precip-mm-h"),
    *(
        _no_run(flag, value)
        for flag, values in {
            "--conditions.precip-mm-h": ("-1", "nan", "inf", "1e9", "2500"),
            "--conditions.visibility-m": ("-1", "0", "0.5", "nan", "inf"),
            "--conditions.wind-speed-m-s": ("-1", "nan", "inf", "500"),
            "--conditions.wind-dir-deg": ("-10", "nan", "inf", "400"),
            "--conditions.exposure-s": ("0", "-1", "nan", "inf", "1e6"),
            "--conditions.metres-per-unit": ("0", "-1", "nan", "inf"),
            "--conditions.capture-width-px": ("-1", "1000000000"),
        }.items()
        for value in values
    ),
]  # fmt: skip


# --- metegs-synth with a bad record -----------------------------------------------------------------------------
def _synth(folder: Path, record: Path, *extra) -> list:
    tiny = [
        "--dataset.synthetic.width", "32", "--dataset.synthetic.height", "24", "--dataset.synthetic.num-views", "2",
        "--dataset.synthetic.num-points", "200", "--preview-views", "1",
    ]  # fmt: skip
    return ["--output", folder / "synth", "--record", record, "--time", STORM_TIME, *tiny, *extra]


def _synth_of_storm(result: Result) -> None:
    weather = json.loads((result.folder / "synth/weather.json").read_text())
    assert {v["theta"]["rain"]["precip_mm_per_h"] for v in weather["views"]} == {6.8}


SYNTH_CASES = [
    _case("synth-record-binary", "metegs-synth", lambda f: _synth(f, _write(f, "storm.csv", NOISE)), r"storm\.csv: is a binary file"),
    _case("synth-record-header-only", "metegs-synth", lambda f: _synth(f, _write(f, "storm.csv", _prsa_lines()[0] + "\n")), r"storm\.csv: holds no records"),
    _case("synth-record-absurd-rain", "metegs-synth", lambda f: _synth(f, _prsa(f, "RAIN", "99999")), r"storm\.csv: line 17, field 'RAIN': 99999 mm in 1 h"),
    _case("synth-record-absurd-wind", "metegs-synth", lambda f: _synth(f, _prsa(f, "WSPM", "300")), r"storm\.csv: line 17, field 'wind speed'"),
    _case("synth-record-ghcnh-header-only", "metegs-synth", lambda f: _synth(f, _write(f, "station.psv", GHCNH_HEADER + "\n")), r"station\.psv: holds no records"),
    Case("synth-record-utf8-bom", "metegs-synth", lambda f: _synth(f, _write(f, "storm.csv", codecs.BOM_UTF8 + "\n".join(_prsa_lines()).encode())), "correct", check=_synth_of_storm),
]  # fmt: skip

CASES = READER_CASES + TRAIN_CASES + SYNTH_CASES
