"""Snow physics against the published fits and their own consistency."""

import math

import pytest
import torch

from metegs_snow.physics import (
    MAX_RATE_MM_H,
    fall_speed_m_s,
    flake_diameter_mm,
    gm_intercept_per_m3_per_mm,
    gm_lambda_per_mm,
    gm_number_density_per_m3,
    gm_sample_melted_diameter_mm,
    gm_water_flux_mm_h,
    map_snow,
)

RATES = [0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 3.0, 5.0, 7.0, 10.0, 30.0]


def snow(rate, wind=0.0):
    return map_snow(rate, wind, 90.0 if wind else None, 1 / 60, 60.0, 40.0, 0.5, 10.0)


def test_gunn_marshall_numbers():
    assert gm_intercept_per_m3_per_mm(1.0) == pytest.approx(3.8e3)
    assert gm_lambda_per_mm(1.0) == pytest.approx(2.55)  # 25.5 cm⁻¹
    assert gm_intercept_per_m3_per_mm(10.0) == pytest.approx(3.8e3 * 10**-0.87)
    assert gm_lambda_per_mm(10.0) == pytest.approx(2.55 * 10**-0.48)


@pytest.mark.parametrize("rate", [0.1, 0.3, 1.0, 3.0, 10.0])
def test_distribution_carries_the_rate_at_one_metre_per_second(rate):
    """The check that D is the melted diameter: π·N0·v/Λ⁴ ≈ R at v ≈ 1 m/s (numerically integrated too)."""
    assert gm_water_flux_mm_h(rate) == pytest.approx(rate, rel=0.15)
    lam, n0 = gm_lambda_per_mm(rate), gm_intercept_per_m3_per_mm(rate)
    d = torch.linspace(0, 40 / lam, 20001, dtype=torch.float64)
    integrand = math.pi / 6 * d**3 * n0 * torch.exp(-lam * d)
    numeric = float(torch.trapezoid(integrand, d)) * 3600 / 1e6
    assert numeric == pytest.approx(gm_water_flux_mm_h(rate), rel=1e-4)


def test_locatelli_hobbs_flake_is_about_four_mm_and_falls_about_one_metre_per_second():
    d = float(flake_diameter_mm(torch.tensor(1.0, dtype=torch.float64)))
    assert d == pytest.approx(4.08, abs=0.05)
    assert 0.95 < fall_speed_m_s(d) < 1.05
    dm = torch.linspace(0.05, 5.0, 200, dtype=torch.float64)
    flake = flake_diameter_mm(dm)
    assert bool((flake >= dm).all()) and bool((flake.diff() >= 0).all())


def test_sampled_sizes_follow_the_truncated_distribution():
    gen = torch.Generator().manual_seed(0)
    u = torch.rand(200_000, generator=gen, dtype=torch.float64)
    d = gm_sample_melted_diameter_mm(u, 1.0, 0.5, 3.0)
    assert float(d.min()) >= 0.5 and float(d.max()) <= 3.0
    assert float(d.mean()) == pytest.approx(snow(1.0).melted_mean_mm, rel=0.01)


def test_zero_rate_is_inactive_and_finite():
    p = snow(0.0)
    assert not p.active and p.expected_count == 0 and p.area_density_per_m == 0
    assert all(math.isfinite(v) for v in (p.lambda_per_mm, p.flake_mean_mm, p.fall_speed_m_s, p.tilt_deg))
    with pytest.raises(ValueError):
        snow(-1.0)


def test_monotone_in_rate():
    with pytest.warns(UserWarning, match="beyond the heaviest snowfalls"):
        ps = [snow(r) for r in RATES]
    for name in ("area_density_per_m", "flake_mean_mm", "melted_mean_mm", "fall_speed_m_s", "rate_mm_h"):
        values = [getattr(p, name) for p in ps]
        assert all(b >= a for a, b in zip(values, values[1:])), (name, values)
    lams = [p.lambda_per_mm for p in ps]
    assert all(b <= a for a, b in zip(lams, lams[1:]))
    assert ps[-1].rate_mm_h == MAX_RATE_MM_H  # clamped


def test_flake_count_peaks_near_two_mm_per_hour_as_documented():
    densities = {r: gm_number_density_per_m3(r, 0.5, 3.0) for r in RATES if r <= MAX_RATE_MM_H}
    peak = max(densities, key=densities.get)
    assert 1.0 <= peak <= 3.0


def test_tilt_grows_with_the_wind():
    tilts = [snow(1.0, wind).tilt_deg for wind in (0.0, 0.5, 1.0, 3.0)]
    assert tilts[0] == 0.0 and all(b > a for a, b in zip(tilts, tilts[1:]))
    p = snow(1.0, 1.0)
    assert p.tilt_deg == pytest.approx(math.degrees(math.atan(1.0 / p.fall_speed_m_s)))
