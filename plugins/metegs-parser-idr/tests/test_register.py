"""The parser reaches metegs through its entry point only, and metegs then detects the format by itself."""

import sys
from importlib.metadata import EntryPoint
from pathlib import Path

import metegs.registry as reg
import pytest
from idr_helpers import write_scene
from metegs.data.config import DatasetConfig
from metegs.data.parsers.base import detect_parser, parse_scene
from metegs.registry import registry


@pytest.fixture
def rediscover(monkeypatch):
    """Rediscover plugins with the given entry points (none installed otherwise); restore the registries after."""
    reg.ensure_plugins_loaded()  # the built-ins register once per process: have them in what is restored
    saved = {k: dict(r._entries) for k, r in reg._REGISTRIES.items()}
    monkeypatch.setattr(reg, "failed_plugins", {})
    monkeypatch.delenv("METEGS_PLUGINS", raising=False)
    sys.modules.pop("metegs_parser_idr.register", None)
    registry("parser")._entries.pop("idr", None)

    def install(*eps):
        monkeypatch.setattr(reg.metadata, "entry_points", lambda group: [e for e in eps if e.group == group])
        monkeypatch.setitem(reg._plugins_state, "loaded", False)

    yield install
    sys.modules.pop("metegs_parser_idr.register", None)
    for k, r in reg._REGISTRIES.items():
        r._entries = saved[k]


def test_the_package_declares_the_entry_point():
    text = (Path(__file__).resolve().parents[1] / "pyproject.toml").read_text()
    section = text.split('[project.entry-points."metegs.plugins"]', 1)[1].split("\n[", 1)[0]
    assert [line for line in section.splitlines() if "=" in line] == [
        'metegs-parser-idr = "metegs_parser_idr.register"'
    ]


def test_the_format_is_detected_only_with_the_plugin(rediscover, tmp_path):
    write_scene(tmp_path, views=4, masks=False)
    rediscover()
    with pytest.raises(Exception, match="cannot tell the scene format"):
        detect_parser(tmp_path)
    rediscover(EntryPoint("metegs-parser-idr", "metegs_parser_idr.register", "metegs.plugins"))
    assert detect_parser(tmp_path) == "idr"
    assert registry("parser").entry("idr").source == "metegs-parser-idr"
    scene = parse_scene(tmp_path, None, DatasetConfig())
    assert scene.parser == "idr" and len(scene) == 4
