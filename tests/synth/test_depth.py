"""Depth for synthesis from a trained run, and the metric-scale guess."""

import json

import numpy as np
import pytest
import torch
from rich.console import Console

from metegs.data.config import DatasetConfig, SyntheticSceneConfig
from metegs.data.parsers.base import parse_scene
from metegs.densify.adc import ADCConfig
from metegs.engine.config import TrainConfig
from metegs.engine.run import depths_from_run, load_run
from metegs.errors import DataError
from metegs.synth.depth import guess_metres_per_unit
from metegs.synth.pipeline import SynthConfig, synthesise

TINY = DatasetConfig(synthetic=SyntheticSceneConfig(width=48, height=36, num_views=5, num_points=600))


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("run")
    config = TrainConfig(
        max_steps=25,
        output_dir=tmp,
        experiment_name="run",
        backend="auto",
        device="cpu",
        progress=False,
        dataset=TINY,
        checkpoint_every=25,
        eval_every=0.0,
        # INRIA's prune threshold: a 25-step run refines from step 0, when 3dgs's 0.1 would cut the Gaussians
        # still at their initial opacity (0.1) and leave the views a quarter uncovered
        densify=ADCConfig(reset_every=0.0, max_gaussians=1500, prune_opacity=0.005),
    )
    trainer = config.setup()
    trainer.train()
    return trainer.run_dir


def test_depth_rendered_from_a_run_matches_the_scene(run_dir):
    scene = parse_scene(None, None, TINY)
    depths, note = depths_from_run(run_dir, scene)
    assert "3dgs" in note and len(depths) == len(scene)
    trainer = load_run(run_dir)
    for i, (rendered, exact) in enumerate(zip(depths, scene.depths)):
        assert rendered.shape == exact.shape and rendered.dtype == np.float32
        known = np.isfinite(rendered)
        assert known.mean() > 0.8
        with torch.no_grad():
            out = trainer.render(i, background=torch.zeros(3))  # what the run itself renders for this view
        np.testing.assert_allclose(rendered[known], out.depth.numpy()[known], rtol=1e-5)
        assert np.array_equal(known, out.alpha.numpy() >= 0.5)
        assert np.median(np.abs(rendered[known] - exact[known]) / exact[known]) < 0.5  # a 25-step run: roughly
    other = parse_scene(None, None, DatasetConfig(synthetic=SyntheticSceneConfig(width=48, height=36, num_views=6)))
    with pytest.raises(DataError, match="trained on other cameras"):
        depths_from_run(run_dir, other)


def test_cli_depth_from_a_run_uses_its_dataset(run_dir, tmp_path):
    out = synthesise(
        SynthConfig(output=tmp_path / "o", depth_from=run_dir, precip_mm_h=20.0, rain_far_m=4.0, exposure_s=1 / 30),
        Console(file=open("/dev/null", "w")),
    )
    weather = json.loads((out / "weather.json").read_text())
    assert weather["depth"].startswith("rendered from run") and len(weather["views"]) == 5
    assert weather["metres_per_unit"] == parse_scene(None, None, TINY).metric_scale


def test_guess_metres_per_unit():
    depths = [np.array([[1.0, 2.0], [np.nan, 3.0]], np.float32), np.array([[0.0, 2.0]], np.float32)]
    assert guess_metres_per_unit(depths, 4.0) == pytest.approx(2.0)  # median of 1, 2, 3, 2 is 2 units = 4 m
    with pytest.raises(DataError, match="metres-per-unit"):
        guess_metres_per_unit([np.full((2, 2), np.nan, np.float32)])
