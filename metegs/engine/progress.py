"""A rich progress bar for training: loss, PSNR, Gaussian count, it/s and ETA.

When the console is not a terminal (a log file, CI), a status line is printed every 5 % of the run instead.
"""

from __future__ import annotations

import time

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn


class TrainProgress:
    """Context manager around rich.Progress; a no-op when disabled."""

    def __init__(self, total: int, start: int = 0, enabled: bool = True, console: Console | None = None):
        self.total, self.start, self.enabled = total, start, enabled
        self.console = console or Console(stderr=True)
        self._progress: Progress | None = None
        self._ema: dict[str, float] = {}

    def __enter__(self) -> TrainProgress:
        self._t0, self._step0 = time.perf_counter(), self.start
        if self.enabled and self.console.is_terminal:
            self._progress = Progress(
                TextColumn("[bold]train"),
                BarColumn(),
                MofNCompleteColumn(),
                TextColumn("{task.fields[speed]:>6.2f} it/s"),
                TextColumn("{task.fields[stats]}"),
                TimeElapsedColumn(),
                TextColumn("ETA"),
                TimeRemainingColumn(),
                console=self.console,
                refresh_per_second=4,
            )
            self._progress.__enter__()
            self._task = self._progress.add_task("train", total=self.total, completed=self.start, speed=0.0, stats="")
        return self

    def update(self, step: int, stats: dict[str, float], num_gaussians: int) -> None:
        for key in ("loss", "psnr"):
            v = stats.get(key)
            if v is not None:
                self._ema[key] = v if key not in self._ema else 0.9 * self._ema[key] + 0.1 * v
        text = f"loss {self._ema.get('loss', 0):.4f}  PSNR {self._ema.get('psnr', 0):5.2f}  #G {num_gaussians}"
        if self._progress is None:
            every = max(1, self.total // 20)
            if self.enabled and (step % every == 0 or step == self.total):
                elapsed = time.perf_counter() - self._t0
                speed = (step - self._step0) / max(elapsed, 1e-9)
                eta = (self.total - step) / max(speed, 1e-9)
                self.console.print(
                    f"step {step}/{self.total}  {text}  {speed:.2f} it/s  ETA {eta:.0f} s", highlight=False
                )
            return
        task = self._progress.tasks[0]
        speed = task.speed or 0.0
        self._progress.update(self._task, completed=step, speed=speed, stats=text)

    def __exit__(self, *exc) -> None:
        if self._progress is not None:
            self._progress.__exit__(*exc)
