"""The example `metegs-snow` plugin (plugins/metegs-snow) joins metegs without any change to metegs.

Runs from the source tree through ``METEGS_PLUGINS`` (so CI needs no install); the check of the installed
entry point skips when the package is not installed (``pip install ./plugins/metegs-snow``).
"""

from dataclasses import replace
from importlib import metadata

import pytest

import metegs.registry as reg
from metegs.registry import registry


def test_snow_is_listed_and_its_options_are_typed_flags(snow_plugin, capsys):
    from metegs.cli.train import components_help, parse_args

    assert "snow" in registry("weather").names()
    assert "snow [metegs" in components_help()  # [metegs-snow] when installed, else [metegs_snow.register]
    cfg = parse_args(["metegs-full", "--weather", "snow", "fog-analytic"])
    assert cfg.weather == ("snow", "fog-analytic")
    assert isinstance(cfg.weather_config("snow"), registry("weather").get("snow"))  # the plugin's own defaults
    cfg = parse_args(["metegs-full", "--weather", "snow", "--snow.max-count", "500", "--snow.albedo", "0.8"])
    assert (cfg.weather_config("snow").max_count, cfg.weather_config("snow").albedo) == (500, 0.8)
    with pytest.raises(SystemExit):
        parse_args(["metegs-full", "--help"])
    help_text = capsys.readouterr().out
    assert "--snow.max-count" in help_text and "Cap on flakes per view" in help_text  # the field's own docstring
    with pytest.raises(SystemExit):  # typed: tyro refuses what is not a number
        parse_args(["metegs-full", "--snow.albedo", "white"])


def test_metegs_synth_synthesises_snow(snow_plugin, tmp_path):
    import json

    from metegs.data.config import DatasetConfig, SyntheticSceneConfig
    from metegs.data.images import load_image
    from metegs.synth.pipeline import SynthConfig, synthesise

    args = SynthConfig(
        output=tmp_path / "snowy",
        kinds="snow",
        precip_mm_h=2.0,
        wind_speed_m_per_s=3.0,
        preview_views=2,
        dataset=DatasetConfig(synthetic=SyntheticSceneConfig(width=96, height=72, num_views=4, num_points=300)),
    )
    out = synthesise(args)
    weather = json.loads((out / "weather.json").read_text())
    assert weather["kinds"] == "snow"
    views = weather["views"]
    assert all(v["gaussians_per_model"]["snow"] > 0 and not v["fog"] for v in views)
    from metegs.synth.contact_sheet import record_label

    assert f"snow {views[0]['gaussians_per_model']['snow']}" in record_label(views[0])[0]  # not θ_rain's streak count
    snowy = load_image(out / views[0]["image"])
    clean = load_image(out / views[0]["clean_image"])
    brighter = (snowy - clean).max(-1) > 2 / 255
    assert 0.01 < brighter.mean() < 0.9 and (snowy - clean).mean() > 0.01  # bright flakes over the scene
    with pytest.raises(Exception, match="independent family makes drops, fog, rain only"):
        synthesise(replace(args, output=tmp_path / "x", family="independent"))


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
    assert trainer.degrade_kinds(trainer.scene) == {"snow", "fog"}  # `--degrade auto`: the kinds of its models
    assert trainer.decisions["degrade"].startswith("snow+fog synthesised")
    i = trainer.dataset.train_indices[0]
    assert (trainer.dataset.images[i] - trainer.dataset.clean_images[i]).abs().mean() > 0.005
    metrics = trainer.train()
    assert metrics["psnr"] > 0
    _viewer_shows_snow(trainer)


def _viewer_shows_snow(trainer):
    """The viewer lists snow among the weather models, ticked for this run, and renders it; unticked, it is gone."""

    from metegs.viewer import Viewer, ViewerConfig
    from metegs.viewer.camera import pose_of
    from metegs.viewer.weather import WeatherValues

    viewer = Viewer(trainer, ViewerConfig(port=0))
    try:
        assert viewer.model_boxes["snow"].value and not viewer.model_boxes["rain-streaks"].value
        assert viewer.weather.names == ["snow", "fog-analytic"]
        pose = pose_of(trainer.dataset.cameras, 0)
        viewer.set_weather(WeatherValues(precip_mm_h=3.0))  # clear air: snow and its veil
        snowy = viewer.render(pose, 48, "weather").astype(float)
        viewer.model_boxes["snow"].value = False
        viewer._models_changed()  # what the box's callback does
        assert viewer.weather.names == ["fog-analytic"]
        veil = viewer.render(pose, 48, "weather").astype(float)
        bright = (snowy - veil).max(-1) > 40
        assert 0 < bright.mean() < 0.5 and (snowy - veil).mean() > 0  # bright flakes, here and there
    finally:
        viewer.close()


@pytest.mark.skipif(
    not any(ep.value == "metegs_snow.register" for ep in metadata.entry_points(group="metegs.plugins")),
    reason="metegs-snow is not installed (pip install ./plugins/metegs-snow)",
)
def test_installed_entry_point_registers_snow():
    reg.ensure_plugins_loaded()
    assert registry("weather").entry("snow").source == "metegs-snow"
