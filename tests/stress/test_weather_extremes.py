"""Weather from 0 to 500 mm/h and visibility from 1 m to none: θ stays finite and bounded, and rendering it
(synthesis, the fog model and its gradients, the MeteGS weather branch) stays finite."""

import dataclasses
import itertools
import math

import numpy as np
import pytest
import torch

from metegs.data.config import DatasetConfig, SyntheticSceneConfig
from metegs.data.parsers.base import parse_scene
from metegs.meteo import CameraSpec, theta_from_values
from metegs.weather.conditions import ConditionsConfig, theta_for_cameras

RATES_MM_H = [0.0, 1e-9, 0.01, 0.1, 2.5, 10.0, 50.0, 100.0, 250.0, 500.0]
VISIBILITIES_M = [1.0, 2.0, 10.0, 50.0, 200.0, 1000.0, 5000.0, 1e5, None]


def _floats(obj, path="theta"):
    if dataclasses.is_dataclass(obj):
        for f in dataclasses.fields(obj):
            yield from _floats(getattr(obj, f.name), f"{path}.{f.name}")
    elif isinstance(obj, (list, tuple)):
        for i, v in enumerate(obj):
            yield from _floats(v, f"{path}[{i}]")
    elif isinstance(obj, (int, float)) and not isinstance(obj, bool):
        yield path, float(obj)


@pytest.mark.parametrize("wind", [0.0, 40.0])
def test_theta_is_finite_and_bounded_over_the_whole_range(wind):
    for rate, vis in itertools.product(RATES_MM_H, VISIBILITIES_M):
        th = theta_from_values(rate, vis, wind, 90.0 if wind else None, camera=CameraSpec())
        where = f"P={rate} mm/h, V={vis} m, wind={wind}"
        bad = [(p, v) for p, v in _floats(th) if not math.isfinite(v)]
        assert not bad, f"{where}: non-finite {bad}"
        r, f, d = th.rain, th.fog, th.drops
        assert 0 <= r.count <= r.n_max and r.count == int(r.count), where
        assert 0 <= r.opacity <= 1 and 0 <= r.opacity_effective <= 1, where
        assert 0 <= r.mean_coverage <= 1 and r.subsample_ratio >= 0, where
        assert 0 < r.near_m <= r.far_m or not r.active, where
        assert r.streak_length_m >= 0 and r.sigma_parallel_m >= 0 and r.sigma_perp_m >= 0, where
        assert r.beta_rain_per_m >= 0 and r.tilt_deg >= 0 and r.tilt_deg <= 90, where
        assert f.beta_total_per_m >= 0 and f.beta_fog_per_m >= 0 and f.beta_veil_per_m >= 0, where
        assert all(b >= 0 for b in f.beta_rgb_per_m), where
        assert 0 <= f.lattice_opacity <= 1, where
        assert d.count >= 0 and d.arrival_rate_per_s >= 0, where
        if vis is not None and vis < 1000:  # the measured visibility is honoured: by the fog, or by the rain's veil
            assert f.beta_veil_per_m >= 0.99 * math.log(1 / f.contrast_threshold) / vis, where
        if rate == 0:
            assert not r.active and r.count == 0, where


def test_theta_from_a_scene_camera_at_the_extremes():
    scene = parse_scene(None, None, DatasetConfig(synthetic=SyntheticSceneConfig(width=32, height=24, num_views=2)))
    for rate, vis in [(0.0, 1.0), (500.0, None), (500.0, 1.0), (1e-9, 1e5)]:
        th = theta_for_cameras(ConditionsConfig(precip_mm_h=rate, visibility_m=vis), scene.cameras, 10.0)
        assert all(math.isfinite(v) for _, v in _floats(th)), (rate, vis)


@pytest.fixture(scope="module")
def tiny_scene():
    return parse_scene(
        None, None, DatasetConfig(synthetic=SyntheticSceneConfig(width=32, height=24, num_views=2, num_points=200))
    )


