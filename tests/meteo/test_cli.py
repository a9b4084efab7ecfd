"""`metegs-meteo summary` writes a PNG and prints the period; `metegs-meteo at` prints θ."""

from __future__ import annotations

import json

import cv2
import pytest

from metegs.cli.meteo import main
from metegs.errors import ConfigError, DataError
from metegs.meteo import DEFAULT_CAPTURE_TIME, default_storm_record, default_theta
from metegs.meteo.storm import STORM_READER_OPTIONS

from .conftest import shared_file


def test_summary_of_the_shipped_storm_writes_a_png(tmp_path, capsys):
    out = tmp_path / "plots" / "storm.png"
    written = main(["summary", "--plot", str(out)])
    assert written == out and out.is_file()
    img = cv2.imread(str(out))
    assert img is not None and img.shape[0] > 500 and img.shape[1] > 1000
    text = capsys.readouterr().out
    assert "72.50" in text and "violent" in text and "moderate" in text and f"wrote {out}" in text
    assert not list(out.parent.glob(".*.tmp"))  # written atomically


@pytest.mark.data
def test_summary_of_a_real_file_with_reader_options(tmp_path, capsys):
    path = shared_file("beijing-prsa", "PRSA_Data_Aotizhongxin_20130301-20170228.csv")
    options = [f"{k}={','.join(v) if isinstance(v, tuple) else v}" for k, v in STORM_READER_OPTIONS.items()]
    out = tmp_path / "beijing.png"
    main(
        [
            "summary",
            str(path),
            "--reader",
            "csv",
            "--set",
            *options,
            "--start",
            "2016-07-19T00:00Z",
            "--end",
            "2016-07-22T00:00Z",
            "--plot",
            str(out),
            "--max-rows",
            "12",
        ]
    )
    text = capsys.readouterr().out
    assert out.is_file() and "heavy" in text and "bin start" in text


@pytest.mark.data
def test_summary_of_a_metar_collective(tmp_path, capsys):
    path = shared_file("metar-pyiem", "collective.txt")
    out = tmp_path / "kmia.png"
    with pytest.warns(UserWarning):
        main(["summary", str(path), "--set", "year=2024", "month=6", "--station", "KMIA", "--plot", str(out)])
    assert out.is_file() and "+TSRA" in capsys.readouterr().out


def test_at_prints_theta(capsys):
    theta = main(["at"])
    text = capsys.readouterr().out
    assert theta.conditions.time_utc == DEFAULT_CAPTURE_TIME
    assert "θ_rain" in text and "θ_fog" in text and "θ_drops" in text and "number_density_per_m3" in text
    assert theta.rain.active and theta.rain.intensity_class == "moderate" and theta.rain.precip_mm_per_h == 6.8


def test_at_json_and_options(tmp_path, capsys):
    path = tmp_path / "obs.csv"
    path.write_text(
        "time,rain,vis\n2024-01-01T00:00Z,0.0,20000\n2024-01-01T01:00Z,12.0,1500\n2024-01-01T02:00Z,1.0,8000\n"
    )
    main(
        [
            "at",
            str(path),
            "--time",
            "2024-01-01T00:40Z",
            "--window",
            "30min",
            "--agg",
            "mean",
            "--set",
            "time_columns=time",
            "precip_column=rain",
            "visibility_column=vis",
            "--exposure-s",
            "0.004",
            "--json",
        ]
    )
    doc = json.loads(capsys.readouterr().out)
    assert doc["rain"]["precip_mm_per_h"] == 12.0 and doc["rain"]["exposure_s"] == 0.004
    assert doc["fog"]["visibility_m"] == 1500.0 and doc["conditions"]["agg"] == "mean"


def test_cli_errors(tmp_path):
    with pytest.raises(ConfigError, match="--time is needed"):
        main(["at", str(tmp_path / "x.csv")])
    with pytest.raises(DataError, match="file does not exist"):
        main(["at", str(tmp_path / "x.csv"), "--time", "2024-01-01T00:00Z"])
    with pytest.raises(ConfigError, match="KEY=VALUE"):
        main(["summary", str(tmp_path / "x.csv"), "--set", "year"])


def test_entrypoint_turns_errors_into_exit_code_2(tmp_path, monkeypatch, capsys):
    from metegs.cli import meteo

    monkeypatch.setattr(
        "sys.argv", ["metegs-meteo", "at", str(tmp_path / "missing.csv"), "--time", "2024-01-01T00:00Z"]
    )
    with pytest.raises(SystemExit) as exc:
        meteo.entrypoint()
    assert exc.value.code == 2 and "missing.csv: file does not exist" in " ".join(capsys.readouterr().err.split())


def test_shipped_storm_and_default_theta():
    table = default_storm_record()
    assert table.stations == ["Aotizhongxin"] and len(table) == 28
    assert max(r.precip_accum_mm for r in table) == 72.5
    theta = default_theta()
    assert theta.rain.active and theta.rain.count > 0 and theta.conditions.time_utc == DEFAULT_CAPTURE_TIME
