"""Thin command-line entry points."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from rich.console import Console

from metegs.errors import MetegsError


def run_cli(main: Callable[[], Any]) -> None:
    """Run a command; a MetegsError (bad input or configuration) becomes one clear line and exit code 2."""
    try:
        main()
    except MetegsError as exc:
        Console(stderr=True, soft_wrap=True).print(f"[bold red]error:[/] {exc}", highlight=False)
        raise SystemExit(2) from None
