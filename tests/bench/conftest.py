"""Fixtures of the benchmark tests."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parents[2] / "benchmarks"


@pytest.fixture
def benchmark_script(monkeypatch):
    """``load(name)``: the module of ``benchmarks/<name>.py`` (the scripts are not a package; they import each other
    as siblings, so ``benchmarks/`` is on the path while a test runs)."""
    monkeypatch.syspath_prepend(str(BENCHMARKS))

    def load(name: str):
        spec = importlib.util.spec_from_file_location(name, BENCHMARKS / f"{name}.py")
        module = importlib.util.module_from_spec(spec)
        sys.modules[spec.name] = module  # dataclasses of the script look their module up
        spec.loader.exec_module(module)
        return module

    return load
