"""End-to-end: a tiny run on the synthetic scene, its outputs, resume, PLY re-import and CLI tools."""

import json
from dataclasses import replace

import numpy as np
import pytest
import torch

from metegs.data.config import DatasetConfig, SyntheticSceneConfig
from metegs.densify.adc import ADCConfig
from metegs.engine.config import TrainConfig
from metegs.engine.run import load_run
from metegs.gaussians.ply import load_ply
from metegs.render import RenderSettings


def tiny_config(tmp_path, **kw) -> TrainConfig:
    ds = DatasetConfig(synthetic=SyntheticSceneConfig(width=64, height=48, num_views=16, num_points=800))
    return TrainConfig(
        max_steps=60,
        output_dir=tmp_path,
        experiment_name="run",
        backend="auto",
        device="cpu",
        progress=False,
        dataset=ds,
        checkpoint_every=30,
        eval_every=0.5,
        # A 60-step run at 64x48: an opacity reset every 6 steps would be meaningless, and tiny images cross
        # the gradient threshold so often that growth needs a budget (which this also exercises).
        densify=ADCConfig(reset_every=0.0, max_gaussians=2000),
        **kw,
    )


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("train")
    trainer = tiny_config(tmp).setup()
    trainer.initial_psnr = trainer.record_eval(quick=True)["psnr"]
    trainer.history.clear()
    metrics = trainer.train()
    return trainer, metrics


def test_run_folder_contents(trained):
    trainer, metrics = trained
    run = trainer.run_dir
    for name in (
        "config.yml",
        "metrics.json",
        "scene.ply",
        "checkpoints/step-000030.ckpt",
        "checkpoints/step-000060.ckpt",
    ):
        assert (run / name).is_file(), name
    assert sorted(p.name for p in (run / "renders" / "test").glob("*.png"))
    saved = json.loads((run / "metrics.json").read_text())
    assert saved["steps"] == 60 and saved["backend"] in ("cpu", "torch")
    assert saved["psnr"] == pytest.approx(metrics["psnr"])
    assert saved["lpips"] is None or isinstance(saved["lpips"], float)
    if saved["lpips"] is None:
        assert saved["lpips_reason"]
    assert [h["step"] for h in saved["history"]] == [30, 60]


def test_training_improves_over_initialisation(trained):
    trainer, metrics = trained
    assert metrics["psnr"] > trainer.initial_psnr + 1.5  # measured: 9.7 -> 11.7 (cpu) and 11.9 dB (torch)
    assert 1800 < len(trainer.model) <= 2000  # grew to the budget (the 0.1 opacity cull then takes ~3 %), not beyond


def test_scene_ply_reimports_to_identical_renders(trained):
    trainer, _ = trained
    model = load_ply(trainer.run_dir / "scene.ply")
    cam = trainer.dataset.cameras[trainer.dataset.test_indices[0]]
    settings = RenderSettings(sh_degree=trainer.model.active_sh_degree)
    with torch.no_grad():
        a = trainer.rasterizer.render(trainer.model.activated(), cam, settings).rgb
        model.active_sh_degree = trainer.model.active_sh_degree
        b = trainer.rasterizer.render(model.activated(), cam, settings).rgb
    # the built-in scene is z-up: its file is turned y-down for viewers and back on reading (float32 rounding)
    assert torch.allclose(a, b, atol=1e-5)


def test_resume_from_checkpoint_continues_the_step_count(trained, tmp_path):
    trainer, _ = trained
    ckpt = trainer.run_dir / "checkpoints" / "step-000030.ckpt"
    cfg = replace(tiny_config(tmp_path), load_checkpoint=ckpt, max_steps=40)
    resumed = cfg.setup()
    assert resumed.step == 30
    assert len(resumed.model) == resumed.optimizers["means"].param_groups[0]["params"][0].shape[0]
    metrics = resumed.train()
    assert metrics["steps"] == 40


def test_a_run_resumed_at_its_end_scores_as_it_did(trained, tmp_path):
    """Resumed from its last checkpoint with nothing left to train, a run evaluates with the SH degree its last step
    rendered with (it used to render degree 0, a different scene)."""
    trainer, metrics = trained
    ckpt = trainer.run_dir / "checkpoints" / f"step-{trainer.step:06d}.ckpt"
    resumed = replace(tiny_config(tmp_path), load_checkpoint=ckpt).setup()
    assert resumed.model.active_sh_degree == trainer.model.active_sh_degree > 0
    assert resumed.train()["psnr"] == pytest.approx(metrics["psnr"], abs=1e-6)


