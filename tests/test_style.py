"""The code style of pyproject.toml ([tool.ruff]): lint rules and `ruff format` hold on every source file, so that
the line length, which the lint rules leave to the formatter, cannot drift again."""

import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("ruff", reason="ruff is a dev dependency")

ROOT = Path(__file__).resolve().parents[1]
SOURCES = ["metegs", "tests", "benchmarks"]


def _ruff(*args: str, cwd: Path = ROOT) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "ruff", *args], cwd=cwd, capture_output=True, text=True, timeout=120)


def test_sources_pass_the_lint_rules():
    result = _ruff("check", *SOURCES)
    assert result.returncode == 0, result.stdout + result.stderr


def test_sources_are_formatted():
    result = _ruff("format", "--check", *SOURCES)
    assert result.returncode == 0, "run `ruff format metegs tests benchmarks`:\n" + result.stdout + result.stderr


def test_an_unformatted_file_is_caught(tmp_path):
    """The check reads the project's settings and fails on a line past its length."""
    (tmp_path / "pyproject.toml").write_text((ROOT / "pyproject.toml").read_text())
    (tmp_path / "long.py").write_text("x = [" + ", ".join(str(i) for i in range(60)) + "]\n")
    result = _ruff("format", "--check", "long.py", cwd=tmp_path)
    assert result.returncode != 0 and "long.py" in result.stdout + result.stderr
