"""Benchmark conditions picked from real records: rain hours per WMO class, fog per visibility."""

from pathlib import Path

import pytest

from metegs.bench.conditions import (
    CLASS_TARGET_MM_H,
    ConditionSpec,
    class_bounds,
    pick_rain_hour,
    pick_visibility,
    resolve_condition,
)
from metegs.errors import ConfigError, DataError
from metegs.meteo import default_storm_path

SHARED = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "meteo"
PRSA = SHARED / "beijing-prsa" / "PRSA_Data_Aotizhongxin_20130301-20170228.csv"
ISD = SHARED / "isd-janmayen-1988" / "DS3505.txt"


def need(path: Path) -> Path:
    if not path.is_file():
        pytest.skip(f"{path} absent (shared data only in development checkouts)")
    return path


def test_class_targets_lie_inside_their_classes():
    for name, target in CLASS_TARGET_MM_H.items():
        lo, hi = class_bounds(name)
        assert lo < target < hi
    with pytest.raises(ConfigError, match="unknown WMO rain class"):
        class_bounds("torrential")


def test_rain_hours_of_the_shipped_storm():
    storm = default_storm_path()
    violent = pick_rain_hour(storm, "violent")
    assert violent.precip_mm_h == pytest.approx(72.5) and violent.time == "2013-08-11T06:30Z"
    moderate = pick_rain_hour(storm, "moderate")
    assert 2.5 <= moderate.precip_mm_h < 10 and moderate.wmo_class == "moderate"
    with pytest.raises(DataError, match="heavy"):
        pick_rain_hour(storm, "heavy")  # the excerpt jumps from 6.8 to 72.5 mm/h


@pytest.mark.data
def test_every_wmo_class_is_found_in_the_prsa_record():
    path = need(PRSA)
    picks = {c: pick_rain_hour(path, c) for c in ("light", "moderate", "heavy", "violent")}
    for cls, pick in picks.items():
        lo, hi = class_bounds(cls)
        assert lo < pick.precip_mm_h < hi and pick.wmo_class == cls and pick.station == "Aotizhongxin"
    assert picks["violent"].precip_mm_h == pytest.approx(72.5)


@pytest.mark.data
def test_fog_observations_near_the_target_visibilities():
    path = need(ISD)
    for target in (1000, 500, 200):
        pick = pick_visibility(path, target)
        assert 1 / 1.5 <= pick.visibility_m / target <= 1.5
        assert pick.fog_kind in ("fog", "mist") and pick.present_weather
    with pytest.raises(DataError, match="calls for fog"):
        pick_visibility(path, 1e6)


@pytest.mark.data
def test_rain_and_fog_condition_records_both_sources():
    rc = resolve_condition(
        ConditionSpec(
            "rf",
            "rain+fog",
            rain={"record": str(need(PRSA)), "class": "heavy"},
            fog={"record": str(need(ISD)), "visibility_m": 500},
        )
    )
    assert rc.conditions.record == PRSA and rc.conditions.visibility_m == rc.provenance["fog"]["visibility_m"]
    assert rc.provenance["rain"]["wmo_class"] == "heavy" and rc.provenance["fog"]["present_weather"]
    assert rc.to_dict()["conditions"]["time"] == rc.provenance["rain"]["time"]


def test_explicit_and_given_time_conditions():
    rc = resolve_condition(
        ConditionSpec("x", "rain+fog", rain={"precip_mm_h": 12.0}, fog={"visibility_m": 300, "explicit": True})
    )
    assert rc.conditions.precip_mm_h == 12.0 and rc.conditions.visibility_m == 300 and rc.conditions.record is None
    storm = default_storm_path()
    rc = resolve_condition(ConditionSpec("y", "rain", rain={"record": str(storm), "time": "2013-08-11T06:30Z"}))
    assert rc.provenance["rain"]["precip_mm_h"] == pytest.approx(72.5) and rc.conditions.time == "2013-08-11T06:30Z"


def test_bad_condition_specs_are_clear():
    with pytest.raises(ConfigError, match="kind"):
        ConditionSpec("a", "snow", rain={"precip_mm_h": 1})
    with pytest.raises(ConfigError, match="needs a 'fog:' source"):
        ConditionSpec("a", "rain+fog", rain={"precip_mm_h": 1})
    with pytest.raises(ConfigError, match="unknown key"):
        resolve_condition(ConditionSpec("a", "rain", rain={"precip": 1}))
    with pytest.raises(ConfigError, match="not found"):
        resolve_condition(ConditionSpec("a", "rain", rain={"record": "/nowhere.csv", "class": "light"}))