def test_load_run_and_eval_cli(trained):
    from metegs.cli.eval import EvalArgs
    from metegs.cli.eval import main as eval_main

    trainer, metrics = trained
    again = load_run(trainer.run_dir)
    assert len(again.model) == len(trainer.model)
    m = eval_main(EvalArgs(run_dir=trainer.run_dir, ply=trainer.run_dir / "scene.ply"))
    assert m["psnr"] == pytest.approx(metrics["psnr"], abs=1e-4)
    assert (trainer.run_dir / "eval.json").is_file()


def test_render_cli(trained, tmp_path):
    from metegs.cli.render import RenderArgs
    from metegs.cli.render import main as render_main

    trainer, _ = trained
    out = render_main(RenderArgs(run_dir=trainer.run_dir, split="train", output=tmp_path / "r", depth=True))
    assert len(list(out.glob("*_depth.png"))) == len(trainer.dataset.train_indices)


def test_render_cli_camera_paths_write_videos_of_the_clean_scene(trained, tmp_path):
    import json

    import imageio.v3 as iio

    from metegs.cli.render import RenderArgs
    from metegs.cli.render import main as render_main
    from metegs.errors import DataError

    trainer, _ = trained
    spiral = render_main(RenderArgs(run_dir=trainer.run_dir, camera_path="spiral", frames=6, output=tmp_path / "s"))
    assert spiral.parent == tmp_path / "s" and spiral.stat().st_size > 0
    if spiral.suffix in (".mp4", ".gif"):
        frames = iio.imread(spiral, index=None)
        assert len(frames) == 6 and frames.shape[1:3] == (48, 64) and frames.std() > 1  # the scene, not blank
    path = tmp_path / "path.json"
    key = {"camera_to_world": trainer.dataset.cameras.camera_to_worlds[0].reshape(-1).tolist(), "fov": 50}
    path.write_text(json.dumps({"render_width": 40, "render_height": 30, "fps": 5, "camera_path": [key, key]}))
    assert render_main(RenderArgs(run_dir=trainer.run_dir, camera_path=str(path), output=tmp_path / "f")).is_file()
    path.write_text(json.dumps({"render_width": 40, "render_height": 30, "camera_path": [key, {"fov": 50}]}))
    with pytest.raises(DataError, match=r"camera_path\[1\]: 'camera_to_world' must be 16 numbers"):
        render_main(RenderArgs(run_dir=trainer.run_dir, camera_path=str(path), output=tmp_path / "g"))


def test_render_cli_weather_along_a_camera_path_follows_the_met_record(trained, tmp_path):
    import imageio.v3 as iio

    from metegs.cli.render import RenderArgs
    from metegs.cli.render import main as render_main
    from metegs.errors import ConfigError

    trainer, _ = trained
    args = RenderArgs(run_dir=trainer.run_dir, camera_path="interpolate", frames=4, weather="record", hours=3)
    clean = render_main(replace(args, output=tmp_path))
    weather = next(tmp_path.glob("camera-path-weather.*"))
    if clean.suffix not in (".mp4", ".gif"):
        pytest.skip("no video encoder: frames written as PNG folders")
    clean_frames, weather_frames = (iio.imread(p, index=None).astype(float) for p in (clean, weather))
    assert weather_frames.shape == clean_frames.shape == (4, 48, 64, 3)
    # the shipped storm's rain (6.8 mm/h and more over those hours) changes every frame, below the caption too
    assert all(np.abs(w - c)[:30].mean() > 2 for w, c in zip(weather_frames, clean_frames))
    with pytest.raises(ConfigError, match="--camera-path"):
        RenderArgs(run_dir=trainer.run_dir, weather="run")


def test_missing_data_folder_is_a_clear_error(tmp_path):
    from metegs.errors import DataError

    with pytest.raises(DataError, match="does not exist"):
        replace(tiny_config(tmp_path), data=tmp_path / "nowhere").setup()