@pytest.mark.parametrize(
    "rate,vis,kinds",
    [
        (0.0, 1.0, "fog"),
        (500.0, None, "rain"),
        (500.0, 1.0, "rain+fog"),
        (500.0, 10.0, "rain+fog+drops"),
        (0.1, None, "rain+fog"),
        (50.0, 1e5, "rain+fog"),
    ],
)
def test_synthesised_weather_stays_finite_and_in_range(tiny_scene, rate, vis, kinds):
    from metegs.weather.degrade import degrade_scene

    th = theta_for_cameras(ConditionsConfig(precip_mm_h=rate, visibility_m=vis), tiny_scene.cameras, 10.0)
    degraded, records = degrade_scene(tiny_scene, th, kinds=kinds, seed=0, metres_per_unit=10.0)
    for img in degraded.images:
        assert np.isfinite(img).all() and img.min() >= 0 and img.max() <= 1
    for rec in records:
        assert math.isfinite(rec["rain_coverage"]) and 0 <= rec["rain_coverage"] <= 1
    if vis == 1.0:  # 1 m visibility: everything beyond a few metres is airlight
        spread = degraded.images[0].reshape(-1, 3).std(axis=0).max()
        assert spread < tiny_scene.images[0].reshape(-1, 3).std(axis=0).max() * 0.1


def test_fog_model_gradients_stay_finite_for_extreme_extinction(tiny_scene):
    """The learnable fog at β from 1 m visibility (3/m: transmittance e^-600 over 200 m) and at none."""
    from metegs.render.base import RenderOutput, RenderSettings
    from metegs.weather.base import WeatherScene
    from metegs.weather.fog_analytic import FogAnalyticConfig

    cams = tiny_scene.cameras
    for vis in (1.0, None):
        th = theta_for_cameras(ConditionsConfig(precip_mm_h=0.0, visibility_m=vis), cams, 10.0)
        scene = WeatherScene(cameras=cams, up=torch.tensor([0.0, 0.0, 1.0]), metres_per_unit=10.0, images=None, seed=0)
        fog = FogAnalyticConfig(airlight=(0.8, 0.8, 0.8)).setup(theta=th, scene=scene)
        if not fog.active:
            continue
        H, W = 24, 32
        rgb = torch.rand(H, W, 3, requires_grad=True)
        depth = torch.full((H, W), 20.0)
        depth[0, 0] = 0.0
        depth[0, 1] = 1e9
        out = RenderOutput(rgb, torch.ones(H, W), depth, torch.zeros(0), torch.zeros(0, 2), 0, W, H)
        image = fog.apply(rgb, out, 0, RenderSettings())
        assert torch.isfinite(image).all()
        params = [p for p in fog.parameters() if p.requires_grad]
        image.sum().backward()
        assert torch.isfinite(rgb.grad).all()
        assert all(p.grad is None or torch.isfinite(p.grad).all() for p in params)


@pytest.mark.parametrize("rate,vis", [(500.0, 1.0), (0.0, 1.0)])
def test_metegs_weather_branch_trains_finite_at_the_extremes(tmp_path, rate, vis):
    from metegs.config import apply_overrides
    from metegs.registry import registry

    config = apply_overrides(
        registry("method").get("metegs-full")(),
        {
            "max_steps": 4,
            "eval_every": 0,
            "checkpoint_every": 0,
            "save_renders": False,
            "progress": False,
            "compare_baseline": False,
            "degrade": "rain+fog",
            "conditions": {"precip_mm_h": rate, "visibility_m": vis},
            "weights": {"perceptual": 0.0},
            "rain_streaks": {"max_count": 500},
            "dataset": {"test_every": 2, "synthetic": {"width": 32, "height": 24, "num_views": 4, "num_points": 300}},
        },
    )
    trainer = config.setup(run_dir=tmp_path / "run")
    metrics = trainer.train()
    assert math.isfinite(metrics["psnr"]) and math.isfinite(metrics["ssim"])
    assert all(torch.isfinite(p).all() for p in trainer.model.params.values())
    for m in trainer.weather_models:
        assert all(torch.isfinite(p).all() for p in m.parameters())
