"""degrade_scene on the synthetic scene: monotone in rain rate and visibility, consistent fog, per-view rain."""

import dataclasses

import numpy as np
import pytest
import torch

from metegs.data.config import SyntheticSceneConfig
from metegs.data.parsers.synthetic import build_scene
from metegs.errors import ConfigError, DataError
from metegs.meteo import theta_from_values
from metegs.weather.conditions import camera_spec
from metegs.weather.degrade import UNKNOWN_DEPTH, degrade_scene, fill_unknown_depth, iter_degraded_views
from metegs.weather.fog_analytic import fog_composite, ray_lengths

# one P per WMO class: drizzle, light, moderate, heavy, violent rain
CLASSES = [(0.3, "drizzle"), (1.5, "rain"), (6.0, "rain"), (20.0, "rain"), (70.0, "rain")]


@pytest.fixture(scope="module")
def scene():
    return build_scene(SyntheticSceneConfig(width=96, height=72, num_views=3, num_points=50))


@pytest.fixture(scope="module")
def camera(scene):
    # 1/30 s and a fixed 4 m far limit: at 96x72 px the contrast rule would leave almost no visible streak
    return camera_spec(scene.cameras, exposure_s=1 / 30, capture_width_px=0, far_m=4.0)


def psnr(a, b) -> float:
    mse = float(np.mean((np.stack(a) - np.stack(b)) ** 2))
    return float("inf") if mse == 0 else -10 * np.log10(mse)


def luminance_contrast(images) -> float:
    """Mean over views of the RMS contrast (std of luminance)."""
    return float(np.mean([(im @ np.array([0.2126, 0.7152, 0.0722], np.float32)).std() for im in images]))


def test_more_rain_more_coverage_and_lower_psnr_across_wmo_classes(scene, camera):
    coverage, quality, classes = [], [], []
    for p, kind in CLASSES:
        theta = theta_from_values(p, kind=kind, camera=camera)
        classes.append(theta.rain.intensity_class if kind == "rain" else "drizzle")
        rainy, records = degrade_scene(scene, theta, kinds="rain", seed=0)
        assert all(r["num_rain_gaussians"] > 0 for r in records)
        coverage.append(np.mean([r["rain_coverage"] for r in records]))
        quality.append(psnr(rainy.images, scene.images))
    assert classes == ["drizzle", "light", "moderate", "heavy", "violent"]
    assert all(b > 1.3 * a for a, b in zip(coverage, coverage[1:])), coverage
    assert all(b < a - 0.5 for a, b in zip(quality, quality[1:])), quality


def test_lower_visibility_lower_contrast(scene, camera):
    contrasts = [luminance_contrast(scene.images)]
    for visibility in (5000.0, 1000.0, 300.0, 100.0):
        theta = theta_from_values(0.0, visibility_m=visibility, fog_kind="fog", camera=camera)
        foggy, records = degrade_scene(scene, theta, kinds="fog")
        assert all(r["fog"] and r["num_rain_gaussians"] == 0 for r in records)
        contrasts.append(luminance_contrast(foggy.images))
    assert all(b < a for a, b in zip(contrasts, contrasts[1:])), contrasts


def test_zero_rain_and_infinite_visibility_give_exactly_the_clean_images(scene, camera):
    theta = theta_from_values(0.0, visibility_m=None, camera=camera)
    clear, records = degrade_scene(scene, theta, kinds="rain+fog+drops", seed=5)
    for im, clean in zip(clear.images, scene.images):
        assert im.dtype == np.float32 and np.array_equal(im, clean)
    assert all(r["num_rain_gaussians"] == 0 and not r["fog"] for r in records)
    # no lens drops either when they were not asked for, whatever θ_drops says
    theta = theta_from_values(0.0, camera=camera)
    assert all(np.array_equal(a, b) for a, b in zip(degrade_scene(scene, theta)[0].images, scene.images))


