"""benchmarks/other_generator.py: its fog is Koschmieder's in closed form, its streaks only blend towards their
radiance, and the independent family is itself again after the block."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from metegs.data.config import DatasetConfig, SyntheticSceneConfig
from metegs.data.parsers.base import parse_scene
from metegs.weather.conditions import ConditionsConfig, theta_for_cameras
from metegs.weather.degrade import degrade_scene
from metegs.weather.independent import IndependentEngine, pixel_rays

MPU = 10.0


@pytest.fixture(scope="module")
def scene():
    return parse_scene(
        None, None, DatasetConfig(synthetic=SyntheticSceneConfig(width=48, height=36, num_views=3, num_points=200))
    )


def _degrade(generator, scene, variant, kinds, precip, visibility):
    theta = theta_for_cameras(ConditionsConfig(precip_mm_h=precip, visibility_m=visibility), scene.cameras, MPU)
    with generator.drawing(variant):
        degraded, records = degrade_scene(scene, theta, kinds=kinds, metres_per_unit=MPU, family="independent")
    return degraded, records


def test_its_fog_is_koschmieder_under_its_airlight(benchmark_script, scene):
    g = benchmark_script("other_generator")
    variant = dataclasses.replace(g.VARIANTS["smog"], streak_radiance=None)
    original = IndependentEngine.view
    degraded, records = _degrade(g, scene, variant, "fog", 0.0, 300.0)
    assert IndependentEngine.view is original and records[0]["kinds"] == "fog"
    for i in range(len(scene)):
        depth = np.asarray(scene.depths[i], np.float64)
        _, _, per_depth = pixel_rays(scene.cameras[i], *depth.shape)
        t = np.exp(-3.912 / 300.0 * np.minimum(depth * per_depth * MPU, 1500.0))[..., None]
        expected = degraded.clean_images[i] * t + np.asarray(variant.airlight) * (1 - t)
        assert np.allclose(degraded.images[i], np.clip(expected, 0, 1), atol=1e-5)


def test_its_streaks_only_blend_towards_their_radiance(benchmark_script, scene):
    g = benchmark_script("other_generator")
    variant = g.VARIANTS["rain"]
    degraded, records = _degrade(g, scene, variant, "rain", 22.0, None)
    assert records[0]["kinds"] == "rain"
    for clean, rainy in zip(degraded.clean_images, degraded.images, strict=True):
        changed = np.abs(rainy - clean).max(-1) > 1e-6
        assert 0.02 < changed.mean() < 0.9  # streaks over part of the view
        share = (rainy - clean) / np.where(
            np.abs(variant.streak_radiance - clean) > 1e-3, variant.streak_radiance - clean, np.inf
        )
        assert (share[changed] >= -1e-4).all() and (share[changed] <= variant.alpha[1] + 1e-4).all()
