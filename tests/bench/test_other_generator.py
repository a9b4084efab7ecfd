"""benchmarks/other_generator.py: its fog is Koschmieder's in closed form, its streaks only blend towards their
radiance, and the independent family is itself again after the block."""

from __future__ import annotations

import dataclasses
import json
import re

import numpy as np
import pytest

from metegs.data.config import DatasetConfig, SyntheticSceneConfig
from metegs.data.parsers.base import parse_scene
from metegs.weather.conditions import ConditionsConfig, theta_for_cameras
from metegs.weather.degrade import degrade_scene
from metegs.weather.independent import IndependentEngine, pixel_rays

MPU = 10.0


@pytest.fixture(scope="module")
def scene():
    return parse_scene(
        None, None, DatasetConfig(synthetic=SyntheticSceneConfig(width=48, height=36, num_views=3, num_points=200))
    )


def _degrade(generator, scene, variant, kinds, precip, visibility):
    theta = theta_for_cameras(ConditionsConfig(precip_mm_h=precip, visibility_m=visibility), scene.cameras, MPU)
    with generator.drawing(variant):
        degraded, records = degrade_scene(scene, theta, kinds=kinds, metres_per_unit=MPU, family="independent")
    return degraded, records


def test_its_fog_is_koschmieder_under_its_airlight(benchmark_script, scene):
    g = benchmark_script("other_generator")
    variant = dataclasses.replace(g.VARIANTS["smog"], streak_radiance=None)
    original = IndependentEngine.view
    degraded, records = _degrade(g, scene, variant, "fog", 0.0, 300.0)
    assert IndependentEngine.view is original and records[0]["kinds"] == "fog"
    for i in range(len(scene)):
        depth = np.asarray(scene.depths[i], np.float64)
        _, _, per_depth = pixel_rays(scene.cameras[i], *depth.shape)
        t = np.exp(-3.912 / 300.0 * np.minimum(depth * per_depth * MPU, 1500.0))[..., None]
        expected = degraded.clean_images[i] * t + np.asarray(variant.airlight) * (1 - t)
        assert np.allclose(degraded.images[i], np.clip(expected, 0, 1), atol=1e-5)


def test_its_streaks_only_blend_towards_their_radiance(benchmark_script, scene):
    g = benchmark_script("other_generator")
    variant = g.VARIANTS["rain"]
    degraded, records = _degrade(g, scene, variant, "rain", 22.0, None)
    assert records[0]["kinds"] == "rain"
    for clean, rainy in zip(degraded.clean_images, degraded.images, strict=True):
        changed = np.abs(rainy - clean).max(-1) > 1e-6
        assert 0.02 < changed.mean() < 0.9  # streaks over part of the view
        share = (rainy - clean) / np.where(
            np.abs(variant.streak_radiance - clean) > 1e-3, variant.streak_radiance - clean, np.inf
        )
        assert (share[changed] >= -1e-4).all() and (share[changed] <= variant.alpha[1] + 1e-4).all()


def test_its_views_say_which_variant_drew_them(benchmark_script, scene):
    g = benchmark_script("other_generator")
    with g.drawing(g.VARIANTS["rain"], "rain"):
        _, records = degrade_scene(
            scene,
            theta_for_cameras(ConditionsConfig(precip_mm_h=22.0), scene.cameras, MPU),
            kinds="rain",
            metres_per_unit=MPU,
            family="independent",
        )
    assert g.drawn_by({"views": records}) == "rain"
    assert g.drawn_by({"views": [{"family": "independent"}]}) is None


def test_a_suite_cell_drawn_by_another_generator_is_refused(benchmark_script, tmp_path):
    from types import SimpleNamespace

    from metegs.bench import data

    g = benchmark_script("other_generator")
    cells = {
        "independent": [{"family": "independent"}],
        "smog": [{"family": "other generator", "variant": "smog"}],
        "rain": [{"family": "other generator", "variant": "rain"}],
    }
    for name, views in cells.items():
        (tmp_path / name).mkdir()
        (tmp_path / name / "weather.json").write_text(json.dumps({"views": views}))
    independent = SimpleNamespace(name="rain-heavy-other", kind="rain", family="independent")
    physical = SimpleNamespace(name="rain+fog", kind="rain+fog", family="physical")
    original = data.degraded_dataset
    with g.guarded_cells("rain"):
        for refused in ("independent", "smog"):
            with pytest.raises(SystemExit, match="not by 'rain'"):
                data.degraded_dataset(tmp_path / refused, None, None, independent, None, 0)
        folder, weather = data.degraded_dataset(tmp_path / "rain", None, None, independent, None, 0)
        assert folder == tmp_path / "rain" and g.drawn_by(weather) == "rain"
        # metegs's own models draw a physical cell whichever generator draws the independent ones
        assert data.degraded_dataset(tmp_path / "independent", None, None, physical, None, 0)[0].name == "independent"
    assert data.degraded_dataset is original
    # through the suite itself, which looks the function up each time it degrades a cell (an import of it at the top
    # of metegs.bench.suite would bind the unguarded one and pass another generator's photos as this one's)
    from metegs.bench.suite import SuiteRunner

    (tmp_path / "cell" / "data").mkdir(parents=True)
    (tmp_path / "cell" / "data" / "weather.json").write_text(json.dumps({"views": cells["smog"]}))
    runner = SimpleNamespace(suite=SimpleNamespace(seed=0), console=None, thetas={})
    suite_scene = SimpleNamespace(name="s", data=None, parser=None, in_memory=True, synth=None)
    with g.guarded_cells("rain"), pytest.raises(SystemExit, match="not by 'rain'"):
        SuiteRunner._degraded(runner, suite_scene, independent, tmp_path / "cell", None, None)


@pytest.mark.parametrize(
    ("variant", "kind", "missing"),
    [("rain", "fog", "fog"), ("rain", "rain+fog", "fog"), ("fog", "rain+fog", "rain"), ("fog", "rain", "rain")],
)
def test_a_suite_cell_whose_weather_the_variant_does_not_draw_is_refused(
    benchmark_script, tmp_path, variant, kind, missing
):
    """The variant draws only the cell's kinds it has (`engine_view`), so a cell asking for more would train under a θ
    whose weather its photos lack: refused before anything is drawn, naming the condition."""
    from types import SimpleNamespace

    from metegs.bench import data

    g = benchmark_script("other_generator")
    cell = SimpleNamespace(name="the-cell", kind=kind, family="independent")
    with g.guarded_cells(variant), pytest.raises(SystemExit, match=re.escape(f"'the-cell' is {kind}, ")) as refused:
        data.degraded_dataset(tmp_path / "cell", None, None, cell, None, 0)
    assert f"variant draws no {missing}:" in str(refused.value) and not (tmp_path / "cell").exists()
