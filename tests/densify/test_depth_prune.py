"""Depth-aware pruning: camera-depth thresholds, the world-z reference formula, and its use inside ADC."""

from __future__ import annotations

import math
import time

import pytest
import torch

from metegs.cameras import Cameras
from metegs.densify.adc import AdaptiveDensityControl, ADCConfig
from metegs.densify.depth_prune import DepthAwarePruning, DepthPruneConfig, median_camera_depth
from metegs.engine.optim import OptimConfig, make_optimizers
from metegs.errors import ConfigError
from metegs.gaussians.model import GaussianModel, inverse_sigmoid


def cameras_at(eyes, forward=(0.0, 0.0, 1.0), f=100.0, size=200) -> Cameras:
    """Cameras at ``eyes`` all looking along ``forward`` (OpenCV axes: z forward, y down)."""
    fwd = torch.tensor(forward, dtype=torch.float32)
    fwd = fwd / fwd.norm()
    down_hint = torch.tensor([0.0, 1.0, 0.0]) if abs(float(fwd[1])) < 0.9 else torch.tensor([0.0, 0.0, -1.0])
    right = torch.linalg.cross(down_hint, fwd)
    right = right / right.norm()
    down = torch.linalg.cross(fwd, right)
    c2w = torch.eye(4).repeat(len(eyes), 1, 1)
    c2w[:, :3, 0], c2w[:, :3, 1], c2w[:, :3, 2] = right, down, fwd
    c2w[:, :3, 3] = torch.tensor(eyes, dtype=torch.float32)
    cams = Cameras.create(c2w, f, f, size / 2, size / 2, size, size)
    cams.validate()
    return cams


def model_at(means, opacities=None) -> GaussianModel:
    means = torch.as_tensor(means, dtype=torch.float32)
    params = GaussianModel.empty_params(means.shape[0], sh_degree=0)
    params["means"] = means
    params["scales"] = torch.full((means.shape[0], 3), math.log(1e-3))
    if opacities is not None:
        params["opacities"] = inverse_sigmoid(torch.as_tensor(opacities, dtype=torch.float32))
    return GaussianModel(params, sh_degree=0)


def test_camera_depth_is_the_median_over_the_cameras_that_see_the_point():
    # Cameras on the z axis looking along +z; the point at z = 2 is 2, 3 and 10 in front of them.
    cams = cameras_at([(0, 0, 0), (0, 0, -1), (0, 0, -8)])
    pts = torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, -20.0], [50.0, 0.0, 2.0]])
    d = median_camera_depth(pts, cams)
    assert d[0] == pytest.approx(3.0)
    assert torch.isnan(d[1])  # behind every camera
    # (50, 0, 2) projects inside only the farthest camera's image: 100·50/10 + 100 = 600 > 200 for the others
    assert torch.isnan(d[2])
    cams = cameras_at([(0, 0, 0), (0, 0, -1), (0, 0, -300)])
    assert median_camera_depth(pts, cams)[2] == pytest.approx(302.0)  # only the far camera sees it


def test_near_gaussians_get_the_base_threshold_and_far_ones_base_over_wp():
    cams = cameras_at([(x, 0.0, 0.0) for x in (-0.2, 0.0, 0.2)])
    z = torch.linspace(1.0, 10.0, 200)
    model = model_at(torch.stack([torch.zeros_like(z), torch.zeros_like(z), z], 1))
    rule = DepthPruneConfig(weight=3.0).setup(cameras=cams)
    thr = rule.thresholds(model, 0.005)
    assert thr[0] == pytest.approx(0.005) and thr[-1] == pytest.approx(0.005 / 3)
    assert torch.all(thr[1:] <= thr[:-1] + 1e-9)  # farther -> lower threshold
    assert rule(model, 0.01)[-1] == pytest.approx(0.01 / 3)  # callable as the ADC prune_rule
    assert rule.last_stats["seen"] == 200


def test_camera_depth_follows_the_view_not_world_z():
    # Cameras look along world +x: depth grows with x while every Gaussian has the same world z.
    cams = cameras_at([(0.0, y, 0.0) for y in (-0.1, 0.0, 0.1)], forward=(1.0, 0.0, 0.0))
    x = torch.linspace(1.0, 10.0, 100)
    model = model_at(torch.stack([x, torch.zeros_like(x), torch.zeros_like(x)], 1))
    thr = DepthAwarePruning(DepthPruneConfig(), cams).thresholds(model, 0.005)
    assert thr[0] == pytest.approx(0.005) and thr[-1] == pytest.approx(0.005 / 3)
    flat = DepthAwarePruning(DepthPruneConfig(depth_mode="world_z"), cams).thresholds(model, 0.005)
    assert torch.allclose(flat, torch.full_like(flat, 0.005))  # equal z: no depth information


