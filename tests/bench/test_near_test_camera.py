"""benchmarks/near_test_camera.py: a Gaussian put right in front of a test camera is found, and hiding it gives the
view back what it cost."""

from __future__ import annotations

import pytest
import torch

from metegs.data.config import DatasetConfig, SyntheticSceneConfig
from metegs.densify.adc import ADCConfig
from metegs.engine.config import TrainConfig
from metegs.engine.run import load_run
from metegs.gaussians.sh import rgb_to_sh

TINY = DatasetConfig(synthetic=SyntheticSceneConfig(width=48, height=36, num_views=9, num_points=600))


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    config = TrainConfig(
        max_steps=60,
        output_dir=tmp_path_factory.mktemp("run"),
        experiment_name="run",
        backend="auto",
        device="cpu",
        progress=False,
        dataset=TINY,
        checkpoint_every=60,
        eval_every=0.0,
        densify=ADCConfig(reset_every=0.0, max_gaussians=1500, prune_opacity=0.005),
    )
    trainer = config.setup()
    trainer.train()
    return trainer.run_dir


def _block_view(trainer, view: int) -> None:
    """Move one Gaussian to a tenth of test view ``view``'s median depth on its axis: large, opaque, and of the
    colour furthest from the view's mean."""
    index = list(trainer.dataset.test_indices)[view]
    camera = trainer.dataset.cameras[[index]]
    params = trainer.model.params
    depth = float(camera.project(params["means"].detach())[0, :, 2].median())
    c2w = camera.camera_to_worlds[0]
    colour = (trainer.dataset.images[index].reshape(-1, 3).mean(0) < 0.5).float()
    with torch.no_grad():
        params["means"][0] = c2w[:3, 3] + 0.1 * depth * c2w[:3, 2]  # OpenCV axes: z looks forward
        params["scales"][0] = torch.log(torch.tensor(0.2 * depth))
        params["opacities"][0] = 6.0
        params["sh0"][0, 0] = rgb_to_sh(colour)
        params["shN"][0] = 0.0


def test_a_gaussian_in_front_of_the_camera_is_found_and_costs_the_view(benchmark_script, run_dir):
    near = benchmark_script("near_test_camera")
    clean = near.near_camera(load_run(run_dir), view=0, fraction=0.25)
    trainer = load_run(run_dir)
    _block_view(trainer, 0)
    blocked = near.near_camera(trainer, view=0, fraction=0.25)
    assert blocked["near_large"] >= clean["near_large"] + 1
    assert blocked["psnr"][0] < clean["psnr"][0] - 3.0  # the view looks into the Gaussian
    assert blocked["psnr_without_near"][0] > blocked["psnr"][0] + 3.0  # hidden, the view comes back
    assert blocked["psnr"][1:] == pytest.approx(clean["psnr"][1:], abs=0.5)  # other test views hardly see it
    assert blocked["camera_spacings_from_training"] == pytest.approx(clean["camera_spacings_from_training"])
