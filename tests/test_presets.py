"""Every YAML preset in configs/ applies cleanly to the method it is meant for."""

from pathlib import Path

import pytest

from metegs.cli.train import parse_args

PRESETS = sorted((Path(__file__).resolve().parents[1] / "configs").glob("*.yaml"))


def test_there_are_presets():
    assert PRESETS


@pytest.mark.parametrize("preset", PRESETS, ids=lambda p: p.name)
def test_preset_loads(preset):
    cfg = parse_args(["3dgs", "--config", str(preset)])
    assert cfg.method == "3dgs" and cfg.max_steps > 0
