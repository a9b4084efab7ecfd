"""Thin command-line entry points."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from rich.console import Console

from metegs.errors import MetegsError

INTERRUPTED_EXIT_CODE = 130
"""Exit code after Ctrl-C (128 + SIGINT), as shells report it."""


def run_cli(main: Callable[[], Any]) -> None:
    """Run a command; bad input or configuration (a MetegsError) and a failed read or write (an OSError, with its
    path) become one clear line and exit code 2; Ctrl-C stops with one line (and the error's resume advice)."""
    console = Console(stderr=True, soft_wrap=True)
    try:
        main()
    except MetegsError as exc:
        console.print(f"[bold red]error:[/] {exc}", highlight=False)
        raise SystemExit(getattr(exc, "exit_code", 2)) from None
    except OSError as exc:
        console.print(f"[bold red]error:[/] {describe_os_error(exc)}", highlight=False)
        raise SystemExit(2) from None
    except KeyboardInterrupt:
        console.print("[bold yellow]interrupted[/] (Ctrl-C)", highlight=False)
        raise SystemExit(INTERRUPTED_EXIT_CODE) from None


def describe_os_error(exc: OSError) -> str:
    """``path: what went wrong`` of a failed file operation (both paths of a rename)."""
    where = " -> ".join(str(p) for p in (exc.filename, exc.filename2) if p is not None)
    what = exc.strerror or str(exc) or type(exc).__name__
    return f"{where}: {what}" if where else what
