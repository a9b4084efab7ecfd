"""Short training runs with every learning rate multiplied by 10: no NaN or Inf in the model, the weather,
the losses or the metrics. 1000x learning rates finish finite or stop cleanly, and a run that does diverge
stops with a clear error naming the cause and a checkpoint to resume from."""

import math
from pathlib import Path

import pytest
import torch

from metegs.config import apply_overrides
from metegs.engine.optim import OptimConfig
from metegs.errors import MetegsError
from metegs.registry import registry

LR_FIELDS = ("means_lr", "means_lr_final", "sh0_lr", "shN_lr", "opacities_lr", "scales_lr", "quats_lr")
TINY = {"test_every": 4, "synthetic": {"width": 32, "height": 24, "num_views": 8, "num_points": 400}}


def _config(method: str, multiplier: float, steps: int, **extra):
    base = registry("method").get(method)()
    optim = OptimConfig()
    overrides = {
        "max_steps": steps,
        "eval_every": 0.5,
        "checkpoint_every": 5,
        "save_renders": False,
        "progress": False,
        "densify": {"max_gaussians": 1500},
        "dataset": TINY,
        "optim": {k: getattr(optim, k) * multiplier for k in LR_FIELDS},
        **extra,
    }
    if method != "3dgs":
        overrides.update(
            weather_lr=base.weather_lr * multiplier,
            gtn={"lr": base.gtn.lr * multiplier},
            degrade="rain+fog",
            conditions={"precip_mm_h": 20.0, "visibility_m": 300.0},
            compare_baseline=False,
            weights={"perceptual": 0.0},
            rain_streaks={"max_count": 300},
        )
    return apply_overrides(base, overrides)


def _assert_finite_run(trainer, metrics):
    for name, p in trainer.model.params.items():
        assert torch.isfinite(p).all(), f"non-finite {name}"
    for key in ("psnr", "ssim"):
        assert math.isfinite(metrics[key]), key
    for h in metrics["history"]:
        assert math.isfinite(h["psnr"]) and math.isfinite(h["ssim"])
    for m in getattr(trainer, "weather_models", []):
        assert all(torch.isfinite(p).all() for p in m.parameters()), m.name
    if getattr(trainer, "gtn", None) is not None:
        assert all(torch.isfinite(p).all() for p in trainer.gtn.parameters())


@pytest.mark.parametrize("method,steps", [("3dgs", 30), ("metegs-full", 12)])
def test_ten_times_the_learning_rates_stays_finite(tmp_path, method, steps):
    trainer = _config(method, 10.0, steps).setup(run_dir=tmp_path / method)
    metrics = trainer.train()
    _assert_finite_run(trainer, metrics)
    assert metrics["steps"] == steps and any((tmp_path / method / "checkpoints").glob("*.ckpt"))


@pytest.mark.filterwarnings("ignore:save_ply")
def test_1000x_learning_rates_finish_finite_or_stop_cleanly(tmp_path):
    trainer = _config("3dgs", 1000.0, 20).setup(run_dir=tmp_path / "run")
    try:
        metrics = trainer.train()
    except MetegsError as exc:
        assert "diverged" in str(exc)
    else:
        _assert_finite_run(trainer, metrics)


@pytest.mark.filterwarnings("ignore:save_ply")
def test_a_diverging_run_stops_with_the_cause_and_a_checkpoint(tmp_path):
    trainer = _config("3dgs", 1.0, 20).setup(run_dir=tmp_path / "run")

    def poison(tr, stats):  # what an overflow in a kernel or a bad learning rate leaves behind
        if tr.step == 7:
            tr.model.params["scales"].data[0] = float("nan")

    trainer.step_hooks.append(poison)
    with pytest.raises(MetegsError) as info:
        trainer.train()
    text = str(info.value)
    assert "diverged at step 8" in text and "non-finite (NaN/Inf)" in text and "scales" in text
    named = [Path(w) for w in text.split() if w.endswith(".ckpt")]
    assert named and named[0].is_file(), "the error names a checkpoint to resume from"
    assert named[0].name == "step-000005.ckpt"
