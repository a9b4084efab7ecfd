"""Per-view exposure: the affines' gauge, what they do to a render, which tone test views take, and runs on photos
of varying exposure."""

import json
from dataclasses import replace

import pytest
import torch

from metegs.cameras import Cameras
from metegs.engine.optim import OptimConfig
from metegs.engine.run import evaluate_run
from metegs.models.exposure import ViewExposure, nearest_training_rows


def cameras_along_a_street(n: int) -> Cameras:
    """``n`` cameras 1 m apart along x, all looking along +z (OpenCV axes)."""
    c2w = torch.eye(4).repeat(n, 1, 1)
    c2w[:, 0, 3] = torch.arange(n, dtype=torch.float32)
    return Cameras.create(c2w, 50.0, 50.0, 32.0, 24.0, 64, 48)


def test_each_view_finds_its_nearest_other_training_view():
    cameras = cameras_along_a_street(7)
    rows = nearest_training_rows(cameras, [0, 2, 3, 5])
    # view 1 sits between training views 0 and 2 (rows 0, 1), view 4 between 3 and 5 (rows 2, 3); a training
    # view's neighbour is never itself
    assert rows[0] == 1 and rows[2] == 2 and rows[3] == 1 and rows[5] == 2 and rows[6] == 3
    assert rows[1] in (0, 1) and rows[4] in (2, 3)
    assert nearest_training_rows(cameras, [3]) == [0, 0, 0, -1, 0, 0, 0]  # alone: nobody to ask for view 3


def test_the_heading_decides_between_cameras_in_one_place():
    c2w = torch.eye(4).repeat(3, 1, 1)
    c2w[1, :3, :3] = c2w[2, :3, :3] = torch.diag(torch.tensor([-1.0, 1.0, -1.0]))  # views 1 and 2 look back
    c2w[2, 0, 3] = 0.1
    cameras = Cameras.create(c2w, 50.0, 50.0, 32.0, 24.0, 64, 48)
    assert nearest_training_rows(cameras, [0, 1])[2] == 1  # view 2 stands nearer view 0 but looks as view 1 does


def street_exposure(tones: torch.Tensor) -> ViewExposure:
    """A ViewExposure over 12 street cameras, training views 0, 2, ..., 10 with gains ``tones`` [6, 3]."""
    cameras = cameras_along_a_street(12)
    train = list(range(0, 12, 2))
    exposure = ViewExposure(train, 12, nearest=nearest_training_rows(cameras, train))
    with torch.no_grad():
        exposure.offsets[:, 0] = tones - 1.0
    return exposure


def test_test_views_take_the_nearest_photos_tone_where_tone_follows_the_street():
    ramp = torch.linspace(0.6, 1.4, 6)[:, None].expand(6, 3)  # automatic exposure brightening down the street
    exposure = street_exposure(ramp)
    near, average = exposure.tone_errors()
    assert near < average and exposure.tones_from_nearest()
    gains, offsets = exposure.gains_and_offsets()
    rgb = torch.rand(4, 6, 3)
    assert torch.allclose(exposure(rgb, 3), rgb * gains[1] + offsets[1])  # view 3: training view 2's tone (row 1)
    assert torch.allclose(exposure(rgb, 11), rgb * gains[5] + offsets[5])  # past the end: the last photo's


