"""Explicit `--conditions.*` values are refused when the options are parsed, naming the flag as typed."""

from __future__ import annotations

import math

import pytest
import tyro

from metegs.errors import ConfigError
from metegs.meteo import theta_from_values
from metegs.weather.conditions import ConditionsConfig

BAD = {
    "precip_mm_h": (-1.0, math.nan, math.inf, 1e9, 2540.0),
    "visibility_m": (-1.0, 0.0, 0.5, math.nan, math.inf),
    "wind_speed_m_s": (-1.0, math.nan, math.inf, 500.0),
    "wind_dir_deg": (-10.0, math.nan, math.inf, 400.0),
    "exposure_s": (0.0, -1.0, math.nan, math.inf, 1e6),
    "metres_per_unit": (0.0, -1.0, math.nan, math.inf),
    "capture_width_px": (-1, 10**9),
}


@pytest.mark.parametrize(("name", "value"), [(n, v) for n, vs in BAD.items() for v in vs])
def test_impossible_values_name_the_flag(name, value):
    extra = {"precip_mm_h": 5.0} if name.startswith("wind") else {}
    with pytest.raises(ConfigError, match=rf"^--conditions\.{name.replace('_', '-')} "):
        ConditionsConfig(**{name: value, **extra})


def test_the_bounds_themselves_are_accepted():
    c = ConditionsConfig(precip_mm_h=2400.0, visibility_m=1.0, wind_speed_m_s=120.0, wind_dir_deg=360.0)
    assert c.precip_mm_h == 2400.0 and ConditionsConfig(precip_mm_h=0.0, wind_dir_deg=0.0).wind_dir_deg == 0.0


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"time": "yesterday"}, r"--conditions\.time: cannot read time 'yesterday'"),
        ({"window": "-1h"}, r"--conditions\.window: cannot read duration '-1h'"),
        ({"record": "x.csv", "set": ("year",)}, r"--conditions\.set expects KEY=VALUE, got 'year'"),
        ({"wind_dir_deg": 90.0}, r"--conditions\.wind-\* go with --conditions\.precip-mm-h"),
        ({"station": "X"}, r"need --conditions\.record"),
    ],
)
def test_other_options_are_checked_when_parsed(kwargs, match):
    with pytest.raises(ConfigError, match=match):
        ConditionsConfig(**kwargs)


def test_tyro_surfaces_the_error_at_parse_time():
    with pytest.raises(ConfigError, match=r"--conditions\.wind-dir-deg inf"):
        tyro.cli(ConditionsConfig, args=["--precip-mm-h", "5", "--wind-dir-deg", "inf"])


def test_theta_from_values_refuses_a_non_finite_direction():
    with pytest.raises(ConfigError, match="wind_dir_deg_from must be a finite number"):
        theta_from_values(5.0, None, 3.0, math.inf)
