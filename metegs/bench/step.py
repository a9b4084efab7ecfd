"""Training-step benchmark: each method's own training step on the synthetic scene, per backend.

The model is the scene's point cloud resampled to the requested number of Gaussians (jittered by
a fraction of the nearest-neighbour spacing, scales from the nearest-neighbour distances as at
initialisation, full SH degree), so footprints are those of a real early-training model.
A step is the trainer's `train_step` held at mid-run on a step where no refinement, opacity reset or
extra points are due: for `3dgs` render + `(1-λ)·L1 + λ·(1-SSIM)` + backward + Adam (+ the
densification statistics); for `metegs-full` as `metegs-train metegs-full` runs it on the built-in
scene (rain and fog synthesised, the weather branch through the GTN, the clean branch); `metegs-full-blind`
the same without clean references (no clean branch), as on a user's capture. Each record also times the
rasteriser alone on the same model (`raster_ms`), the floor of a step.
"""

from __future__ import annotations

import statistics
import time
from dataclasses import dataclass, replace

import numpy as np
import torch

from metegs.bench.memory import PeakMemory, rss_mb, sync
from metegs.engine.config import TrainConfig
from metegs.engine.optim import make_optimizers
from metegs.engine.trainer import Trainer
from metegs.errors import ConfigError
from metegs.gaussians.model import GaussianModel
from metegs.render.cpu_backend import thread_split

METHODS = ("3dgs", "metegs-full", "metegs-full-blind")
"""Methods whose steps the benchmark can time (`metegs-full-blind`: without the clean references, as on a user's
capture: no clean branch)."""


@dataclass
class StepRecord:
    """One method and backend at one model size."""

    method: str
    backend: str
    num_gaussians: int
    width: int
    height: int
    step_ms: float
    """Median time of a full training step."""
    raster_ms: float
    """Median time of the rasteriser alone on the same model and views: the scene's render and its backward."""
    iterations_per_s: float
    rss_before_mb: float
    """Resident memory of the process before the steps (torch, the dataset, the model)."""
    step_peak_mb: float
    """Peak memory of the steps above ``rss_before_mb``."""
    torch_threads: int
    """Threads of torch's own ops (loss, Adam, autograd) during the steps."""


def resampled_model(
    points: np.ndarray, colors: np.ndarray, n: int, sh_degree: int, seed: int, device: torch.device | str = "cpu"
) -> GaussianModel:
    """``n`` Gaussians on ``device`` drawn from a point cloud [P, 3] with jitter (no densification needed)."""
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, len(points), n)
    spread = np.linalg.norm(points.max(0) - points.min(0)) / max(len(points), 1) ** (1 / 3)
    pts = points[idx] + rng.normal(0, 0.1 * spread, (n, 3)).astype(points.dtype)
    model = GaussianModel.from_points(pts, colors[idx], sh_degree=sh_degree, device=device)
    model.active_sh_degree = sh_degree
    return model


def hold_at_mid_run(trainer: Trainer) -> None:
    """Put ``trainer`` at mid-run on a step where no refinement, opacity reset or extra points are due (its
    `train_step` does not advance the step, so every timed step is the same kind)."""
    step = trainer.config.max_steps // 2
    every = getattr(trainer.densifier, "every", 0) or 0
    reset = getattr(trainer.densifier, "reset_every", 0) or 0
    while (every and step % every == 0) or (reset and step % reset == 0):
        step += 1
    trainer.step = step
    if getattr(trainer, "extra_points", None) is not None:
        trainer.extra_points.done = True


def method_config(config: TrainConfig, method: str) -> TrainConfig:
    """``config``'s device, threads and dataset for ``method`` (`3dgs`: ``config`` itself)."""
    if method == "3dgs":
        return config
    if method in ("metegs-full", "metegs-full-blind"):
        from metegs.methods import metegs_full

        shared = ("device", "threads", "torch_threads", "dataset", "seed", "backend")
        return replace(
            metegs_full(),
            compare_baseline=False,
            clean_supervision=method == "metegs-full",
            **{k: getattr(config, k) for k in shared},
        )
    raise ConfigError(f"--methods: unknown method {method!r}; expected one of {', '.join(METHODS)}")


def run_step_benchmark(
    config: TrainConfig,
    sizes: list[int],
    backends: list[str],
    repeats: int = 10,
    progress=None,
    methods: tuple[str, ...] = ("3dgs",),
) -> list[StepRecord]:
    """Time the training steps of every method and backend at every model size."""
    records = []
    for method in methods:
        for backend in backends:
            trainer = replace(method_config(config, method), backend=backend, progress=False).setup()
            with thread_split(trainer.config.backend, config.torch_threads):
                records += _time_sizes(trainer, method, sizes, repeats, progress)
    return records


def _time_sizes(trainer: Trainer, method: str, sizes: list[int], repeats: int, progress) -> list[StepRecord]:
    """Records of ``trainer``'s steps at each model size."""
    config, scene, views, records = trainer.config, trainer.scene, trainer.dataset.train_indices, []
    hold_at_mid_run(trainer)
    for n in sizes:
        trainer.model = resampled_model(
            scene.points, scene.point_colors, n, trainer.model.max_sh_degree, 0, device=trainer.device
        )
        trainer.optimizers = make_optimizers(trainer.model.params, config.optim, trainer.extent)
        times = []
        for i in range(repeats + 1):
            t0 = time.perf_counter()
            trainer.train_step(views[i % len(views)])
            sync(trainer.device)
            if i > 0:  # the first step warms up
                times.append(time.perf_counter() - t0)
        raster = _raster_ms(trainer, views, repeats)
        # memory in steps of their own: on CPU a thread samples the resident set every 0.5 ms, which would
        # take CPU time and the GIL from the timed steps
        before = rss_mb()
        with PeakMemory(trainer.device) as mem:
            for i in range(min(repeats, 3)):
                trainer.train_step(views[i % len(views)])
        ms = statistics.median(times) * 1e3
        W, H = int(trainer.dataset.cameras.width[0]), int(trainer.dataset.cameras.height[0])
        records.append(
            StepRecord(
                method, config.backend, n, W, H, ms, raster, 1e3 / ms, before, mem.peak_mb, torch.get_num_threads()
            )
        )
        if progress is not None:
            progress(records[-1])
    return records


def _raster_ms(trainer: Trainer, views: list[int], repeats: int) -> float:
    """Median ms of ``trainer``'s scene render of a training view and its backward (of a fixed random weighting of
    the colours), after one warm-up: the rasteriser's share of a step. Weights and cleared gradients are prepared
    outside the timed part, as a step's optimiser clears them."""
    times = []
    for i in range(repeats + 1):
        index = views[i % len(views)]
        bg = trainer.background(training=True)
        W, H = int(trainer.dataset.cameras.width[index]), int(trainer.dataset.cameras.height[index])
        grad = torch.rand((H, W, 3), generator=torch.Generator().manual_seed(i)).to(trainer.device)
        for p in trainer.model.params.values():
            p.grad = None
        sync(trainer.device)
        t0 = time.perf_counter()
        out = trainer.render(index, background=bg)
        out.rgb.backward(grad.to(out.rgb.dtype))
        sync(trainer.device)
        if i > 0:
            times.append(time.perf_counter() - t0)
    for p in trainer.model.params.values():
        p.grad = None
    return statistics.median(times) * 1e3