def test_the_leave_one_out_errors_do_not_depend_on_the_order_of_the_training_views():
    cameras = cameras_along_a_street(12)
    ramp = torch.linspace(0.6, 1.4, 6)[:, None].expand(6, 3)
    errors = []
    for train in (list(range(0, 12, 2)), [10, 0, 8, 2, 6, 4]):
        exposure = ViewExposure(train, 12, nearest=nearest_training_rows(cameras, train))
        with torch.no_grad():
            exposure.offsets[:, 0] = ramp[torch.as_tensor(train) // 2] - 1.0  # each view its place's tone
        errors.append(exposure.tone_errors())
    assert errors[0] == pytest.approx(errors[1]) and errors[0][0] < errors[0][1]


def test_test_views_keep_the_average_tone_where_tone_jumps_from_shot_to_shot():
    jumps = torch.tensor([0.6, 1.4, 0.6, 1.4, 0.6, 1.4])[:, None].expand(6, 3)  # neighbours disagree most
    exposure = street_exposure(jumps)
    near, average = exposure.tone_errors()
    assert near > average and not exposure.tones_from_nearest()
    rgb = torch.rand(4, 6, 3)
    assert exposure(rgb, 3) is rgb


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
    brightened or darkened (gains 0.6-1.4 per channel); test photos as they were. 600 steps: at 150 the scene's
    own underfitting hides the tone (the gain over seeds of the gains ran from -0.3 to +0.9 dB; at 600, +1.1 to
    +1.6 dB)."""
    results = {}
    for name, choice in (("with", "on"), ("without", "auto")):  # auto: off on the rendered built-in scene
        trainer = exposure_trainer(tmp_path_factory.mktemp(name), choice, steps=600)
        gen = torch.Generator().manual_seed(1)
        gains = {}
        for i in trainer.dataset.train_indices:
            gains[i] = 0.6 + 0.8 * torch.rand(3, generator=gen)
            trainer.dataset.images[i] = (trainer.dataset.images[i] * gains[i]).clamp(0, 1)
        metrics = trainer.train()
        results[name] = (trainer, metrics, gains)
    return results


def exposure_trainer(folder, choice: str, steps: int = 150):
    """A ``steps``-step run of the tiny synthetic scene with `view_exposure` ``choice``, its test views scored against
    their photos as a capture's are (not against the built-in scene's clean renders)."""
    from tests.engine.test_trainer import tiny_config

    cfg = tiny_config(folder, save_renders=False)
    optim = OptimConfig(exposure_lr=3e-2)  # short runs: faster than a real run's 1e-3
    trainer = replace(cfg, max_steps=steps, eval_every=0.0, view_exposure=choice, optim=optim).setup()
    trainer.dataset.clean_images = None
    trainer.exposure, trainer.exposure_optimizer = trainer._make_exposure()
    return trainer


@pytest.fixture(scope="module")
def orbit_run(tmp_path_factory):
    """3dgs with per-view exposure on the tiny scene photographed as a camera on automatic exposure would round
    it: each photo, test photos included, brightened or darkened by how far round the orbit it stands."""
    trainer = exposure_trainer(tmp_path_factory.mktemp("orbit"), "on")
    centers = trainer.dataset.cameras.centers
    offset = centers - centers.mean(dim=0)
    azimuth = torch.atan2(offset[:, 1], offset[:, 0])
    phases = torch.tensor([0.0, 0.5, 1.0])
    ds = trainer.dataset
    for i in range(len(ds.images)):
        ds.images[i] = (ds.images[i] * (1.0 + 0.35 * torch.sin(azimuth[i] + phases))).clamp(0, 1)
    return trainer, trainer.train()


def test_test_views_scored_in_their_nearest_photos_tone_where_tone_follows_the_orbit(orbit_run):
    trainer, metrics = orbit_run
    assert trainer.decisions["test_tone"].startswith("their nearest training photo's"), trainer.decisions
    assert metrics["test_tone"] == "nearest"
    saved = json.loads((trainer.run_dir / "metrics.json").read_text())
    assert saved["test_tone"] == "nearest" and evaluate_run(trainer)["test_tone"] == "nearest"
    trainer.exposure.nearest = None  # the same Gaussians, test views in the photos' average tone
    average = trainer.record_eval(quick=True)["psnr"]
    assert metrics["psnr"] > average + 0.5, (metrics["psnr"], average)


def test_test_views_keep_the_average_tone_where_each_photo_was_exposed_at_random(exposure_runs):
    assert exposure_runs["with"][0].decisions["test_tone"].startswith("the photos' average (each training photo")
    assert exposure_runs["with"][1]["test_tone"] == "average" and exposure_runs["without"][1]["test_tone"] is None


def test_against_clean_references_the_same_rule_picks_the_tone(orbit_run, tmp_path):
    """Clean references are photos too, each exposed where its camera stood: where the tone follows the orbit, a run
    scored against them takes the nearest photo's tone as one scored on its photos does, and scores better for it."""
    photos, _ = orbit_run
    from tests.engine.test_trainer import tiny_config

    cfg = tiny_config(tmp_path, save_renders=False)
    trainer = replace(cfg, max_steps=150, eval_every=0.0, view_exposure="on", optim=OptimConfig(exposure_lr=3e-2))
    trainer = trainer.setup()
    trainer.dataset.images = [image.clone() for image in photos.dataset.images]
    trainer.dataset.clean_images = [image.clone() for image in photos.dataset.images]
    metrics = trainer.train()
    assert trainer.dataset.clean_images is not None and metrics["test_tone"] == "nearest"
    assert trainer.decisions["test_tone"].startswith("their nearest training photo's"), trainer.decisions
    trainer.exposure.nearest = None  # the same Gaussians, test views in the photos' average tone
    assert metrics["psnr"] > trainer.record_eval(quick=True)["psnr"] + 0.5


def test_per_view_exposure_recovers_the_scene_from_photos_of_varying_exposure(exposure_runs):
    with_psnr = exposure_runs["with"][1]["psnr"]
    without_psnr = exposure_runs["without"][1]["psnr"]
    assert with_psnr > without_psnr + 0.75, (with_psnr, without_psnr)
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
    ckpt = trainer.run_dir / "checkpoints" / "step-000600.ckpt"
    resumed = replace(trainer.config, load_checkpoint=ckpt, output_dir=tmp_path, experiment_name="resumed").setup()
    for saved, loaded in zip(trainer.exposure.gains_and_offsets(), resumed.exposure.gains_and_offsets(), strict=True):
        assert torch.equal(saved.detach(), loaded.detach())
    moments = resumed.exposure_optimizer.state_dict()["state"]
    assert moments and float(moments[0]["exp_avg_sq"].abs().sum()) > 0  # Adam's moments came back too
