"""A tiny metegs-full run trained once per test session with the live viewer attached (paused and stepped once
on the way); its folder is shared by the viewer tests (across xdist workers, through a file lock)."""

from __future__ import annotations

import json
import os
import threading
import time
from dataclasses import replace
from pathlib import Path

import pytest
import torch
from filelock import FileLock

STEPS = 40


def _wait(predicate, timeout: float = 120.0) -> bool:
    deadline = time.perf_counter() + timeout
    while time.perf_counter() < deadline:
        if predicate():
            return True
        time.sleep(0.02)
    return False


def _drive(control, record: dict) -> None:
    """From a helper thread: pause the run, check that it stays put, step it once, take a snapshot, resume."""
    try:
        record["reached_step_5"] = _wait(lambda: control.step >= 5)
        control.pause()
        record["blocked"] = _wait(lambda: control.blocked)
        s0 = control.step
        time.sleep(1.0)
        record["paused_steps"] = [s0, control.step]
        control.step_once()
        record["stepped"] = _wait(lambda: control.step == s0 + 1 and control.blocked)
        time.sleep(0.5)
        record["after_step"] = control.step
        record["expected_after_step"] = s0 + 1
        control.request_snapshot()
        record["snapshot_while_paused"] = _wait(
            lambda: control.snapshot is not None and control.snapshot.step == s0 + 1
        )
        record["rate_while_paused"] = control.iterations_per_second()
    finally:
        control.resume()


def train_live(out: Path) -> dict:
    from metegs.data.config import DatasetConfig, SyntheticSceneConfig
    from metegs.methods import metegs_full
    from metegs.viewer import Viewer, ViewerConfig

    config = replace(
        metegs_full(),
        max_steps=STEPS,
        output_dir=out,
        experiment_name="run",
        progress=False,
        device="cpu",
        compare_baseline=False,
        checkpoint_every=0,
        eval_every=0.5,
        dataset=DatasetConfig(synthetic=SyntheticSceneConfig(width=64, height=48, num_views=8)),
    )
    trainer = config.setup()
    threads_before = torch.get_num_threads()
    viewer = Viewer(trainer, ViewerConfig(port=0), live=True)
    record: dict = {
        "run_dir": str(trainer.run_dir),
        "port": viewer.port,
        "backend": trainer.config.backend,
        "threads_before": threads_before,
    }

    def threads_seen(tr, stats):  # on the training thread: torch's count and the cpu kernels'
        if tr.step == 3 and tr.config.backend == "cpu":
            from metegs.render.cpu_backend import load_extension

            record["threads_during"] = [torch.get_num_threads(), load_extension().get_num_threads()]

    trainer.step_hooks.append(threads_seen)
    helper = threading.Thread(target=_drive, args=(viewer.control, record), daemon=True)
    helper.start()
    try:
        trainer.train()  # in the main thread, as metegs-train does
        helper.join(timeout=60)
        viewer.training_finished()
        record["threads_after"] = torch.get_num_threads()
        record["final_step"] = trainer.step
        record["panel"] = viewer.train_md.content
        record["history_len"] = len(viewer.control.history)
        record["viewer_error"] = viewer.last_error
    finally:
        viewer.close()
    return record


@pytest.fixture(scope="session")
def live_run(tmp_path_factory) -> dict:
    """The record of the live training (steps seen while paused etc.) and its run folder."""
    root = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        root = root.parent  # shared by the xdist workers of this session
    done = root / "metegs-viewer-run.json"
    with FileLock(str(root / "metegs-viewer-run.lock")):
        if done.is_file():
            return json.loads(done.read_text())
        record = train_live(root / "metegs-viewer-run")
        done.write_text(json.dumps(record))
        return record
