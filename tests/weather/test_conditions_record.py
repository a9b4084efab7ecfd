"""`--conditions.record` with reader options: any csv or METAR file drives a training run's weather."""

import pytest

from metegs.data.config import DatasetConfig, SyntheticSceneConfig
from metegs.data.parsers.base import parse_scene
from metegs.errors import ConfigError, DataError
from metegs.weather.conditions import ConditionsConfig, theta_for_cameras


@pytest.fixture(scope="module")
def cameras():
    scene = parse_scene(None, None, DatasetConfig(synthetic=SyntheticSceneConfig(width=32, height=24, num_views=2)))
    return scene.cameras


def test_a_csv_with_its_own_columns(tmp_path, cameras):
    path = tmp_path / "station.csv"
    path.write_text("when,rr_mm_h,vis_km\n2024-05-01T10:00Z,3.0,20\n2024-05-01T11:00Z,12.5,0.4\n")
    config = ConditionsConfig(
        record=path,
        time="2024-05-01T11:00Z",
        window="30min",
        set=(
            "time_columns=when",
            "precip_column=rr_mm_h",
            "precip_kind=rate",
            "visibility_column=vis_km",
            "visibility_unit=km",
        ),
    )
    theta = theta_for_cameras(config, cameras, 10.0)
    assert theta.conditions.precip_mm_per_h == pytest.approx(12.5)
    assert theta.fog.visibility_m == pytest.approx(400.0)


def test_the_csv_without_options_names_what_is_missing(tmp_path, cameras):
    path = tmp_path / "station.csv"
    path.write_text("when,rr_mm_h\n2024-05-01T10:00Z,3.0\n")
    with pytest.raises(
        DataError,
        match=r"station\.csv: cannot tell which columns to read: no time column found.*--set time_columns=.*"
        r"columns: when, rr_mm_h",
    ):
        theta_for_cameras(ConditionsConfig(record=path, time="2024-05-01T10:00Z"), cameras, 10.0)


def test_reader_options_need_a_record(cameras):
    with pytest.raises(ConfigError, match="need --conditions.record"):
        theta_for_cameras(ConditionsConfig(set=("year=2024",)), cameras, 10.0)
