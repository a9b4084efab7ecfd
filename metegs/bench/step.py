"""Training-step benchmark: render, loss, backward and Adam on the synthetic scene, per backend.

The model is the scene's point cloud resampled to the requested number of Gaussians (jittered by
a fraction of the nearest-neighbour spacing, scales from the nearest-neighbour distances as at
initialisation, full SH degree), so footprints are those of a real early-training model.
Densification is not run: a step is render + `(1-λ)·L1 + λ·(1-SSIM)` + backward + Adam.
"""

from __future__ import annotations

import statistics
import time
from dataclasses import dataclass, replace

import numpy as np
import torch

from metegs.bench.memory import PeakMemory, rss_mb
from metegs.engine.config import TrainConfig
from metegs.engine.optim import make_optimizers
from metegs.engine.trainer import Trainer
from metegs.gaussians.model import GaussianModel
from metegs.render.cpu_backend import thread_split


@dataclass
class StepRecord:
    """One backend at one model size."""

    backend: str
    num_gaussians: int
    width: int
    height: int
    step_ms: float
    """Median time of a full training step."""
    iterations_per_s: float
    rss_before_mb: float
    """Resident memory of the process before the steps (torch, the dataset, the model)."""
    step_peak_mb: float
    """Peak memory of the steps above ``rss_before_mb``."""
    torch_threads: int
    """Threads of torch's own ops (loss, Adam, autograd) during the steps."""


def resampled_model(points: np.ndarray, colors: np.ndarray, n: int, sh_degree: int, seed: int) -> GaussianModel:
    """``n`` Gaussians drawn from a point cloud [P, 3] with jitter (no densification needed)."""
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, len(points), n)
    spread = np.linalg.norm(points.max(0) - points.min(0)) / max(len(points), 1) ** (1 / 3)
    pts = points[idx] + rng.normal(0, 0.1 * spread, (n, 3)).astype(points.dtype)
    model = GaussianModel.from_points(pts, colors[idx], sh_degree=sh_degree)
    model.active_sh_degree = sh_degree
    return model


def _train_step(trainer: Trainer, index: int) -> None:
    """Render, loss, backward and Adam (no densification)."""
    bg = trainer.background(training=True)
    out = trainer.render(index, background=bg)
    trainer.loss_fn(out.rgb, trainer.target(index, bg)).backward()
    for opt in trainer.optimizers.values():
        opt.step()
        opt.zero_grad(set_to_none=True)


def run_step_benchmark(
    config: TrainConfig, sizes: list[int], backends: list[str], repeats: int = 10, progress=None
) -> list[StepRecord]:
    """Time full training steps of every backend at every model size."""
    records = []
    for backend in backends:
        trainer = Trainer(replace(config, backend=backend, progress=False))
        with thread_split(trainer.config.backend, config.torch_threads):
            records += _time_sizes(trainer, sizes, repeats, progress)
    return records


def _time_sizes(trainer: Trainer, sizes: list[int], repeats: int, progress) -> list[StepRecord]:
    """Records of ``trainer``'s steps at each model size."""
    config, scene, views, records = trainer.config, trainer.scene, trainer.dataset.train_indices, []
    for n in sizes:
        trainer.model = resampled_model(scene.points, scene.point_colors, n, trainer.model.max_sh_degree, 0)
        trainer.optimizers = make_optimizers(trainer.model.params, config.optim, trainer.extent)
        times = []
        for i in range(repeats + 1):
            t0 = time.perf_counter()
            _train_step(trainer, views[i % len(views)])
            if i > 0:  # the first step warms up
                times.append(time.perf_counter() - t0)
        # memory in steps of their own: on CPU a thread samples the resident set every 0.5 ms, which would
        # take CPU time and the GIL from the timed steps
        before = rss_mb()
        with PeakMemory(trainer.device) as mem:
            for i in range(min(repeats, 3)):
                _train_step(trainer, views[i % len(views)])
        ms = statistics.median(times) * 1e3
        W, H = int(trainer.dataset.cameras.width[0]), int(trainer.dataset.cameras.height[0])
        records.append(StepRecord(config.backend, n, W, H, ms, 1e3 / ms, before, mem.peak_mb, torch.get_num_threads()))
        if progress is not None:
            progress(records[-1])
    return records
