"""Weather kinds come from the registered models: parsing, their order, what precipitates, and clear errors."""

import pytest

from metegs.errors import ConfigError
from metegs.weather.kinds import join_kinds, kind_of, parse_kinds, precipitation_kinds, weather_kinds


def test_the_builtin_kinds_and_their_models():
    kinds = weather_kinds()
    assert list(kinds) == ["rain", "fog", "drops"]  # world-space weather, then media, then the lens
    assert kinds["fog"] == ["fog-analytic", "fog-gaussians"] and kind_of("lens-droplets") == "drops"
    assert precipitation_kinds() == {"rain"}  # what falls anew in every photo


def test_kinds_parse_and_join_in_one_order():
    assert parse_kinds(" Fog + rain ") == {"rain", "fog"}
    assert join_kinds({"drops", "fog", "rain"}) == "rain+fog+drops"


@pytest.mark.parametrize(
    "text,message",
    [
        ("hail+fog", r"from rain, fog .*unknown: hail"),
        ("drops", r"with '\+drops' for the lens"),
        ("", "expected weather kinds"),
    ],
)
def test_a_kind_no_model_makes_is_refused_naming_the_option(text, message):
    with pytest.raises(ConfigError, match=message):
        parse_kinds(text, "--degrade")
    with pytest.raises(ConfigError, match="--degrade="):
        parse_kinds(text, "--degrade")


def test_degrade_names_the_flag_when_the_kind_is_unknown(tmp_path):
    from metegs.data.config import DatasetConfig, SyntheticSceneConfig
    from metegs.methods import gaussian_splatting

    config = gaussian_splatting()
    config = type(config)(
        method="3dgs", degrade="snow", output_dir=tmp_path, progress=False, device="cpu",
        dataset=DatasetConfig(synthetic=SyntheticSceneConfig(width=32, height=24, num_views=4, num_points=100)),
    )  # fmt: skip
    with pytest.raises(ConfigError, match="--degrade='snow'.*unknown: snow"):
        config.setup()
