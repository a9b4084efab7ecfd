"""Fit a training command into a wall-clock budget (`--budget-minutes`): a few timed steps at each image size choose
the largest size whose run fits, and the number of steps."""

from __future__ import annotations

import gc
import math
import time
from dataclasses import dataclass, replace

from metegs.data.dataset import Dataset, longest_side
from metegs.data.scene import SceneData
from metegs.engine.config import TrainConfig
from metegs.errors import ConfigError
from metegs.render.cpu_backend import thread_split

GROWTH = 2.0
"""Mean cost of a run's steps over the cost of its first steps (the Gaussians densify): 1.2-2.4 measured on real
captures and the built-in scene (docs/getting-started.md, "A time budget"): plans err early on real captures."""
LARGEST_SIDE = 1600
"""The largest longer side a budget may choose (nerfstudio's convention)."""
SMALLEST_SIDE = 100
"""The smallest longer side a budget may choose."""
MIN_STEP_SHARE = 0.5
"""A size is kept while at least this share of `max_steps` fits; below it the next smaller size is tried."""
LEAST_STEP_SHARE = 0.1
"""Below this share of `max_steps` at the smallest size the budget is refused as too short."""
WARM_STEPS = 2
TIMED_STEPS = 8


@dataclass(frozen=True)
class Trial:
    """What one image size costs, measured on the command's runs."""

    downscale: int
    width: int
    height: int
    runs: int
    """Training runs of the command (the method's, then its baseline and blind runs)."""
    step_s: float
    """Estimated mean seconds of a training step, all the command's runs together."""
    fixed_s: float
    """Seconds besides the steps: setting each run up, and every evaluation."""

    def steps_within(self, seconds: float) -> int:
        """The steps that ``seconds`` hold at this size."""
        return max(0, math.floor((seconds - self.fixed_s) / self.step_s))

    def seconds(self, steps: int) -> float:
        return self.fixed_s + steps * self.step_s


@dataclass(frozen=True)
class BudgetPlan:
    """The image size and steps a budget chose, and why."""

    config: TrainConfig
    """The run's config with the chosen size and steps (and no budget left to plan)."""
    text: str
    """The decision, as printed and saved in decisions.json."""


def downscales(scene: SceneData, config: TrainConfig) -> list[int]:
    """Power-of-two downscales a budget may choose, largest image first: the configured one alone when the size is
    set (`--dataset.downscale` or `--dataset.auto-max-side`)."""
    options = config.dataset
    if options.downscale is not None or options.auto_max_side is not None:
        return [Dataset._downscale(scene.cameras, options, "cpu")]
    longest = longest_side(scene.cameras)
    found = [d for d in (2**k for k in range(12)) if SMALLEST_SIDE <= longest / d <= LARGEST_SIDE]
    return found or [1]  # none: the capture is smaller than the smallest side, so its own size


def at_downscale(config: TrainConfig, scene: SceneData, d: int) -> TrainConfig:
    """``config`` loading ``scene``'s images at downscale ``d`` (as a longer side, so the size stays automatic)."""
    if config.dataset.downscale is not None:
        return config
    return replace(config, dataset=replace(config.dataset, auto_max_side=math.ceil(longest_side(scene.cameras) / d)))