def test_masks_replace_masked_out_pixels_by_the_background(tmp_path):
    trainer = replace(tiny_config(tmp_path), background="white").setup()
    ds = trainer.dataset
    assert ds.masks is None
    assert trainer.target(0, torch.ones(3)) is ds.images[0]
    ds.masks = [torch.zeros_like(img[..., 0]) for img in ds.images]
    ds.masks[0][:, : img_w(ds) // 2] = 1.0
    t = trainer.target(0, torch.ones(3))
    half = img_w(ds) // 2
    assert torch.equal(t[:, :half], ds.images[0][:, :half]) and (t[:, half:] == 1.0).all()
    assert trainer.train_step(0)["loss"] >= 0


def img_w(ds) -> int:
    return int(ds.cameras.width[0])


def test_torch_threads_run_torchs_ops_serially_while_the_cpu_kernels_keep_the_runs_threads(tmp_path):
    """`torch_threads: 1` with the cpu backend: every step runs torch's ops on one thread and the kernels on the
    run's two; the counts are restored when training ends."""
    from metegs.render.cpu_backend import CpuExtensionError, load_extension

    try:
        ext = load_extension()
    except CpuExtensionError as exc:
        pytest.skip(f"the cpu rasteriser extension cannot be built here: {exc}")
    previous = torch.get_num_threads()
    try:
        config = replace(tiny_config(tmp_path), backend="cpu", threads=2, torch_threads=1, max_steps=4)
        trainer = config.setup()
        seen = []
        trainer.step_hooks.append(lambda t, stats: seen.append((torch.get_num_threads(), ext.get_num_threads())))
        trainer.train()
        assert seen == [(1, 2)] * 4
        assert (torch.get_num_threads(), ext.get_num_threads()) == (2, 2)
        decisions = json.loads((trainer.run_dir / "decisions.json").read_text())["decisions"]
        assert decisions["threads"] == "torch's own ops on 1, the cpu kernels on 2 (torch_threads)"
    finally:
        torch.set_num_threads(previous)


def test_the_run_records_the_image_size_its_device_chose(tmp_path):
    from metegs.bench.suite import config_changes

    ds = DatasetConfig(synthetic=SyntheticSceneConfig(width=64, height=48, num_views=10, num_points=300))
    config = TrainConfig(
        max_steps=1, output_dir=tmp_path, experiment_name="run", device="cpu", progress=False, dataset=ds
    )
    trainer = config.setup()
    assert trainer.config.dataset.auto_max_side == 640
    assert trainer.decisions["image size"].startswith("64x48 px: the longer side at most 640 px on cpu")
    trainer.train()
    assert config_changes(trainer.run_dir, config) == []  # None in the suite's config: the device's choice
    assert config_changes(trainer.run_dir, replace(config, dataset=replace(ds, auto_max_side=320))) == [
        "dataset.auto_max_side"
    ]


def test_a_method_extends_the_step_through_its_hooks(tmp_path):
    """A method adds a loss term, an optimiser and a densification action by filling the step's hooks; the step
    itself (schedule, backward, statistics, optimisers, densification, stats) is the base trainer's."""
    from metegs.engine.trainer import StepRender, Trainer

    class Tinted(Trainer):
        def setup_method(self):
            self.tint = torch.zeros(3, requires_grad=True)
            self.tint_opt = torch.optim.Adam([self.tint], lr=0.05)
            self.densified = 0

        def photo_render(self, index, background):
            out = self.render(index, background=background)
            return StepRender(out.rgb + self.tint, out, num_scene=len(self.model))

        def step_loss(self, index, background, render, target, stats):
            stats["tint"] = float(self.tint.detach().abs().sum())
            return super().step_loss(index, background, render, target, stats) + 0.1 * self.tint.square().sum()

        def step_optimizers(self):
            return [*super().step_optimizers(), self.tint_opt]

        def densify_step(self):
            self.densified += 1
            return super().densify_step()

    config = tiny_config(tmp_path)
    trainer = Tinted(config)
    # photos 0.2 brighter than the scene renders: the tint learns what the scene cannot
    trainer.dataset.images = [(img + 0.2).clamp(0, 1) for img in trainer.dataset.images]
    means_before = trainer.model.params["means"].detach().clone()
    stats = [trainer.train_step(i) for i in trainer.dataset.train_indices[:8]]
    assert trainer.densified == 8 and all({"loss", "psnr", "tint"} <= set(s) for s in stats)
    assert float(trainer.tint.detach().mean()) > 0.05 and trainer.tint.grad is None  # stepped, then zeroed
    assert not torch.equal(trainer.model.params["means"].detach(), means_before)
    assert trainer.densifier.state is not None and float(trainer.densifier.state.count.sum()) > 0


def test_densification_horizon_is_a_decision_and_the_schedule(tmp_path):
    long = replace(tiny_config(tmp_path / "long"), max_steps=7000, densify=ADCConfig(horizon=3000)).setup()
    assert long.densifier.schedule() == {"start": 50, "stop": 1500, "every": 100, "reset_every": 300}
    assert long.decisions["densification horizon"].startswith("3000 steps: refines from step 50 to 1500")
    within = replace(tiny_config(tmp_path / "within"), max_steps=2000, densify=ADCConfig(horizon=3000)).setup()
    assert "densification horizon" not in within.decisions  # a run inside the horizon keeps its own schedule
