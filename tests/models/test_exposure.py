"""Per-view exposure: the affines' gauge, what they do to a render, and a run on photos of varying exposure."""

from dataclasses import replace

import pytest
import torch

from metegs.engine.optim import OptimConfig
from metegs.models.exposure import ViewExposure


def test_gains_average_to_one_offsets_to_zero_and_map_colours_as_written():
    exposure = ViewExposure([0, 2, 3], num_views=5)
    with torch.no_grad():
        exposure.offsets.copy_(torch.randn(3, 2, 3, generator=torch.Generator().manual_seed(0)) * 0.2)
    gains, offsets = exposure.gains_and_offsets()
    assert torch.allclose(gains.mean(dim=0), torch.ones(3), atol=1e-6)
    assert torch.allclose(offsets.mean(dim=0), torch.zeros(3), atol=1e-6)
    rgb = torch.rand(4, 6, 3)
    assert torch.allclose(exposure(rgb, 2), rgb * gains[1] + offsets[1], atol=1e-6)  # view 2 is training row 1
    assert exposure(rgb, 1) is rgb and exposure(rgb, 4) is rgb  # views outside training: as rendered


def test_a_fresh_exposure_is_the_identity_and_gradients_reach_its_offsets():
    exposure = ViewExposure([0, 1], num_views=2)
    rgb = torch.rand(3, 3, 3)
    assert torch.equal(exposure(rgb, 0), rgb)
    exposure(rgb, 0).sum().backward()
    assert exposure.offsets.grad is not None and exposure.offsets.grad.abs().sum() > 0


@pytest.fixture(scope="module")
def exposure_runs(tmp_path_factory):
    """3dgs with and without per-view exposure on the tiny synthetic scene whose training photos were each
    brightened or darkened (gains 0.6-1.4 per channel); test photos as they were."""
    from tests.engine.test_trainer import tiny_config

    results = {}
    for name, choice in (("with", "on"), ("without", "auto")):  # auto: off on the rendered built-in scene
        cfg = tiny_config(tmp_path_factory.mktemp(name), save_renders=False)
        optim = OptimConfig(exposure_lr=3e-2)  # 150 steps: faster than a real run's 1e-3
        trainer = replace(cfg, max_steps=150, eval_every=0.0, view_exposure=choice, optim=optim).setup()
        gen = torch.Generator().manual_seed(1)
        gains = {}
        for i in trainer.dataset.train_indices:
            gains[i] = 0.6 + 0.8 * torch.rand(3, generator=gen)
            trainer.dataset.images[i] = (trainer.dataset.images[i] * gains[i]).clamp(0, 1)
        metrics = trainer.train()
        results[name] = (trainer, metrics, gains)
    return results


def test_per_view_exposure_recovers_the_scene_from_photos_of_varying_exposure(exposure_runs):
    with_psnr = exposure_runs["with"][1]["psnr"]
    without_psnr = exposure_runs["without"][1]["psnr"]
    assert with_psnr > without_psnr + 1.0, (with_psnr, without_psnr)
    assert exposure_runs["without"][0].exposure is None
    assert exposure_runs["without"][0].decisions["view_exposure"].startswith("off (a rendered scene")


def test_learned_gains_follow_the_photos_gains(exposure_runs):
    trainer, _, gains = exposure_runs["with"]
    learned = trainer.exposure.gains_and_offsets()[0].detach()  # [V, 3]
    applied = torch.stack([gains[i] for i in trainer.dataset.train_indices])
    corr = torch.corrcoef(torch.stack([learned.flatten(), applied.flatten()]))[0, 1]
    assert corr > 0.8, float(corr)


def test_a_resumed_run_continues_from_the_saved_gains(exposure_runs, tmp_path):
    trainer, _, _ = exposure_runs["with"]
    ckpt = trainer.run_dir / "checkpoints" / "step-000150.ckpt"
    resumed = replace(trainer.config, load_checkpoint=ckpt, output_dir=tmp_path, experiment_name="resumed").setup()
    for saved, loaded in zip(trainer.exposure.gains_and_offsets(), resumed.exposure.gains_and_offsets(), strict=True):
        assert torch.equal(saved.detach(), loaded.detach())
    moments = resumed.exposure_optimizer.state_dict()["state"]
    assert moments and float(moments[0]["exp_avg_sq"].abs().sum()) > 0  # Adam's moments came back too
