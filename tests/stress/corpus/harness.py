"""The corpus harness: `Case`, and `run_case`, which runs a command's console entry point in-process."""

from __future__ import annotations

import atexit
import importlib
import re
import shutil
import sys
import tempfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

COMMANDS = {
    "metegs-train": "metegs.cli.train",
    "metegs-eval": "metegs.cli.eval",
    "metegs-render": "metegs.cli.render",
    "metegs-meteo": "metegs.cli.meteo",
    "metegs-bench": "metegs.cli.bench",
    "metegs-synth": "metegs.cli.synth",
    "metegs-view": "metegs.cli.view",
    "metegs-process-images": "metegs.cli.process_images",
}
"""Console script -> module whose ``entrypoint()`` pyproject.toml installs for it."""

TINY_SCENE = [
    "--dataset.synthetic.width", "32", "--dataset.synthetic.height", "24",
    "--dataset.synthetic.num-views", "6", "--dataset.synthetic.num-points", "200", "--dataset.test-every", "3",
]  # fmt: skip
"""metegs-train flags of a synthetic scene small enough for a few-second run."""

QUIET_RUN = ["--max-steps", "4", "--no-progress", "--no-save-renders", "--eval-every", "0"]
"""metegs-train flags of a run that only has to finish."""


_TRAINED: dict[str, Path] = {}


def trained_run(folder: Path, method: str = "3dgs") -> Path:
    """A finished tiny run of ``method`` copied to ``folder/run`` (trained once per process, then copied)."""
    if method not in _TRAINED:
        from metegs.cli.train import main

        cache = Path(tempfile.mkdtemp(prefix="metegs-corpus-"))
        atexit.register(shutil.rmtree, cache, True)
        extra = ["--no-compare-baseline", "--weights.perceptual", "0"] if method != "3dgs" else []
        main([method, *TINY_SCENE, *QUIET_RUN, "--output-dir", str(cache), "--experiment-name", "run", *extra])
        _TRAINED[method] = cache / "synthetic" / method / "run"
    run = Path(folder) / "run"
    shutil.copytree(_TRAINED[method], run)
    return run


@dataclass
class Result:
    """What a command did: its exit code and what it printed."""

    code: int
    stdout: str
    stderr: str
    folder: Path
    """The case's temporary folder (inputs and outputs)."""


@dataclass
class Case:
    """One bad input or fault: build the input, run one command, expect one class of outcome."""

    id: str
    """Short unique name (the pytest id)."""
    command: str
    """Console script to run (a key of `COMMANDS`)."""
    argv: Callable[[Path], list[str]]
    """Builds the input in the given folder and returns the command's arguments."""
    expect: Literal["clear", "correct"]
    """``clear``: exit 2 and one error line matching `match`; ``correct``: exit 0 and `check` passes."""
    match: str = ""
    """Regex the error line must contain (the file or field it names); required for ``clear``."""
    check: Callable[[Result], None] | None = None
    """Raises AssertionError when the result is wrong (required for ``correct``; for ``clear``, what must hold after
    the error, e.g. that no code ran and nothing was lost)."""
    marks: list = field(default_factory=list)
    """pytest marks of the case (e.g. ``pytest.mark.slow``)."""

    def __post_init__(self):
        if self.command not in COMMANDS:
            raise ValueError(f"{self.id}: unknown command {self.command!r}")
        if self.expect == "clear" and not self.match:
            raise ValueError(f"{self.id}: a 'clear' case names what the error must mention (match)")
        if self.expect == "correct" and self.check is None:
            raise ValueError(f"{self.id}: a 'correct' case needs a check")


def run_command(command: str, args: list[str], capsys) -> tuple[int, str, str]:
    """Run ``command``'s console entry point with ``args`` in this process: (exit code, stdout, stderr)."""
    entrypoint = importlib.import_module(COMMANDS[command]).entrypoint
    saved = sys.argv
    sys.argv = [command, *args]
    code = 0
    try:
        entrypoint()
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    finally:
        sys.argv = saved
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def run_case(case: Case, folder: Path, capsys, monkeypatch) -> Result:
    """Build ``case``'s input in ``folder``, run it there, and assert the outcome its class promises."""
    monkeypatch.chdir(folder)
    args = [str(a) for a in case.argv(folder)]
    capsys.readouterr()  # what building the input printed
    code, out, err = run_command(case.command, args, capsys)
    result = Result(code, out, err, folder)
    shown = f"{case.command} {' '.join(args)}\nexit {code}\nstderr:\n{err[-3000:]}"
    assert "Traceback" not in err, f"traceback:\n{shown}"
    if case.expect == "clear":
        assert code == 2, f"expected a clear error (exit 2):\n{shown}"
        lines = [ln for ln in err.splitlines() if ln.startswith("error:") or "error" in ln.lower()]
        assert lines, f"no error line:\n{shown}"
        assert re.search(case.match, " ".join(err.split())), f"the error does not name {case.match!r}:\n{shown}"
    else:
        assert code == 0, f"expected a correct result (exit 0):\n{shown}"
    if case.check is not None:
        case.check(result)
    return result
