"""The example `metegs-snow` plugin (plugins/metegs-snow) joins metegs without any change to metegs.

Runs from the source tree through ``METEGS_PLUGINS`` (so CI needs no install); the check of the installed
entry point skips when the package is not installed (``pip install ./plugins/metegs-snow``).
"""

import sys
from importlib import metadata
from pathlib import Path

import pytest

import metegs.registry as reg
from metegs.registry import registry

SNOW_SRC = Path(__file__).resolve().parents[2] / "plugins" / "metegs-snow" / "src"


@pytest.fixture
def snow_plugin(monkeypatch):
    """Rediscover plugins with the snow plugin importable from its source folder; restore the registries after."""
    reg.ensure_plugins_loaded()  # the built-ins register once per process: have them in what is restored
    saved = {k: dict(r._entries) for k, r in reg._REGISTRIES.items()}
    monkeypatch.syspath_prepend(str(SNOW_SRC))
    monkeypatch.setenv("METEGS_PLUGINS", "metegs_snow.register")
    monkeypatch.setattr(reg, "failed_plugins", {})
    monkeypatch.setitem(reg._plugins_state, "loaded", False)
    sys.modules.pop("metegs_snow.register", None)
    yield
    sys.modules.pop("metegs_snow.register", None)
    for k, r in reg._REGISTRIES.items():
        r._entries = saved[k]


def test_snow_is_listed_and_selectable_from_the_command_line(snow_plugin):
    from metegs.cli.train import components_help, parse_args

    assert "snow" in registry("weather").names()
    assert "snow [metegs" in components_help()  # [metegs-snow] when installed, else [metegs_snow.register]
    cfg = parse_args(["metegs-full", "--weather", "snow", "fog-analytic"])
    assert cfg.weather == ("snow", "fog-analytic")
    assert isinstance(cfg.weather_config("snow"), registry("weather").get("snow"))  # the plugin's own defaults


def test_metegs_full_trains_with_snow_instead_of_rain(snow_plugin, tmp_path):
    from metegs.data.config import DatasetConfig, SyntheticSceneConfig
    from metegs.engine.metegs_config import LossWeights, MeteGSConfig
    from metegs.weather.conditions import ConditionsConfig
    from metegs.weather.learnable import LearnableTransients

    cfg = MeteGSConfig(
        weather=("snow", "fog-analytic"),
        max_steps=3,
        output_dir=tmp_path,
        experiment_name="snow",
        device="cpu",
        progress=False,
        compare_baseline=False,
        weights=LossWeights(perceptual=0.0),
        dataset=DatasetConfig(synthetic=SyntheticSceneConfig(width=48, height=36, num_views=6, num_points=300)),
        conditions=ConditionsConfig(precip_mm_h=1.5, visibility_m=800.0, wind_speed_m_s=3.0, wind_dir_deg=270.0),
    )
    trainer = cfg.setup()
    (snow,) = [m for m in trainer.weather_models if isinstance(m, LearnableTransients)]
    assert snow.inner.name == "snow" and len(snow.views) == len(trainer.dataset.train_indices)
    assert trainer.decisions["weather snow"].startswith("on:")
    assert "rain" not in trainer.degrade_kinds(trainer.scene)  # `--degrade auto` synthesises the kinds named: fog only
    metrics = trainer.train()
    assert metrics["psnr"] > 0


@pytest.mark.skipif(
    not any(ep.value == "metegs_snow.register" for ep in metadata.entry_points(group="metegs.plugins")),
    reason="metegs-snow is not installed (pip install ./plugins/metegs-snow)",
)
def test_installed_entry_point_registers_snow():
    reg.ensure_plugins_loaded()
    assert registry("weather").entry("snow").source == "metegs-snow"
