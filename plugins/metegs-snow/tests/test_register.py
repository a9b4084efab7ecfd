"""`snow` reaches metegs through the entry point (or METEGS_PLUGINS) only, once, and builds by name."""

import sys
from importlib.metadata import EntryPoint
from pathlib import Path

import metegs.registry as reg
import pytest
from metegs.registry import PluginWarning, registry
from metegs.weather import build_weather_models
from snow_helpers import scene, theta

from metegs_snow.model import Snow


@pytest.fixture
def rediscover(monkeypatch):
    """Rediscover plugins with the given entry points (none installed otherwise); restore the registries after."""
    reg.ensure_plugins_loaded()  # the built-ins register once per process: have them in what is restored
    saved = {k: dict(r._entries) for k, r in reg._REGISTRIES.items()}
    monkeypatch.setattr(reg, "failed_plugins", {})
    monkeypatch.delenv("METEGS_PLUGINS", raising=False)
    sys.modules.pop("metegs_snow.register", None)
    for r in reg._REGISTRIES.values():
        r._entries.pop("snow", None)

    def install(*eps):
        monkeypatch.setattr(reg.metadata, "entry_points", lambda group: [e for e in eps if e.group == group])
        monkeypatch.setitem(reg._plugins_state, "loaded", False)

    yield install
    sys.modules.pop("metegs_snow.register", None)
    for k, r in reg._REGISTRIES.items():
        r._entries = saved[k]


def test_the_package_declares_the_entry_point():
    text = (Path(__file__).resolve().parents[1] / "pyproject.toml").read_text()
    section = text.split('[project.entry-points."metegs.plugins"]', 1)[1].split("\n[", 1)[0]
    assert [line for line in section.splitlines() if "=" in line] == ['metegs-snow = "metegs_snow.register"']


def test_entry_point_registers_snow_and_it_builds_by_name(rediscover):
    rediscover()
    assert "snow" not in registry("weather").names()
    rediscover(EntryPoint("metegs-snow", "metegs_snow.register", "metegs.plugins"))
    assert "snow" in registry("weather").names()
    assert registry("weather").entry("snow").source == "metegs-snow"
    (model,) = build_weather_models(["snow"], theta(1.0), scene())
    assert isinstance(model, Snow) and model.active and model.transient


def test_env_var_and_entry_point_together_register_once(rediscover, monkeypatch):
    monkeypatch.setenv("METEGS_PLUGINS", "metegs_snow.register")
    rediscover(EntryPoint("metegs-snow", "metegs_snow.register", "metegs.plugins"))
    assert registry("weather").names().count("snow") == 1  # no PluginWarning either (warnings are errors here)


def test_a_clashing_snow_from_another_package_is_reported(rediscover):
    rediscover()
    registry("weather").names()
    registry("weather").register("snow", "other_pkg:Snow", source="other")
    rediscover(EntryPoint("metegs-snow", "metegs_snow.register", "metegs.plugins"))
    with pytest.warns(PluginWarning, match="already registered by other"):
        registry("weather").names()
