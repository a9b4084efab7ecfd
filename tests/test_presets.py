"""Every YAML preset in configs/ loads, applies every value it sets, and stays a small override of a named method."""

from pathlib import Path

import pytest
import yaml

from metegs.cli.train import method_configs, parse_args

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
PRESETS = sorted(CONFIGS.glob("*.yaml"))
COMMON_CASES = ("rain-only", "fog-only", "rain-fog", "blind-real-capture", "quick-preview", "high-quality")
GENERIC_METHODS = ("3dgs", "metegs-full")
"""Presets that name no method are meant for any: they are applied to these."""
MAX_VALUES = 8
"""A preset is a small override: at most this many values."""


def leaves(tree: dict, prefix: str = "") -> dict[str, object]:
    """Flattened ``a.b.c -> value`` of a nested mapping."""
    out = {}
    for key, value in tree.items():
        path = f"{prefix}{key}"
        out.update(leaves(value, path + ".") if isinstance(value, dict) else {path: value})
    return out


def lookup(config, path: str):
    for part in path.split("."):
        config = getattr(config, part.replace("-", "_"))
    return config


def test_the_common_cases_have_presets():
    names = {p.stem for p in PRESETS}
    assert set(COMMON_CASES) <= names, sorted(set(COMMON_CASES) - names)


@pytest.mark.parametrize("preset", PRESETS, ids=lambda p: p.name)
def test_preset_loads_and_applies_every_value(preset, request):
    text = preset.read_text()
    if "snow" in (yaml.safe_load(text).get("weather") or ()):
        request.getfixturevalue(
            "snow_plugin"
        )  # the preset needs the example plugin (pip install ./plugins/metegs-snow)
    assert text.startswith("#") and "metegs-train" in text.split("\n\n")[0], "say what it is for and how to run it"
    overrides = yaml.safe_load(text)
    method = overrides.pop("method", None)
    assert method is None or method in method_configs(), f"{preset.name}: unknown method {method!r}"
    values = leaves(overrides)
    assert 0 < len(values) + (method is not None) <= MAX_VALUES
    runs = [[]] if method is not None else [[m] for m in GENERIC_METHODS]
    for extra in runs:
        cfg = parse_args([*extra, "--config", str(preset)])
        assert cfg.method == (method or extra[0]) and cfg.max_steps > 0
        for path, value in values.items():
            got = lookup(cfg, path)
            assert (list(got) if isinstance(got, tuple) else got) == value, (preset.name, path)


def test_command_line_flags_win_over_a_preset():
    cfg = parse_args(["--config", str(CONFIGS / "rain-fog.yaml"), "--weather", "rain-streaks", "--max-steps", "7"])
    assert cfg.method == "metegs-full" and cfg.weather == ("rain-streaks",) and cfg.max_steps == 7