def test_world_z_mode_matches_the_reference_formula():
    g = torch.Generator().manual_seed(0)
    means = torch.randn(500, 3, generator=g) * 3
    model = model_at(means)
    w, base = 2.5, 0.01
    thr = DepthAwarePruning(DepthPruneConfig(depth_mode="world_z", weight=w), cameras_at([(0, 0, -10)])).thresholds(
        model, base
    )
    z = means[:, 2]
    d_hat = (z - z.min()) / (z.max() - z.min()) * (w - 1) + 1
    assert torch.allclose(thr, base / d_hat, rtol=1e-6)


def test_gaussians_seen_by_no_camera_get_the_base_threshold():
    cams = cameras_at([(0, 0, 0), (0.1, 0, 0)])
    z = torch.linspace(1.0, 10.0, 50)
    means = torch.cat(
        [
            torch.stack([torch.zeros_like(z), torch.zeros_like(z), z], 1),
            torch.tensor([[0.0, 0.0, -5.0], [1e4, 0.0, 5.0]]),
        ]
    )  # behind; outside every image
    rule = DepthAwarePruning(DepthPruneConfig(), cams)
    thr = rule.thresholds(model_at(means), 0.005)
    assert thr[-2:].tolist() == pytest.approx([0.005, 0.005])
    assert rule.last_stats["seen"] == 50 and thr[49] == pytest.approx(0.005 / 3)
    nobody = DepthAwarePruning(DepthPruneConfig(), cameras_at([(0, 0, 100)])).thresholds(model_at(means), 0.005)
    assert torch.allclose(nobody, torch.full_like(nobody, 0.005))


def test_bad_config():
    with pytest.raises(ConfigError, match="weight"):
        DepthAwarePruning(DepthPruneConfig(weight=0.5), cameras_at([(0, 0, 0)]))


def test_adc_with_the_depth_rule_keeps_far_faint_gaussians_that_plain_adc_prunes():
    cams = cameras_at([(x, 0.0, 0.0) for x in (-0.2, 0.0, 0.2)])
    z = torch.linspace(1.0, 10.0, 40)
    means = torch.stack([torch.zeros_like(z), torch.zeros_like(z), z], 1)
    opac = torch.full((40,), 0.5)
    opac[0] = opac[-1] = 0.003  # between t_p / w_p = 0.00167 and t_p = 0.005
    opac[-2] = 0.001  # below even the far threshold

    def run(rule):
        model = model_at(means, opac)
        opts = make_optimizers(model.params, OptimConfig(), extent=1.0)
        adc = AdaptiveDensityControl(ADCConfig(prune_opacity=0.005), max_steps=3000, extent=1.0, prune_rule=rule)
        report = adc.refine(model, opts, step=100)
        return model.params["means"][:, 2].detach(), report

    kept_plain, report = run(None)
    assert report == {"clone": 0, "split": 0, "prune": 3}
    assert float(z[0]) not in kept_plain.tolist() and float(z[-1]) not in kept_plain.tolist()
    kept_depth, report = run(DepthAwarePruning(DepthPruneConfig(), cams))
    assert report == {"clone": 0, "split": 0, "prune": 2, "prune_depth": 2}
    assert float(z[-1]) in kept_depth.tolist()  # far and faint: kept by the depth rule only
    assert float(z[0]) not in kept_depth.tolist() and float(z[-2]) not in kept_depth.tolist()  # near: pruned


def test_fast_for_100k_gaussians_and_50_cameras():
    eyes = [(5 * math.cos(a), 5 * math.sin(a), 1.0) for a in torch.linspace(0, 2 * math.pi, 51)[:50].tolist()]
    c2w = []
    for eye in eyes:  # ring of cameras looking at the origin
        cam = cameras_at([eye], forward=tuple(-torch.tensor(eye) / torch.tensor(eye).norm()))
        c2w.append(cam.camera_to_worlds[0])
    cams = Cameras.create(torch.stack(c2w), 200.0, 200.0, 160.0, 120.0, 320, 240)
    model = model_at(torch.randn(100_000, 3, generator=torch.Generator().manual_seed(0)))
    rule = DepthAwarePruning(DepthPruneConfig(), cams)
    start = time.perf_counter()
    thr = rule.thresholds(model, 0.005)
    elapsed = time.perf_counter() - start
    assert thr.shape == (100_000,) and torch.isfinite(thr).all()
    assert rule.last_stats["seen"] > 99_000
    assert elapsed < 5.0, f"{elapsed:.2f} s"  # about 0.7 s on 2 shared cores
