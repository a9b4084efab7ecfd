"""The live viewer's hook in the training loop: pause / resume / single steps, statistics, and copies of the scene
taken between steps (so that the viewer never reads Gaussians the optimiser is changing)."""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

from metegs.viewer.render import Snapshot

MAX_HISTORY = 100_000
"""Most per-step records kept for the curves (older ones are thinned)."""


@dataclass
class StepRecord:
    """One training step as the curves show it."""

    step: int
    loss: float
    psnr: float
    num_gaussians: int


class TrainingControl:
    """``Trainer.step_hooks`` entry: called after every step in the training thread.

    It records the step, hands the viewer a `Snapshot` when one was asked for, and blocks while paused
    (serving snapshots meanwhile). ``step_once()`` lets exactly one more step run while paused.
    """

    def __init__(self):
        self._cond = threading.Condition()
        self.paused = False
        self._steps_allowed = 0
        self._closed = False
        self._want_snapshot = False
        self.snapshot: Snapshot | None = None
        """The latest copy of the scene handed over by the training thread."""
        self.history: list[StepRecord] = []
        self.step = 0
        self.num_gaussians = 0
        self.running = False
        """True between the first step and `finished()`."""
        self._rate_window: list[tuple[int, float]] = []
        self._paused_since: float | None = None
        self._paused_total = 0.0

    # --- called from the training thread --------------------------------------------------------
    def __call__(self, trainer, stats: dict[str, float]) -> None:
        now = time.perf_counter()
        self.running = True
        self.step, self.num_gaussians = trainer.step, len(trainer.model)
        self.history.append(
            StepRecord(
                trainer.step,
                float(stats.get("loss", float("nan"))),
                float(stats.get("psnr", float("nan"))),
                len(trainer.model),
            )
        )
        if len(self.history) > MAX_HISTORY:
            self.history = self.history[::2]
        self._rate_window.append((trainer.step, now - self._paused_total))
        if len(self._rate_window) > 200:
            del self._rate_window[:100]
        self._serve(trainer)
        with self._cond:
            if self._steps_allowed > 0:
                self._steps_allowed -= 1
                return
            while self.paused and self._steps_allowed == 0 and not self._closed:
                if self._paused_since is None:
                    self._paused_since = time.perf_counter()
                self._cond.wait(0.05)
                if self._want_snapshot:
                    self._cond.release()
                    try:
                        self._serve(trainer)
                    finally:
                        self._cond.acquire()
            if self._paused_since is not None:
                self._paused_total += time.perf_counter() - self._paused_since
                self._paused_since = None
            if self._steps_allowed > 0:
                self._steps_allowed -= 1

    def _serve(self, trainer) -> None:
        if self._want_snapshot:
            self.snapshot = Snapshot.of(trainer.model, trainer.step)
            self._want_snapshot = False

    # --- called from the viewer -------------------------------------------------------------------
    def request_snapshot(self) -> None:
        """Ask for a copy of the scene at the next step boundary (or at once while paused)."""
        with self._cond:
            self._want_snapshot = True
            self._cond.notify_all()

    @property
    def snapshot_pending(self) -> bool:
        return self._want_snapshot

    @property
    def blocked(self) -> bool:
        """True while the training thread waits in the hook (paused)."""
        return self._paused_since is not None

    def pause(self) -> None:
        with self._cond:
            self.paused = True
            self._steps_allowed = 0
            self._cond.notify_all()

    def resume(self) -> None:
        with self._cond:
            self.paused = False
            self._steps_allowed = 0
            self._cond.notify_all()

    def step_once(self) -> None:
        """While paused: let one more training step run."""
        with self._cond:
            if self.paused:
                self._steps_allowed += 1
                self._cond.notify_all()

    def finished(self) -> None:
        """Training is over: never block again."""
        with self._cond:
            self.running = False
            self._closed = True
            self.paused = False
            self._cond.notify_all()

    def iterations_per_second(self, window_s: float = 5.0) -> float:
        """Steps per second over the last ``window_s`` of unpaused training."""
        w = self._rate_window
        if len(w) < 2:
            return 0.0
        last_step, last_t = w[-1]
        first = next(((s, t) for s, t in w if last_t - t <= window_s), w[-2])
        if first[0] == last_step:
            first = w[-2]
        dt = last_t - first[1]
        return (last_step - first[0]) / dt if dt > 0 else 0.0
