"""Aggregation over a window, WMO classes, the paper's normalisation and present-weather gating."""

from __future__ import annotations

from datetime import datetime, timedelta, timezone

import pytest

from metegs.errors import ConfigError, DataError
from metegs.meteo import (
    Observation,
    ObservationTable,
    conditions_at,
    default_storm_record,
    intensity_class,
    normalised_intensity,
    wmo_score,
)
from metegs.meteo.observations import Accumulation
from metegs.meteo.weather_codes import parse_weather_token

T0 = datetime(2024, 6, 1, tzinfo=timezone.utc)


def hourly(rates, **kw):
    return ObservationTable(
        [
            Observation(time_utc=T0 + timedelta(hours=i + 1), station="S", precip_accums=(Accumulation(r, 1.0),), **kw)
            for i, r in enumerate(rates)
        ]
    )


def wx(*codes):
    return tuple(parse_weather_token(c) for c in codes)


@pytest.mark.parametrize(
    ("rate", "kind", "expected"),
    [
        (0, "rain", "none"),
        (0.3, "rain", "light"),
        (2.5, "rain", "moderate"),
        (9.99, "rain", "moderate"),
        (10, "rain", "heavy"),
        (50, "rain", "violent"),
        (0.05, "drizzle", "light"),
        (0.2, "drizzle", "moderate"),
        (0.6, "drizzle", "heavy"),
        (None, "rain", "unknown"),
    ],
)
def test_wmo_classes(rate, kind, expected):
    assert intensity_class(rate, kind) == expected


def test_scores():
    assert (
        wmo_score(0) == 0
        and wmo_score(2.5) == pytest.approx(0.25)
        and wmo_score(50) == pytest.approx(0.75)
        and wmo_score(500) == 1
    )
    assert (
        normalised_intensity(5, 0, 10) == 0.5
        and normalised_intensity(20, 0, 10) == 1
        and normalised_intensity(-1, 0, 10) == 0
    )
    assert normalised_intensity(3, 2, 2) == 0


def test_window_mean_max_min():
    table = hourly([0.0, 2.0, 8.0, 1.0])  # hours ending 01, 02, 03, 04 UTC
    t = T0 + timedelta(hours=2, minutes=30)  # 1-h window 02:00-03:00 lies in the 8 mm/h hour
    assert conditions_at(table, t, "1h", "max").precip_mm_per_h == 8.0
    c = conditions_at(table, t, "2h", "mean")  # 01:30-03:30: half of 2, all of 8, half of 1
    assert c.precip_mm_per_h == pytest.approx((0.5 * 2 + 8 + 0.5 * 1) / 2)
    assert conditions_at(table, t, "2h", "min").precip_mm_per_h == 1.0
    assert c.intensity_class == "moderate" and c.normalised == pytest.approx(4.75 / 8)
    assert conditions_at(table, t, "2h", "mean", p_range_mm_per_h=(0, 4)).normalised == 1.0
    assert conditions_at(table, T0 + timedelta(hours=3), "1h", "max", align="before").precip_mm_per_h == 8.0


def test_gap_is_unknown_not_zero():
    table = hourly([1.0, 1.0])
    c = conditions_at(table, T0 + timedelta(hours=10), "1h", "max")
    assert c.precip_mm_per_h is None and not c.rain_active and c.precip_source == "none"
    assert any("no record within 3 h" in n for n in c.notes)
    half = conditions_at(table, T0 + timedelta(hours=2), "2h", "mean")
    assert half.precip_coverage == pytest.approx(0.5) and half.precip_mm_per_h == 1.0


def test_fog_without_rain_and_rain_without_fog():
    fog = ObservationTable(
        [
            Observation(
                time_utc=T0, station="S", visibility_m=300, weather=wx("FG"), precip_accums=(Accumulation(1.2, 6.0),)
            )
        ]
    )
    c = conditions_at(fog, T0, "1h", "max")
    assert c.fog_active and c.fog_kind == "fog" and not c.rain_active  # the 6-h amount fell earlier
    rain = ObservationTable(
        [
            Observation(
                time_utc=T0, station="S", visibility_m=4000, weather=wx("RA"), precip_accums=(Accumulation(6.0, 1.0),)
            )
        ]
    )
    c = conditions_at(rain, T0, "1h", "max")
    assert c.rain_active and not c.fog_active and c.precip_mm_per_h == 6.0


def test_present_weather_gives_a_rate_when_nothing_is_measured():
    table = ObservationTable([Observation(time_utc=T0, station="EDDF", visibility_m=6000, weather=wx("+SHRA", "BR"))])
    c = conditions_at(table, T0, "1h", "max")
    assert c.precip_source == "present_weather" and c.precip_mm_per_h == 22.0
    assert c.rain_active and c.fog_active and c.fog_kind == "mist"
    snow = ObservationTable(
        [Observation(time_utc=T0, station="S", weather=wx("SN"), precip_accums=(Accumulation(1.0, 1.0),))]
    )
    c = conditions_at(snow, T0, "1h", "max")
    assert c.precip_kind == "snow" and not c.rain_active


def test_visibility_and_wind_follow_the_aggregation():
    recs = [
        Observation(
            time_utc=T0 + timedelta(minutes=m), station="S", visibility_m=v, wind_speed_m_per_s=u, wind_dir_deg_from=d
        )
        for m, v, u, d in ((0, 4000, 2.0, 350), (20, 800, 6.0, 10), (40, 10000, 4.0, 30))
    ]
    table = ObservationTable(recs)
    t = T0 + timedelta(minutes=20)
    mx = conditions_at(table, t, "1h", "max")
    assert mx.visibility_m == 800 and mx.wind_speed_m_per_s == 6.0 and mx.wind_dir_deg_from == 10
    assert conditions_at(table, t, "1h", "min").visibility_m == 10000
    mean = conditions_at(table, t, "1h", "mean")
    assert mean.visibility_m == pytest.approx(3 / (1 / 4000 + 1 / 800 + 1 / 10000))
    assert mean.wind_speed_m_per_s == pytest.approx(4.0) and mean.wind_dir_deg_from == pytest.approx(12.6, abs=1.0)
    assert mean.fog_active and mean.fog_kind == "mist"  # 1.9 km, no rain, no present weather: visibility decides


def test_errors():
    table = hourly([1.0])
    with pytest.raises(ConfigError, match="unknown aggregation 'median'"):
        conditions_at(table, T0, "1h", "median")
    two = ObservationTable([Observation(time_utc=T0, station="A"), Observation(time_utc=T0, station="B")])
    with pytest.raises(DataError, match="holds 2 stations"):
        conditions_at(two, T0)
    with pytest.raises(DataError, match="cannot read time"):
        conditions_at(table, "noon")


def test_shipped_storm_range():
    table = default_storm_record()
    assert len(table) == 28
    classes = {conditions_at(table, r.time_utc - timedelta(minutes=30), "1h", "max").intensity_class for r in table}
    assert {"none", "light", "moderate", "violent"} <= classes
