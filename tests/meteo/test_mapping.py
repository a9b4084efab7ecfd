"""The mapping θ: property tests (monotone, bounded, finite), the fog-lattice rule, and the §8.4/§8.5 checks."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from metegs.errors import ConfigError
from metegs.meteo import CameraSpec, MappingConfig, PaperMapping, physics, theta_from_values

FAST = settings(max_examples=150, deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow])

RAIN_UP_IN_P = (
    "number_density_per_m3",
    "diameter_mean_mm",
    "diameter_median_volume_mm",
    "fall_speed_m_per_s",
    "streak_length_m",
    "sigma_parallel_m",
    "sigma_perp_m",
    "far_m",
    "frustum_volume_m3",
    "expected_count",
    "count",
    "opacity_effective",
    "beta_rain_per_m",
    "wmo_score",
)
RAIN_DOWN_IN_P = ("lambda_per_mm", "tilt_deg", "subsample_ratio")
FOG_UP_IN_P = ("beta_rain_per_m", "beta_total_per_m", "beta_veil_per_m")
FOG_DOWN_IN_P = ("beta_fog_per_m", "lattice_opacity")
FOG_UP_IN_INV_V = ("beta_total_per_m", "beta_fog_per_m", "beta_veil_per_m", "lattice_opacity")
RAIN_DOWN_IN_INV_V = ("far_m", "frustum_volume_m3", "expected_count", "count", "opacity_effective")

rates = st.floats(0.0, 500.0, allow_nan=False)
visibilities = st.one_of(st.none(), st.floats(1.0, 50_000.0))
winds = st.floats(0.0, 40.0)
directions = st.one_of(st.none(), st.floats(0.0, 359.9))
exposures = st.floats(1e-4, 0.1)
n_maxes = st.sampled_from([1_000, 100_000])


def assert_direction(lo, hi, names, up: bool, where: str) -> None:
    for name in names:
        a, b = getattr(lo, name), getattr(hi, name)
        tol = 1e-9 * max(abs(a), abs(b), 1e-300)
        if up:
            assert b >= a - tol, f"{where}.{name} decreased: {a} -> {b}"
        else:
            assert b <= a + tol, f"{where}.{name} increased: {a} -> {b}"


def camera_config(exposure, n_max):
    return CameraSpec(exposure_s=exposure), MappingConfig(n_max=n_max)


@FAST
@given(rates, rates, visibilities, winds, directions, exposures, n_maxes)
def test_rain_is_monotone_in_p(p1, p2, vis, wind, direction, exposure, n_max):
    p1, p2 = sorted((p1, p2))
    camera, config = camera_config(exposure, n_max)
    lo = theta_from_values(p1, vis, wind, direction, camera=camera, config=config)
    hi = theta_from_values(p2, vis, wind, direction, camera=camera, config=config)
    assert_direction(lo.rain, hi.rain, RAIN_UP_IN_P + ("opacity", "mean_coverage"), True, "rain")
    assert_direction(lo.rain, hi.rain, RAIN_DOWN_IN_P, False, "rain")
    assert_direction(lo.fog, hi.fog, FOG_UP_IN_P, True, "fog")
    assert_direction(lo.fog, hi.fog, FOG_DOWN_IN_P, False, "fog")
    assert_direction(lo.drops, hi.drops, ("arrival_rate_per_s", "count"), True, "drops")
    for a, b in zip(lo.fog.beta_rgb_per_m, hi.fog.beta_rgb_per_m):
        assert b <= a * (1 + 1e-9)


@FAST
@given(rates, rates, winds, exposures)
def test_drizzle_is_monotone_in_p(p1, p2, wind, exposure):
    p1, p2 = sorted((p1, p2))
    camera = CameraSpec(exposure_s=exposure)
    lo = theta_from_values(p1, None, wind, 90.0, kind="drizzle", camera=camera)
    hi = theta_from_values(p2, None, wind, 90.0, kind="drizzle", camera=camera)
    assert_direction(lo.rain, hi.rain, RAIN_UP_IN_P + ("opacity", "mean_coverage"), True, "rain")
    assert_direction(lo.rain, hi.rain, RAIN_DOWN_IN_P, False, "rain")
    assert hi.rain.diameter_mean_mm <= 0.5


@FAST
@given(rates, st.floats(1.0, 50_000.0), st.floats(1.0, 50_000.0), winds, exposures, n_maxes)
def test_monotone_in_inverse_visibility(p, v1, v2, wind, exposure, n_max):
    far_v, near_v = sorted((v1, v2), reverse=True)  # 1/near_v >= 1/far_v
    camera, config = camera_config(exposure, n_max)
    clear = theta_from_values(p, far_v, wind, 0.0, camera=camera, config=config)
    dense = theta_from_values(p, near_v, wind, 0.0, camera=camera, config=config)
    assert_direction(clear.fog, dense.fog, FOG_UP_IN_INV_V, True, "fog")
    for a, b in zip(clear.fog.beta_rgb_per_m, dense.fog.beta_rgb_per_m):
        assert b >= a * (1 - 1e-9)  # Kim's q jumps at 50 km: the range stops there
    assert_direction(clear.rain, dense.rain, RAIN_DOWN_IN_INV_V, False, "rain")
    assert_direction(clear.rain, dense.rain, ("subsample_ratio",), True, "rain")
    assert clear.rain.number_density_per_m3 == dense.rain.number_density_per_m3


def all_numbers(obj):
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        if isinstance(v, bool) or v is None or isinstance(v, str):
            continue
        if isinstance(v, (int, float)):
            yield f.name, v
        elif isinstance(v, tuple):
            for i, x in enumerate(v):
                if isinstance(x, (int, float)):
                    yield f"{f.name}[{i}]", x


@settings(max_examples=200, deadline=None, database=None)
@given(
    st.one_of(st.sampled_from([0.0, 500.0]), st.floats(0.0, 1e5)),
    st.one_of(st.none(), st.floats(0.05, 1e7)),
    st.floats(0.0, 80.0),
    directions,
    exposures,
    st.sampled_from(["rain", "drizzle"]),
)
def test_bounded_and_finite_for_every_non_negative_input(p, vis, wind, direction, exposure, kind):
    theta = theta_from_values(p, vis, wind, direction, kind=kind, camera=CameraSpec(exposure_s=exposure))
    for part in (theta.rain, theta.fog, theta.drops):
        for name, value in all_numbers(part):
            assert math.isfinite(value), f"{type(part).__name__}.{name} = {value}"
            assert value >= 0 or name.startswith("velocity_enu_m_per_s"), f"{name} = {value}"
    r, f = theta.rain, theta.fog
    assert 0 <= r.opacity <= 0.99 and 0 <= r.opacity_effective <= 0.99 and 0 <= r.mean_coverage <= 1
    assert 0 <= r.count <= r.n_max and 0 < r.subsample_ratio <= 1
    assert 0 <= r.tilt_deg < 90 and r.near_m <= r.far_m <= 10.0
    assert 0 <= f.lattice_opacity < 1 and f.beta_veil_per_m >= f.beta_rain_per_m
    assert 0 <= theta.drops.count <= 40


def test_zero_and_violent_rain():
    dry = theta_from_values(0.0)
    assert not dry.rain.active and dry.rain.count == 0 and dry.rain.number_density_per_m3 == 0
    assert dry.fog.beta_veil_per_m == pytest.approx(physics.LN20 / 25_000)
    storm = theta_from_values(500.0, None, 10.0, 180.0)
    assert storm.rain.active and storm.rain.intensity_class == "violent"
    assert storm.rain.count == min(100_000, round(storm.rain.expected_count))
    capped = theta_from_values(500.0, None, 10.0, 180.0, camera=CameraSpec(far_m=10.0)).rain
    assert capped.count == 100_000 and capped.opacity_effective > capped.opacity


def transmittance_through_lattice(beta, spacing, sigma, origin, direction, length):
    """Π(1 − o·e^{−r⊥²/2σ²}) over lattice Gaussians whose centres project onto the segment (3DGS compositing)."""
    o = physics.fog_lattice_opacity(beta, spacing, sigma)
    axis = int(np.argmax(np.abs(direction)))
    others = [a for a in range(3) if a != axis]
    reach = 4.0 * sigma
    end = origin + length * direction
    lo = math.floor((min(origin[axis], end[axis]) - reach) / spacing)
    hi = math.ceil((max(origin[axis], end[axis]) + reach) / spacing)
    half = int(math.ceil(reach / spacing / abs(direction[axis]) * 1.8)) + 1
    total = 0.0
    offsets = np.arange(-half, half + 1)
    gi, gj = np.meshgrid(offsets, offsets, indexing="ij")
    for k in range(lo, hi + 1):
        s = (k * spacing - origin[axis]) / direction[axis]  # where the ray's line meets this lattice plane
        cross = origin + s * direction
        centres = np.empty((gi.size, 3))
        centres[:, axis] = k * spacing
        centres[:, others[0]] = (np.round(cross[others[0]] / spacing) + gi.ravel()) * spacing
        centres[:, others[1]] = (np.round(cross[others[1]] / spacing) + gj.ravel()) * spacing
        rel = centres - origin
        t = rel @ direction
        inside = (t >= 0) & (t <= length)
        perp2 = np.einsum("ij,ij->i", rel, rel) - t * t
        g = np.exp(-perp2[inside] / (2 * sigma * sigma))
        total += np.log1p(-o * g).sum()
    return math.exp(total)


@settings(max_examples=40, deadline=None, database=None)
@given(st.floats(50.0, 2000.0), st.floats(20.0, 300.0), st.sampled_from([1.0, 0.8, 0.7]), st.integers(0, 2**32 - 1))
def test_fog_lattice_reproduces_beer_lambert(visibility, length, sigma_ratio, seed):
    """θ_fog's lattice (spacing, σ, opacity) composited like 3DGS along a random ray gives e^{−β·d} within 1 %.

    Directions are uniform on the sphere and origins uniform in a cell (numpy, seeded by hypothesis): a ray
    exactly parallel to a lattice axis is a measure-zero case that sees whole lattice planes.
    """
    fog = theta_from_values(0.0, visibility, config=MappingConfig(fog_sigma_ratio=sigma_ratio)).fog
    rng = np.random.default_rng(seed)
    d = rng.normal(size=3)
    d /= np.linalg.norm(d)
    origin = rng.uniform(0.0, fog.lattice_spacing_m, 3)
    t = transmittance_through_lattice(fog.beta_fog_per_m, fog.lattice_spacing_m, fog.lattice_sigma_m, origin, d, length)
    assert t == pytest.approx(math.exp(-fog.beta_fog_per_m * length), rel=0.01)


def test_fog_lattice_opacity_rule():
    beta = physics.beta_from_visibility_per_m(200.0)
    assert physics.fog_lattice_opacity(beta, 1.0, 1.0) == pytest.approx(beta / (2 * math.pi), rel=0.01)  # §8.2: 0.0024
    assert physics.fog_lattice_opacity(physics.beta_from_visibility_per_m(500.0), 2.0, 2.0) == pytest.approx(
        0.0019, abs=1e-4
    )
    dense = physics.fog_lattice_opacity(3.0, 1.0, 1.0)  # exact Li2 inversion, far from the small-o regime
    assert physics.dilogarithm(dense) == pytest.approx(3.0 / (2 * math.pi))
    with pytest.raises(ValueError, match="finer lattice"):
        physics.fog_lattice_opacity(20.0, 1.0, 1.0)
    assert theta_from_values(0.0, 0.2).fog.lattice_opacity <= 0.002  # very dense fog: the lattice is refined
    assert theta_from_values(0.0, 50.0).fog.lattice_spacing_m == pytest.approx(
        2 * math.pi * physics.dilogarithm(0.002) / (physics.LN20 / 50)
    )


def test_research_sanity_checks():
    # Gunn–Kinzer fall speeds within 2 % (§8.5)
    for d, v in ((1.0, 4.03), (2.0, 6.49), (5.0, 9.09)):
        assert physics.fall_speed_m_per_s(d) == pytest.approx(v, rel=0.02)
    # Marshall–Palmer flux consistency: (π/6)∫D³·v_t·N dD within [1.0, 1.2]·P
    d = np.linspace(1e-3, 6.0, 6000)
    v = np.array([physics.fall_speed_m_per_s(x) for x in d])
    for p in (1.0, 10.0, 100.0):
        n = physics.MP_N0_PER_M3_PER_MM * np.exp(-physics.mp_lambda_per_mm(p) * d)
        flux = 3.6e-3 * math.pi / 6 * np.trapezoid(d**3 * v * n, d)  # mm³ m⁻² s⁻¹ -> mm/h
        assert 1.0 <= flux / p <= 1.2
    assert physics.beta_from_visibility_per_m(1000.0, 0.05) == pytest.approx(0.002996, abs=1e-6)
    assert physics.beta_from_visibility_per_m(1000.0, 0.02) == pytest.approx(0.003912, abs=1e-6)
    # wind from 270° at 5 m/s: drops drift east (+x), tilt atan(5/v_t) (no log-law reduction at 10 m)
    theta = theta_from_values(10.0, None, 5.0, 270.0, config=MappingConfig(drop_height_m=10.0))
    east, north, up = theta.rain.velocity_enu_m_per_s
    assert east == pytest.approx(5.0) and abs(north) < 1e-9 and up < 0
    assert theta.rain.tilt_deg == pytest.approx(math.degrees(math.atan(5.0 / theta.rain.fall_speed_m_per_s)))
    assert physics.wind_at_height_m_per_s(10.0, 2.0, 0.03) == pytest.approx(7.2, abs=0.05)


@pytest.mark.parametrize(
    ("p", "n", "drops", "beta_km"),
    [
        (0.5, 158, 44e3, 0.196),
        (2.5, 436, 122e3, 0.576),
        (10, 894, 250e3, 1.46),
        (50, 1801, 505e3, 4.29),
        (100, 2354, 660e3, 6.83),
    ],
)
def test_worked_values(p, n, drops, beta_km):
    """Research note §8.4 (60°×40° frustum from 0.5 to 10 m, no cap)."""
    camera = CameraSpec(far_m=10.0)
    rain = theta_from_values(p, camera=camera, config=MappingConfig(n_max=10**7)).rain
    assert rain.number_density_per_m3 == pytest.approx(n, rel=0.01)
    assert rain.expected_count == pytest.approx(drops, rel=0.02)
    assert rain.beta_rain_per_m * 1000 == pytest.approx(beta_km, rel=0.01)
    assert rain.mean_coverage == pytest.approx(0.0115, abs=0.001)  # set by T = 1/60 s, not by P


def test_paper_form_is_available_and_the_physics_reduces_to_it():
    paper = PaperMapping.fit(CameraSpec(), MappingConfig(n_max=10**7))
    assert paper.base == 0 and 0.45 <= paper.gamma <= 0.55
    assert paper.k == pytest.approx(70_000, rel=0.1)  # §8.1.4: n(1 mm/h)·V_f; the fit spreads the curvature
    camera = CameraSpec(far_m=10.0)
    for p in (1.0, 3.0, 10.0, 30.0, 50.0):
        physical = theta_from_values(p, camera=camera, config=MappingConfig(n_max=10**7)).rain.expected_count
        assert paper.count(p) == pytest.approx(physical, rel=0.1)  # a power law through a curved log-log line: ±8 %
    custom = PaperMapping(base=100.0, k=2000.0, gamma=0.7, n_max=20_000)
    config = MappingConfig(mapping="paper", paper=custom)
    rain = theta_from_values(10.0, camera=camera, config=config).rain
    assert rain.mapping == "paper" and rain.count == round(100 + 2000 * 10**0.7)
    assert theta_from_values(1000.0, camera=camera, config=config).rain.count == 20_000
    # coverage is preserved: fewer Gaussians, each more opaque
    assert rain.count * rain.opacity_effective == pytest.approx(rain.expected_count * rain.opacity, rel=1e-3)


def test_subsampling_preserves_coverage():
    full = theta_from_values(20.0, camera=CameraSpec(far_m=10.0), config=MappingConfig(n_max=10**7)).rain
    capped = theta_from_values(20.0, camera=CameraSpec(far_m=10.0), config=MappingConfig(n_max=100_000)).rain
    assert capped.count == 100_000 and capped.coverage_preserved
    assert capped.count * capped.opacity_effective == pytest.approx(full.count * full.opacity, rel=1e-3)


def test_fog_from_visibility_and_rain_double_counting():
    fog = theta_from_values(0.0, 200.0).fog
    assert fog.active and fog.kind == "fog" and fog.beta_total_per_m == pytest.approx(physics.LN20 / 200)
    assert fog.beta_rgb_per_m[0] == fog.beta_rgb_per_m[2]  # dense fog is grey (Kim q = 0)
    wet = theta_from_values(10.0, 2000.0).fog  # visibility measured in rain already holds the rain's share
    assert wet.beta_fog_per_m == pytest.approx(wet.beta_total_per_m - wet.beta_rain_per_m)
    assert wet.beta_veil_per_m == pytest.approx(wet.beta_total_per_m)
    no_vis = theta_from_values(10.0).fog
    assert no_vis.visibility_source == "none" and not no_vis.active
    assert no_vis.beta_total_per_m == pytest.approx(no_vis.beta_rain_per_m + no_vis.beta_background_per_m)
    assert theta_from_values(0.0, None, fog_kind="mist").fog.visibility_m == 3000.0


def test_lens_drops_and_camera_checks():
    drops = theta_from_values(
        10.0, None, 5.0 / physics.wind_at_height_m_per_s(1.0), 0.0, camera=CameraSpec(facing_wind_cos=1.0)
    ).drops
    assert drops.arrival_rate_per_s == pytest.approx(894 * 5.0 * 9e-4, rel=0.02)  # §5: ≈ 4 drops/s
    assert theta_from_values(10.0).drops.count >= 0 and not theta_from_values(0.0).drops.active
    with pytest.raises(ConfigError, match="exposure_s"):
        theta_from_values(1.0, camera=CameraSpec(exposure_s=0.0))
    with pytest.raises(ConfigError, match="non-negative"):
        theta_from_values(-1.0)
    with pytest.raises(ConfigError, match="non-negative"):
        theta_from_values(float("nan"))
    cam = CameraSpec.from_intrinsics(fx=500.0, width=1000, height=500, exposure_s=0.004)
    assert cam.fov_x_deg == pytest.approx(90.0) and cam.exposure_s == 0.004