def timed_steps(trainer, warm: int = WARM_STEPS, timed: int = TIMED_STEPS) -> float:
    """Median seconds of ``trainer``'s first training steps after ``warm`` untimed ones (the trainer is spent)."""
    order = trainer._view_order()
    times = []
    with thread_split(trainer.config.backend, trainer.config.torch_threads):
        for i in range(warm + timed):
            t0 = time.perf_counter()
            trainer.train_step(next(order))
            trainer.step += 1
            if i >= warm:
                times.append(time.perf_counter() - t0)
    return sorted(times)[len(times) // 2]


def companion_configs(trainer) -> list[TrainConfig]:
    """The runs the command trains after ``trainer``'s: the 3dgs baseline and, with clean references, the blind run
    (`compare_baseline`)."""
    from metegs.engine.compare import baseline_config

    config = trainer.config
    if not getattr(config, "compare_baseline", False):
        return []
    runs = [baseline_config(config)]
    if getattr(trainer, "use_clean", False):
        runs.append(replace(config, clean_supervision=False, compare_baseline=False))
    return runs


def run_costs(trainer, evals: int) -> tuple[float, float]:
    """(seconds a step, seconds of ``evals`` evaluations) of ``trainer``'s run, growth included; the trainer is spent."""
    step_s = timed_steps(trainer) * GROWTH
    t0 = time.perf_counter()
    trainer.record_eval(quick=True)
    return step_s, evals * (time.perf_counter() - t0) * GROWTH


def measure(trainer_cls, config: TrainConfig, scene: SceneData, d: int) -> Trial:
    """Set the command's runs up at downscale ``d`` (each is set up again after planning, so that counts) and time
    their first steps and one evaluation."""
    from metegs.engine.trainer import Trainer

    trial_config = replace(at_downscale(config, scene, d), budget_minutes=None, progress=False, viewer=False)
    evals = (math.ceil(1 / config.eval_every) if config.eval_every > 0 else 0) + 1
    t0 = time.perf_counter()
    trainer = trainer_cls(trial_config, scene=scene)
    costs = [(time.perf_counter() - t0, *run_costs(trainer, evals))]
    width, height = trainer.dataset.sizes[0]
    companions = [(Trainer if c.method == "3dgs" else trainer_cls, c) for c in companion_configs(trainer)]
    del trainer
    for cls, run_config in companions:
        gc.collect()
        t0 = time.perf_counter()
        trainer = cls(run_config, scene=scene)
        costs.append((time.perf_counter() - t0, *run_costs(trainer, evals)))
        del trainer
    gc.collect()
    built_s, step_s, eval_s = (sum(c) for c in zip(*costs, strict=True))
    return Trial(d, width, height, len(costs), step_s, built_s + eval_s)


def plan_budget(trainer_cls, config: TrainConfig, scene: SceneData, spent_s: float) -> BudgetPlan:
    """The largest image size whose command fits ``config.budget_minutes`` (less ``spent_s`` already spent) with at
    least `MIN_STEP_SHARE` of ``config.max_steps``, and the steps that fit (at most ``max_steps``)."""
    budget_s = config.budget_minutes * 60.0
    if config.load_checkpoint is not None:
        raise ConfigError(
            "--budget-minutes chooses a new run's image size and steps; a resumed run keeps its checkpoint's "
            "(--max-steps sets where it ends)"
        )
    started = time.perf_counter()
    half = math.ceil(MIN_STEP_SHARE * config.max_steps)

    def elapsed() -> float:
        return spent_s + time.perf_counter() - started

    def left() -> float:
        return budget_s - elapsed()

    candidates = downscales(scene, config)
    tried: list[Trial] = []
    steps = 0
    for d in candidates:
        if tried and d != candidates[-1]:  # a step costs at least its share of a larger image's: skip what cannot fit
            share = (tried[-1].downscale / d) ** 2
            if left() < share * tried[-1].seconds(half):
                continue
        tried.append(measure(trainer_cls, config, scene, d))
        steps = min(config.max_steps, tried[-1].steps_within(left()))
        if steps >= half:
            break
    chosen = tried[-1]
    if steps < LEAST_STEP_SHARE * config.max_steps:
        which = "the smallest size" if len(candidates) > 1 else "the size set"
        raise ConfigError(
            f"--budget-minutes {config.budget_minutes:g} is too short: at {chosen.width}x{chosen.height} px, {which}, "
            f"{steps} of {config.max_steps} steps fit; {half} steps need about "
            f"{(elapsed() + chosen.seconds(half)) / 60:.1f} minutes (lower --max-steps, or allow more minutes)"
        )
    planned = at_downscale(config, scene, chosen.downscale)
    planned = replace(planned, max_steps=steps, budget_minutes=None)
    others = ", ".join(f"{t.width}x{t.height} {t.seconds(config.max_steps) / 60:.1f} min" for t in tried[:-1])
    text = (
        f"{chosen.width}x{chosen.height} px, {steps} steps in about "
        f"{(elapsed() + chosen.seconds(steps)) / 60:.1f} of {config.budget_minutes:g} "
        f"minutes (the first steps of {chosen.runs} run{'s' if chosen.runs > 1 else ''} timed at "
        f"{1000 * chosen.step_s / GROWTH:.0f} ms"
        + (f"; {config.max_steps} steps would take: {others}" if others else "")
        + (f"; cut from {config.max_steps} to fit" if steps < config.max_steps else "")
        + "); rerun with these flags: "
        + (f"--dataset.auto-max-side {planned.dataset.auto_max_side} " if config.dataset.downscale is None else "")
        + f"--max-steps {steps}"
    )
    return BudgetPlan(planned, text)
