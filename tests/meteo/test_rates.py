"""Accumulations → rates: no double counting of overlapping periods, gaps stay gaps, de-accumulation."""

from __future__ import annotations

from datetime import datetime, timedelta, timezone

import numpy as np
import pytest

from metegs.meteo import MeteoWarning, Observation, ObservationTable, precip_series
from metegs.meteo.observations import Accumulation
from metegs.meteo.rates import deaccumulate

T0 = datetime(2024, 6, 1, tzinfo=timezone.utc)


def at(minutes: float) -> datetime:
    return T0 + timedelta(minutes=minutes)


def obs(minutes, *accums, line=None, **kw):
    return Observation(time_utc=at(minutes), station="KAAA", precip_accums=tuple(accums), line=line, **kw)


def test_speci_inside_hourly_is_not_counted_twice():
    # routine 00:53 (start), SPECI 01:20 with P = 2 mm since 00:53, routine 01:53 with P = 5 mm for the hour
    table = ObservationTable(
        [obs(53), obs(80, Accumulation(2.0, 27 / 60), line=2), obs(113, Accumulation(5.0, 1.0), line=3)]
    )
    s = precip_series(table)
    assert len(s) == 2
    assert np.allclose((s.end_s - s.start_s) / 60, [27, 33])
    assert np.allclose(s.rate_mm_per_h * (s.end_s - s.start_s) / 3600, [2.0, 3.0])  # total stays 5 mm
    assert s.rate_mm_per_h[0] == pytest.approx(2.0 / (27 / 60))


def test_six_hour_total_around_a_three_hour_one():
    table = ObservationTable([obs(180, Accumulation(1.2, 3.0)), obs(360, Accumulation(3.0, 6.0))])
    s = precip_series(table)
    assert np.allclose(s.rate_mm_per_h, [0.4, 0.6])


def test_partial_overlap_and_contradiction_are_dropped_with_a_warning():
    table = ObservationTable(
        [
            obs(60, Accumulation(1.0, 1.0), line=1),
            obs(90, Accumulation(4.0, 1.0), line=2),
            obs(120, Accumulation(0.5, 2.0), line=3),
        ],
        source="x.txt",
    )
    with pytest.warns(
        MeteoWarning,
        match=r"x\.txt station KAAA: ignored 2 precipitation period\(s\).*line 2: its period overlaps another one only partly.*line 3: 0\.5 mm",
    ):
        s = precip_series(table)
    assert len(s) == 1 and s.rate_mm_per_h[0] == 1.0


def test_gaps_stay_gaps():
    table = ObservationTable([obs(60, Accumulation(1.0, 1.0)), obs(300, Accumulation(2.0, 1.0))])
    s = precip_series(table)
    assert s.covered_s() == 2 * 3600  # the three hours between have no data, and no invented zeros
    assert s.overlap_s(at(120).timestamp(), at(180).timestamp()).sum() == 0


def test_traces_and_rates():
    table = ObservationTable(
        [
            obs(60, Accumulation(0.0, 1.0, trace=True)),
            Observation(time_utc=at(120), station="KAAA", precip_rate_mm_per_h=3.0, precip_rate_period_h=0.5),
        ]
    )
    s = precip_series(table, trace_amount_mm=0.05)
    assert np.allclose(s.rate_mm_per_h, [0.05, 3.0]) and s.trace.tolist() == [True, False]
    assert precip_series(table, trace_amount_mm=0.0).rate_mm_per_h[0] == 0.0


def test_era5_land_ramp_and_daily_rollover():
    hours = np.arange(1, 49)  # 01 UTC day 1 .. 00 UTC day 3
    times = [(T0 + timedelta(hours=int(h))).timestamp() for h in hours]
    totals = [((h - 1) % 24 + 1) * 0.5 for h in hours]  # 0.5 mm/h, running since 00 UTC; 00 UTC holds the day's total
    steps = deaccumulate(times, totals, reset_hour_utc=0)
    assert steps[0] == (0.5, 1.0)  # the first total counts from 00 UTC
    assert all(step == pytest.approx((0.5, 1.0)) for step in steps)


def test_running_total_without_reset_that_decreases():
    steps = deaccumulate([0, 3600, 7200], [1.0, 2.0, 0.5])
    assert steps[0] is None and steps[1] == (1.0, 1.0)
    assert "decreases from 2 to 0.5 mm" in steps[2]


def test_running_total_through_the_csv_reader(tmp_path):
    from metegs.meteo import read_observations

    lines = ["time,tp"] + [
        f"{(T0 + timedelta(hours=h)).isoformat()},{((h - 1) % 24 + 1) * 0.2:.1f}" for h in range(1, 30)
    ]
    path = tmp_path / "era5land.csv"
    path.write_text("\n".join(lines) + "\n")
    table = read_observations(path, reader="csv", precip_column="tp", precip_kind="running", precip_reset_hour_utc=0)
    s = precip_series(table)
    assert len(s) == 29 and np.allclose(s.rate_mm_per_h, 0.2)
