"""benchmarks/fog_inversion.py: along the depth the fog was drawn over, its inversion gives the clean photos back;
along another depth it does not."""

from __future__ import annotations

import dataclasses
import json
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from metegs.data.config import DatasetConfig, SyntheticSceneConfig
from metegs.data.parsers.base import parse_scene
from metegs.weather.conditions import ConditionsConfig, theta_for_cameras
from metegs.weather.degrade import degrade_scene

MPU = 10.0


def _run(scene, photos, clean, depth_scale: float, data):
    """A stand-in for a loaded run: it renders the clean images along the scene's depth times ``depth_scale``."""
    views = range(len(scene.names))
    dataset = SimpleNamespace(
        names=list(scene.names),
        images=[torch.as_tensor(photos[i]) for i in views],
        clean_images=[torch.as_tensor(clean[i]) for i in views],
        cameras=scene.cameras,
        train_indices=list(views),
    )

    def render(i):
        depth = torch.as_tensor(scene.depths[i]) * depth_scale
        return SimpleNamespace(depth=depth, alpha=torch.ones_like(depth), rgb=dataset.clean_images[i])

    return SimpleNamespace(
        dataset=dataset,
        render=render,
        background=lambda training: None,
        config=SimpleNamespace(data=data),
        run_dir=data,
    )


@pytest.fixture(scope="module")
def fogged(tmp_path_factory):
    scene = parse_scene(
        None, None, DatasetConfig(synthetic=SyntheticSceneConfig(width=48, height=36, num_views=3, num_points=200))
    )
    # the dome lies past where 200 m fog lets any of its light through: hold every depth to 100 m
    scene = dataclasses.replace(scene, depths=[np.minimum(d, 100.0 / MPU) for d in scene.depths])
    theta = theta_for_cameras(ConditionsConfig(precip_mm_h=0.0, visibility_m=200.0), scene.cameras, MPU)
    degraded, records = degrade_scene(scene, theta, kinds="fog", metres_per_unit=MPU, family="physical")
    data = tmp_path_factory.mktemp("fog")
    (data / "weather.json").write_text(json.dumps({"family": "physical", "metres_per_unit": MPU, "views": records}))
    return scene, degraded.images, scene.images, data


def test_the_depth_the_fog_was_drawn_along_inverts_it(benchmark_script, fogged):
    inversion = benchmark_script("fog_inversion")
    scene, photos, clean, data = fogged
    exact = _run(scene, photos, clean, 1.0, data)
    scores = inversion.score_run(exact, exact, every=1)
    assert scores["inverted along its depth"] > 40.0
    assert scores["clean render"] > 60.0  # the stand-in renders the clean images themselves
    nearer = inversion.score_run(_run(scene, photos, clean, 0.8, data), exact, every=1)
    assert nearer["inverted along its depth"] < scores["inverted along its depth"] - 10.0


def test_it_needs_metegs_own_fog(benchmark_script, fogged, tmp_path):
    inversion = benchmark_script("fog_inversion")
    (tmp_path / "weather.json").write_text(json.dumps({"family": "independent", "metres_per_unit": MPU, "views": []}))
    with pytest.raises(SystemExit, match="family 'independent'"):
        inversion.exact_media(tmp_path)
