"""Configs: YAML round trip, overrides, and the metegs-train command line."""

from pathlib import Path

import pytest

from metegs.cli.train import parse_args, pop_config_flag
from metegs.config import apply_overrides, load_yaml, save_yaml, to_dict
from metegs.engine.config import TrainConfig
from metegs.errors import ConfigError, MetegsError


def test_yaml_round_trip(tmp_path):
    cfg = TrainConfig(max_steps=123, data=Path("/some/scene"), seed=7)
    cfg = apply_overrides(cfg, {"densify": {"grow_grad2d": 3e-4}, "dataset": {"downscale": 2}})
    save_yaml(cfg, tmp_path / "config.yml", header={"metegs_version": "x"})
    data = load_yaml(tmp_path / "config.yml")
    assert data["metegs_version"] == "x" and data["method"] == "3dgs"
    data.pop("metegs_version")
    back = apply_overrides(TrainConfig(), data)
    assert to_dict(back) == to_dict(cfg)
    assert back.data == Path("/some/scene") and back.dataset.downscale == 2.0


def test_unknown_or_mistyped_fields_are_errors():
    with pytest.raises(ConfigError, match="unknown config field 'densify.nope'"):
        apply_overrides(TrainConfig(), {"densify": {"nope": 1}})
    with pytest.raises(ConfigError, match="max_steps"):
        apply_overrides(TrainConfig(), {"max_steps": "many"})
    with pytest.raises(ConfigError, match="background"):
        apply_overrides(TrainConfig(), {"background": "purple"})


@pytest.mark.parametrize("share", ["1.5", "-0.1"])
def test_a_coverage_share_outside_zero_to_one_is_named(share):
    with pytest.raises(ConfigError, match=rf"--model.sweep-below-coverage {share}: expected a number >= 0 and <= 1"):
        parse_args(["3dgs", "--model.sweep-below-coverage", share])


def test_cli_flags_override_defaults():
    cfg = parse_args(
        ["3dgs", "--max-steps", "5", "--seed", "3", "--densify.grow-grad2d", "0.001", "--backend", "torch"]
    )
    assert cfg.max_steps == 5 and cfg.seed == 3 and cfg.densify.grow_grad2d == 0.001 and cfg.backend == "torch"
    assert cfg.data is None and cfg.method == "3dgs"


def test_config_file_then_cli_flags(tmp_path):
    (tmp_path / "o.yaml").write_text("max_steps: 42\nseed: 9\nmodel:\n  sh_degree: 1\n")
    cfg = parse_args(["3dgs", "--config", str(tmp_path / "o.yaml"), "--seed", "1"])
    assert cfg.max_steps == 42 and cfg.model.sh_degree == 1 and cfg.seed == 1


def test_saved_config_reproduces_the_run_config(tmp_path):
    cfg = parse_args(["3dgs", "--max-steps", "17", "--dataset.test-every", "4"])
    save_yaml(cfg, tmp_path / "config.yml", header={"metegs_version": "0"})
    again = parse_args(["--config", str(tmp_path / "config.yml")])  # method taken from the file
    assert to_dict(again) == to_dict(cfg)


def test_bad_config_file_names_it(tmp_path):
    (tmp_path / "bad.yaml").write_text("max_steps: [unclosed\n")
    with pytest.raises(MetegsError, match="bad.yaml"):
        parse_args(["3dgs", "--config", str(tmp_path / "bad.yaml")])
    with pytest.raises(MetegsError, match="missing.yaml"):
        parse_args(["3dgs", "--config", str(tmp_path / "missing.yaml")])
    (tmp_path / "typo.yaml").write_text("max_stepz: 3\n")
    with pytest.raises(MetegsError, match="typo.yaml.*max_stepz"):
        parse_args(["3dgs", "--config", str(tmp_path / "typo.yaml")])


def test_pop_config_flag_forms():
    assert pop_config_flag(["a", "--config", "x.yml", "b"]) == (["a", "b"], Path("x.yml"))
    assert pop_config_flag(["--config=y.yml"]) == ([], Path("y.yml"))
    assert pop_config_flag(["--load-config", "RUN/config.yml", "b"]) == (["b"], Path("RUN/config.yml"))
    assert pop_config_flag(["--load-config=z.yml"]) == ([], Path("z.yml"))


def test_help_lists_every_component_kind_and_marks_plugins():
    from metegs.cli.train import COMPONENT_KINDS, components_help
    from metegs.registry import registry

    text = components_help()
    for kind in COMPONENT_KINDS:
        assert f"  {kind}: " in text
    assert "rain-streaks" in text and "rain-streaks [" not in text  # built-ins carry no mark
    reg = registry("weather")
    reg.register("test-hail", object, description="test only", source="metegs-hail")  # as a plugin would
    try:
        assert "test-hail [metegs-hail]" in components_help()
    finally:
        reg.unregister("test-hail")


def test_a_config_with_a_retired_field_still_opens_and_says_why(tmp_path):
    cfg = parse_args(["metegs-full", "--max-steps", "17"])
    save_yaml(cfg, tmp_path / "config.yml", header={"metegs_version": "0", "densify_through_fog": 10.0})
    with pytest.warns(UserWarning, match="config.yml: ignoring 'densify_through_fog': densification no longer"):
        again = parse_args(["--config", str(tmp_path / "config.yml")])
    assert to_dict(again) == to_dict(cfg)
    (tmp_path / "new.yaml").write_text("densify_thru_fog: 10\n")  # a field that never was stays an error
    with pytest.raises(MetegsError, match="densify_thru_fog"):
        parse_args(["metegs-full", "--config", str(tmp_path / "new.yaml")])


def test_a_run_of_a_weather_plugin_that_is_not_installed_says_so(tmp_path):
    from metegs.engine.run import load_run_config

    (tmp_path / "config.yml").write_text(
        "method: metegs-full\nweather: [snowfall, fog-analytic]\nsnowfall: {count: 3}\n"
    )
    for load in (lambda: parse_args(["--config", str(tmp_path / "config.yml")]), lambda: load_run_config(tmp_path)):
        with pytest.raises(
            MetegsError, match=r"config.yml: weather model\(s\) snowfall are not registered here: install"
        ):
            load()