def _fog_beta(foggy, clean, distance_m, airlight, keep) -> float:
    """β implied by one view's fog: median of −ln(t)/d over ``keep`` pixels far enough from the airlight."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (foggy - airlight) / (clean - airlight)
    ok = (np.abs(clean - airlight) > 0.15) & (distance_m[..., None] > 20) & (t > 0.05) & (t < 0.95) & keep[..., None]
    return float(np.median(-np.log(t[ok]) / np.broadcast_to(distance_m[..., None], t.shape)[ok]))


def test_two_nearby_views_share_the_fog_but_not_the_rain(scene, camera):
    theta = theta_from_values(30.0, visibility_m=300.0, fog_kind="fog", camera=camera)
    rainy, records = degrade_scene(scene, theta, kinds="rain+fog", seed=1)
    streaks, veiled = degrade_scene(scene, theta, kinds="rain", seed=1)  # the same streaks in the rain's veil alone
    fog = records[0]["fog-analytic"]  # the medium's summary, as in metrics.json (β to 1e-6 /m, airlight to 1e-4)
    airlight = np.array(fog["airlight"], np.float32)
    beta = float(np.mean(fog["beta_per_m"]))
    assert records[1]["fog-analytic"] == fog
    expected = float(np.mean(theta.fog.beta_rgb_per_m)) + theta.fog.beta_rain_per_m  # + rain veil
    assert beta == pytest.approx(expected, abs=1e-6)
    masks, betas = [], []
    for v in (0, 1):
        rays = ray_lengths(scene.cameras[v], *scene.depths[v].shape).numpy()
        distance = scene.depths[v] * rays * scene.metric_scale
        veil = fog_composite(
            torch.from_numpy(scene.images[v]), torch.ones(distance.shape), torch.from_numpy(distance),
            torch.tensor(veiled[v]["fog-analytic"]["beta_per_m"]), torch.tensor(veiled[v]["fog-analytic"]["airlight"]),
        ).numpy()  # fmt: skip
        rain = np.abs(streaks.images[v] - veil).max(-1) > 1 / 255
        assert 0.001 < rain.mean() < 0.5
        masks.append(rain)
        betas.append(_fog_beta(rainy.images[v], scene.images[v], distance, airlight, ~rain))
    # one medium: the images of both views show the same extinction, the one recorded
    assert betas[0] == pytest.approx(beta, rel=0.01) and betas[1] == pytest.approx(beta, rel=0.01)
    iou = (masks[0] & masks[1]).sum() / (masks[0] | masks[1]).sum()
    assert iou < 0.2, iou  # independent rain in each photo
    assert records[0]["theta"] == records[1]["theta"]


def test_rain_is_reproducible_per_view_and_changes_with_the_seed(scene, camera):
    theta = theta_from_values(20.0, camera=camera)
    a, _ = degrade_scene(scene, theta, kinds="rain", seed=3)
    b, _ = degrade_scene(scene, theta, kinds="rain", seed=3)
    c, _ = degrade_scene(scene, theta, kinds="rain", seed=4)
    assert all(np.array_equal(x, y) for x, y in zip(a.images, b.images))
    assert not any(np.array_equal(x, y) for x, y in zip(a.images, c.images))
    (alone,) = iter_degraded_views(scene, theta, kinds="rain", seed=3, views=[2])
    assert np.array_equal(alone.image, a.images[2])  # a view's rain does not depend on the others


def test_returned_scene_and_records(scene, camera):
    thetas = [theta_from_values(p, camera=camera) for p in (2.0, 2.0, 40.0)]
    out, records = degrade_scene(scene, thetas, kinds="rain", seed=0, metres_per_unit=scene.metric_scale)
    assert out is not scene and len(out.images) == len(scene) and out.clean_images is not None
    assert all(np.array_equal(c, im) for c, im in zip(out.clean_images, scene.images))
    assert out.cameras is scene.cameras and out.depths is scene.depths
    assert [r["view"] for r in records] == [0, 1, 2] and records[0]["seed"] == 0
    assert records[2]["theta"]["rain"]["precip_mm_per_h"] == 40.0
    assert records[2]["rain_coverage"] > records[0]["rain_coverage"]


def test_errors(scene, camera):
    theta = theta_from_values(5.0, camera=camera)
    with pytest.raises(DataError, match="no depth maps"):
        degrade_scene(dataclasses.replace(scene, depths=None), theta)
    with pytest.raises(ConfigError, match="one per view"):
        degrade_scene(scene, [theta, theta])
    with pytest.raises(ConfigError, match="kinds='snow'"):
        degrade_scene(scene, theta, kinds="snow")
    with pytest.raises(ConfigError, match="metres_per_unit"):
        degrade_scene(scene, theta, metres_per_unit=-1.0)


def test_unknown_depth_takes_the_nearest_known_depth():
    d = np.array([[1, np.nan, np.nan, 4], [np.nan] * 4, [7, 0, -1, 9]], np.float32)
    np.testing.assert_array_equal(fill_unknown_depth(d), [[1, 1, 4, 4], [1, 1, 4, 4], [7, 7, 9, 9]])
    assert (fill_unknown_depth(np.full((2, 2), np.nan, np.float32)) == UNKNOWN_DEPTH).all()


def test_holes_in_a_rendered_depth_do_not_turn_into_airlight(scene, camera):
    theta = theta_from_values(0.0, visibility_m=1000.0, fog_kind="fog", camera=camera)
    holes = [d.copy() for d in scene.depths]
    holes[0][:10, :10] = np.nan  # e.g. where a trained run renders nothing
    exact, _ = degrade_scene(scene, theta, kinds="fog")
    holed, _ = degrade_scene(scene, theta, kinds="fog", depths=holes)
    assert np.abs(holed.images[0] - exact.images[0]).max() < 0.05
