"""A run never overwrites another, stops cleanly on Ctrl-C and diverges with advice that can be followed."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import replace
from datetime import datetime
from pathlib import Path

import pytest
import torch
import yaml

from metegs.data.config import DatasetConfig, SyntheticSceneConfig
from metegs.engine.checkpoint import load_checkpoint
from metegs.engine.config import TrainConfig
from metegs.errors import Interrupted, TrainingDiverged
from metegs.files import remove_dead_stages

TINY = DatasetConfig(test_every=3, synthetic=SyntheticSceneConfig(width=32, height=24, num_views=6, num_points=200))


def tiny(tmp_path, **kw) -> TrainConfig:
    base = dict(max_steps=4, output_dir=tmp_path, device="cpu", progress=False, dataset=TINY, save_renders=False,
                eval_every=0.0)  # fmt: skip
    return TrainConfig(**{**base, **kw})


class FrozenClock(datetime):
    @classmethod
    def now(cls, tz=None):
        return datetime(2026, 11, 25, 12, 0, 0)


def test_two_runs_in_the_same_second_get_two_folders(tmp_path, monkeypatch):
    monkeypatch.setattr("metegs.engine.trainer.datetime", FrozenClock)
    first, second = tiny(tmp_path).setup(), tiny(tmp_path, seed=1).setup()
    assert first.run_dir == second.run_dir  # the same timestamp before the folders are claimed
    m1, m2 = first.train(), second.train()
    base = tmp_path / "synthetic" / "3dgs" / "2026-11-25_120000"
    assert (first.run_dir, second.run_dir) == (base, base.with_name(base.name + "-2"))
    for run, metrics in ((first, m1), (second, m2)):
        saved = json.loads((run.run_dir / "metrics.json").read_text())
        assert saved["psnr"] == metrics["psnr"]
        assert yaml.safe_load((run.run_dir / "config.yml").read_text())["seed"] == run.config.seed


TRAIN = [sys.executable, "-m", "metegs.cli.train", "3dgs", "--no-progress", "--no-save-renders", "--eval-every", "0",
         "--dataset.synthetic.width", "32", "--dataset.synthetic.height", "24", "--dataset.synthetic.num-views", "6",
         "--dataset.synthetic.num-points", "200", "--dataset.test-every", "3"]  # fmt: skip


def test_two_processes_started_together_keep_both_runs(tmp_path):
    cmd = [*TRAIN, "--max-steps", "4", "--output-dir", str(tmp_path)]
    procs = [subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for _ in range(2)]
    outs = [p.communicate(timeout=300) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], [e[-2000:] for _, e in outs]
    runs = sorted((tmp_path / "synthetic" / "3dgs").iterdir())
    assert len(runs) == 2
    for run in runs:
        assert json.loads((run / "metrics.json").read_text())["steps"] == 4


def test_ctrl_c_saves_a_checkpoint_and_names_it(tmp_path):
    cmd = [*TRAIN, "--max-steps", "100000", "--checkpoint-every", "0", "--output-dir", str(tmp_path),
           "--experiment-name", "run"]  # fmt: skip
    # faulthandler: a child that does not stop is sent SIGABRT and writes every thread's stack to stderr
    env = {**os.environ, "PYTHONFAULTHANDLER": "1"}
    # a suite started in the background by a shell without job control inherits SIGINT ignored, and Python then
    # leaves Ctrl-C ignored in the child too: the child gets the default disposition, as a terminal's process has
    proc = subprocess.Popen(
        cmd,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    try:
        first = tmp_path / "synthetic/3dgs/run/checkpoints/step-000000.ckpt"
        deadline = time.monotonic() + 120
        while not first.exists():
            assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()[1][-2000:]
            time.sleep(0.05)
        time.sleep(1.0)  # some steps
        proc.send_signal(signal.SIGINT)
        try:
            _, err = proc.communicate(timeout=120)
        except subprocess.TimeoutExpired:  # say where it stood: still training, or stopped and stuck on its way out
            proc.send_signal(signal.SIGABRT)
            try:
                out, err = proc.communicate(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
                out, err = proc.communicate()
            pytest.fail(f"no exit within 120 s of Ctrl-C; stdout: {out[-1500:]}\nstderr (stacks): {err[-6000:]}")
    finally:
        if proc.poll() is None:  # a failed wait must not leave a 100000-step run training beside the suite
            proc.kill()
            proc.communicate()
    assert proc.returncode == 130, err[-2000:]
    assert "Traceback" not in err
    flat = " ".join(err.split())
    assert "training interrupted at step" in flat and "--load-checkpoint" in flat
    saved = Path(flat.split("--load-checkpoint ")[1].split()[0].rstrip("`"))
    ckpt = load_checkpoint(saved)
    assert ckpt["step"] > 0 and saved.name == f"step-{ckpt['step']:06d}.ckpt"


def _stop_at(step, exc):
    def hook(trainer, stats):
        if trainer.step == step:
            raise exc

    return hook


def test_interrupt_in_process_keeps_the_step_reached(tmp_path):
    trainer = tiny(tmp_path, max_steps=50, experiment_name="run").setup()
    trainer.step_hooks.append(_stop_at(3, KeyboardInterrupt()))
    with pytest.raises(Interrupted, match=r"step 3 of 50.*step-000003\.ckpt") as info:
        trainer.train()
    assert info.value.exit_code == 130
    resumed = replace(trainer.config, load_checkpoint=trainer.run_dir / "checkpoints").setup()
    assert resumed.step == 3 and resumed.run_dir == trainer.run_dir


def _poison(at):
    def hook(trainer, stats):
        if trainer.step == at:
            with torch.no_grad():
                trainer.model.params["means"][0, 0] = float("nan")

    return hook


def test_divergence_before_any_checkpoint_does_not_advise_resuming(tmp_path):
    trainer = tiny(tmp_path, max_steps=20, checkpoint_every=0).setup()
    trainer.step_hooks.append(_poison(2))
    with pytest.raises(TrainingDiverged, match=r"step 3: non-finite \(NaN/Inf\) means\. No checkpoint after the start"):
        trainer.train()


def test_divergence_after_a_checkpoint_names_it(tmp_path):
    trainer = tiny(tmp_path, max_steps=20, checkpoint_every=2).setup()
    trainer.step_hooks.append(_poison(5))
    with pytest.raises(TrainingDiverged, match=r"Resume from .*step-000004\.ckpt"):
        trainer.train()
    assert torch.isfinite(load_checkpoint(trainer.run_dir / "checkpoints/step-000004.ckpt")["params"]["means"]).all()


def test_config_yml_holds_absolute_paths(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    trainer = tiny(Path("outs"), experiment_name="run").setup()
    trainer.train()
    saved = yaml.safe_load((tmp_path / "outs/synthetic/3dgs/run/config.yml").read_text())
    assert saved["output_dir"] == str(tmp_path / "outs")


def test_staged_folders_of_dead_processes_are_removed(tmp_path):
    output = tmp_path / "rainy"
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    stale = tmp_path / f".rainy.partial-{dead.stdout.strip()}"
    live = tmp_path / f".rainy.partial-{os.getpid()}"
    for folder in (stale, live):
        (folder / "images").mkdir(parents=True)
    assert remove_dead_stages(output) == [stale]
    assert not stale.exists() and live.exists()


def test_resume_with_another_split_of_the_same_scene_is_accepted(tmp_path):
    first = tiny(tmp_path, max_steps=2, experiment_name="run").setup()
    first.train()
    other_split = replace(TINY, test_every=2)
    again = replace(first.config, dataset=other_split, load_checkpoint=first.run_dir / "checkpoints", max_steps=4)
    assert again.setup().step == 2


def test_every_output_gets_the_permissions_the_umask_gives(tmp_path):
    from metegs.files import NEW_FILE_MODE

    mask = os.umask(0o022)
    os.umask(mask)
    assert NEW_FILE_MODE == 0o666 & ~mask
    trainer = tiny(tmp_path, experiment_name="run", save_renders=True).setup()
    trainer.train()
    files = [p for p in trainer.run_dir.rglob("*") if p.is_file()]
    assert {p.suffix for p in files} >= {".yml", ".json", ".ckpt", ".ply", ".png"}
    wrong = {str(p.relative_to(trainer.run_dir)): oct(p.stat().st_mode & 0o777) for p in files}
    assert all(mode == oct(NEW_FILE_MODE) for mode in wrong.values()), wrong


def test_a_stricter_umask_is_honoured(tmp_path):
    code = (
        "import os; os.umask(0o027)\n"
        "from pathlib import Path\n"
        "from metegs.files import atomic_write_text\n"
        "from metegs.data.images import save_image\n"
        "import numpy as np\n"
        f"atomic_write_text(Path({str(tmp_path)!r}) / 'a.json', '{{}}')\n"
        f"save_image(Path({str(tmp_path)!r}) / 'b.png', np.zeros((4, 4, 3)))\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)
    assert {oct(p.stat().st_mode & 0o777) for p in tmp_path.iterdir()} == {oct(0o640)}
