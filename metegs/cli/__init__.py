"""Thin command-line entry points."""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any

from rich.console import Console

from metegs.errors import MetegsError

THREAD_ENV = {"GOMP_SPINCOUNT": "2000"}
"""OpenMP settings of every metegs command, unless the user set them. torch's OpenMP threads spin after each
parallel op before they sleep; by default for 300,000 rounds, which on 2 cores takes the core that the `cpu`
rasteriser's second thread needs (its kernels run on their own pool) and makes every parallel region wait for a
thread a browser showing the live viewer has descheduled. With 2000 they sleep after a few microseconds
(docs/benchmark.md has the measurements). libgomp reads the variable once, when torch loads: this module is
imported before any command module loads torch."""


def thread_env() -> dict[str, str]:
    """The `THREAD_ENV` settings the user has not set in the environment."""
    return {k: v for k, v in THREAD_ENV.items() if k not in os.environ}


os.environ.update(thread_env())  # no effect on a process that loaded torch before importing metegs.cli


def run_cli(main: Callable[[], Any]) -> None:
    """Run a command; a MetegsError (bad input or configuration) becomes one clear line and exit code 2."""
    try:
        main()
    except MetegsError as exc:
        Console(stderr=True, soft_wrap=True).print(f"[bold red]error:[/] {exc}", highlight=False)
        raise SystemExit(2) from None
