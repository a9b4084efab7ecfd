"""Registry and entry-point plugin discovery, including a broken plugin that must not break the CLI."""

import sys
import textwrap
from importlib.metadata import EntryPoint

import pytest

import metegs.registry as reg
from metegs.errors import ConfigError, PluginError
from metegs.registry import PluginWarning, Registry, registry


@pytest.fixture
def fresh_plugins(monkeypatch):
    """Rediscover plugins with fake entry points; restore the registries afterwards."""
    reg.ensure_plugins_loaded()  # the built-ins register once per process: have them in what is restored
    saved = {k: dict(r._entries) for k, r in reg._REGISTRIES.items()}
    monkeypatch.setitem(reg._plugins_state, "loaded", False)
    monkeypatch.setattr(reg, "failed_plugins", {})

    def install(*eps):
        monkeypatch.setattr(reg.metadata, "entry_points", lambda group: [e for e in eps if e.group == group])
        monkeypatch.setitem(reg._plugins_state, "loaded", False)

    yield install
    for k, r in reg._REGISTRIES.items():
        r._entries = saved[k]


@pytest.fixture
def plugin_module(tmp_path, monkeypatch):
    """A real importable plugin module that registers a method and a parser."""
    (tmp_path / "fake_metegs_plugin.py").write_text(
        textwrap.dedent('''
        from metegs.registry import registry
        from metegs.engine.config import TrainConfig

        def fancy():
            """A plugin method."""
            return TrainConfig(method="fancy-plugin", max_steps=7)

        registry("method").register("fancy-plugin", fancy, description="a method from a plugin")
        registry("parser").register("fake-format", "fake_metegs_plugin:FakeParser")

        class FakeParser:
            priority = 5
            @staticmethod
            def can_parse(path):
                return (path / "fake.marker").exists()
    ''')
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    yield "fake_metegs_plugin"
    sys.modules.pop("fake_metegs_plugin", None)


def test_builtins_are_registered_lazily():
    names = registry("parser").names()
    assert {"colmap", "nerfstudio", "llff", "blender", "synthetic"} <= set(names)
    entry = registry("method").entry("3dgs")
    assert callable(entry.load())


def test_unknown_name_lists_the_available_ones():
    with pytest.raises(ConfigError, match="available: .*colmap"):
        registry("parser").get("no-such-format")


def test_duplicate_registration_is_an_error():
    r = Registry("weather")
    r.register("a", object())
    with pytest.raises(PluginError, match="already registered"):
        r.register("a", object())


def test_lazy_target_that_fails_to_import_names_it():
    r = Registry("weather")
    r.register("bad", "no_such_module_xyz:Thing")
    with pytest.raises(PluginError, match="no_such_module_xyz"):
        r.get("bad")


def test_entry_point_plugin_registers_components(fresh_plugins, plugin_module, tmp_path):
    fresh_plugins(EntryPoint("fancy", plugin_module, "metegs.plugins"))
    assert "fancy-plugin" in registry("method").names()
    assert registry("method").entry("fancy-plugin").source == "fancy"
    (tmp_path / "scene").mkdir()
    (tmp_path / "scene" / "fake.marker").write_text("")
    from metegs.data.parsers.base import detect_parser

    assert detect_parser(tmp_path / "scene") == "fake-format"


def test_broken_plugin_warns_with_its_name_and_does_not_break_the_cli(fresh_plugins, plugin_module, capsys):
    fresh_plugins(
        EntryPoint("broken-plugin", "no_such_module_for_metegs_xyz", "metegs.plugins"),
        EntryPoint("fancy", plugin_module, "metegs.plugins"),
    )
    from metegs.cli.train import parse_args

    with pytest.warns(PluginWarning, match="broken-plugin"):
        with pytest.raises(SystemExit) as exit_info:
            parse_args(["--help"])
    assert exit_info.value.code == 0
    out = capsys.readouterr().out
    assert "3dgs" in out and "fancy-plugin" in out
    assert "broken-plugin" in reg.failed_plugins


def test_plugin_raising_at_import_is_reported(fresh_plugins, tmp_path, monkeypatch):
    (tmp_path / "raising_metegs_plugin.py").write_text("raise RuntimeError('boom at import')\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    fresh_plugins(EntryPoint("raiser", "raising_metegs_plugin", "metegs.plugins"))
    with pytest.warns(PluginWarning, match="raiser.*boom at import"):
        names = registry("method").names()
    assert "3dgs" in names


def test_env_var_plugins(fresh_plugins, plugin_module, monkeypatch):
    fresh_plugins()
    monkeypatch.setenv("METEGS_PLUGINS", plugin_module)
    assert "fancy-plugin" in registry("method").names()
