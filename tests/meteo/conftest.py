"""Shared helpers of the meteorology tests: where the real records in ../shared live."""

from __future__ import annotations

from pathlib import Path

import pytest

import metegs.builtins  # noqa: F401  (registers the readers)

SHARED_METEO = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "meteo"


def shared_file(*parts: str) -> Path:
    """A real file of ../shared/data/meteo, or skip the test with the reason when ../shared is absent."""
    path = SHARED_METEO.joinpath(*parts)
    if not path.is_file():
        pytest.skip(f"real meteorological data not found at {path} (needs ../shared beside the repository)")
    return path
