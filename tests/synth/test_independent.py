"""The independent degradation family: made without metegs's weather models, physically sound where it claims to
be, varied per view, reproducible."""

from __future__ import annotations

import ast
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

import metegs.weather.independent as ind
from metegs.cameras import Cameras
from metegs.data.config import DatasetConfig, SyntheticSceneConfig
from metegs.meteo.aggregate import WeatherConditions
from metegs.synth.pipeline import SynthConfig, synthesise


def test_imports_nothing_of_metegs_weather_models_or_mapping():
    tree = ast.parse(Path(ind.__file__).read_text())
    modules = {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
    modules |= {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    forbidden = [m for m in modules if m and m.startswith(("metegs.weather", "metegs.meteo.mapping", "metegs.render"))]
    assert not forbidden, forbidden


def _camera(width=40, height=30, focal=30.0) -> Cameras:
    return Cameras(torch.eye(4)[None], torch.tensor([focal]), torch.tensor([focal]), torch.tensor([width / 2]),
                   torch.tensor([height / 2]), torch.tensor([width]), torch.tensor([height]))  # fmt: skip


def _homogeneous(visibility_m: float) -> ind.FogField:
    return ind.FogField(
        beta_per_m=ind.KOSCHMIEDER / visibility_m, scale_height_m=1e12, channel_scale=(1.0, 1.0, 1.0),
        patch_amplitude=0.0, wave_vectors_per_m=((1.0, 0.0, 0.0),), wave_phases=(0.0,), airlight=(0.8, 0.8, 0.8),
        sun_dir=(0.0, 0.0, 1.0),
    )  # fmt: skip


def test_homogeneous_limit_is_koschmieder():
    """No patches, no height fall-off: t = exp(−3.912·d/V) along each ray (d: ray length), 2 % at d = V."""
    cam, mpu, vis = _camera(), 2.0, 300.0
    depth = np.full((30, 40), 150.0 / mpu, np.float32)  # z = 150 m
    image = np.zeros((30, 40, 3), np.float32)
    out, t = ind.fog_view(image, depth, cam, _homogeneous(vis), np.array([0.0, -1.0, 0.0]), -1e6, mpu)
    _, _, per_depth = ind.pixel_rays(cam, 30, 40)
    expected = np.exp(-ind.KOSCHMIEDER * 150.0 * per_depth / vis)
    assert np.allclose(t[..., 0], expected, rtol=1e-5)
    centre = t[15, 20, 0]  # on the axis, d = z = V / 2
    assert math.isclose(centre, 0.02**0.5, rel_tol=1e-3)
    veil = out / (1 - t)  # a black scene shows only the airlight, brighter towards the horizon and the sun
    assert (veil >= 0.8 * 0.85 - 1e-6).all() and (veil <= 0.8 + 0.12 + 1e-6).all()


def test_height_fog_thins_upwards_and_patches_vary_it():
    rng = np.random.default_rng(3)
    field = ind.draw_fog_field(rng, 200.0, 1.0)
    cam = _camera()
    depth = np.full((30, 40), 80.0, np.float32)
    up = np.array([0.0, -1.0, 0.0])  # OpenCV: y down, so up is −y: the top rows look upwards
    _, t = ind.fog_view(np.zeros((30, 40, 3), np.float32), depth, cam, field, up, 0.0, 1.0)
    assert t[0].mean() > t[-1].mean() * 1.02  # rays climbing out of the fog keep more light
    assert t[..., 2].mean() < t[..., 0].mean()  # blue is extinguished more than red
    assert np.std(t[..., 1] / np.exp(-np.log(t[..., 1]).mean())) > 0.0


def _orientation_deg(layer: np.ndarray) -> float:
    """Dominant direction of the streaks from the image's vertical, by the second moments of the power spectrum
    (streaks put their energy across their own direction)."""
    power = np.abs(np.fft.fftshift(np.fft.fft2(layer - layer.mean()))) ** 2
    h, w = power.shape
    ky, kx = np.mgrid[-(h // 2) : h - h // 2, -(w // 2) : w - w // 2]
    kx, ky = kx / w, ky / h
    across = 0.5 * math.atan2(2 * (power * kx * ky).sum(), (power * (kx * kx - ky * ky)).sum())  # from +x
    return -math.degrees(across)  # the streaks run perpendicular to it: from +y (down)


@pytest.mark.parametrize("angle", [-20.0, 0.0, 15.0])
def test_streaks_run_at_the_angle_asked(angle):
    layer = ind.streak_layer(np.random.default_rng(0), 240, 320, 0.004, 30, angle, 1.0, 0.8, 0.0)
    assert abs(_orientation_deg(layer) - angle) < 4.0
    assert 0.75 < layer.max() <= 0.8


def _conditions(p: float, vis: float | None = None, klass: str | None = None) -> WeatherConditions:
    from datetime import datetime, timezone

    return WeatherConditions(time_utc=datetime(2024, 1, 1, tzinfo=timezone.utc), precip_mm_per_h=p,
                             intensity_class=klass or "unknown", visibility_m=vis)  # fmt: skip


def test_heavier_classes_make_more_rain_and_views_differ():
    image = np.full((240, 320, 3), 0.3, np.float32)  # streaks fade below a pixel at thumbnail sizes
    energy = {}
    for klass in ("light", "moderate", "heavy", "violent"):
        rains = [ind.rain_view(np.random.default_rng([1, v]), image, klass, 0.0, np.full(3, 0.8))[0] for v in range(4)]
        energy[klass] = float(np.mean([np.abs(r - image).mean() for r in rains]))
        assert not np.allclose(rains[0], rains[1])  # drawn anew for every view
    assert energy["light"] < energy["moderate"] < energy["heavy"] < energy["violent"]
    assert energy["light"] > 0.003  # visible at this resolution


def test_rain_class_follows_wmo_bounds():
    assert ind.rain_class(_conditions(0.0)) is None
    assert [ind.rain_class(_conditions(p)) for p in (1.0, 5.0, 20.0, 80.0)] == ["light", "moderate", "heavy", "violent"]


def test_drops_cover_part_of_the_view():
    image = np.random.default_rng(0).random((120, 160, 3)).astype(np.float32)
    out, record = ind.drops_view(np.random.default_rng(5), image, "heavy")
    changed = (np.abs(out - image).max(axis=-1) > 0.02).mean()
    assert record["count"] >= 7 and 0.02 < changed < 0.5


TINY = DatasetConfig(synthetic=SyntheticSceneConfig(width=64, height=48, num_views=4, num_points=200))


def _synth(tmp_path, name, **kw):
    args = SynthConfig(output=tmp_path / name, dataset=TINY, preview_views=2, precip_mm_h=20.0, visibility_m=300.0,
                     kinds="rain+fog", **kw)  # fmt: skip
    return synthesise(args)


def test_metegs_synth_writes_the_independent_family(tmp_path):
    out = _synth(tmp_path, "ind", family="independent")
    again = _synth(tmp_path, "again", family="independent")
    physical = _synth(tmp_path, "phys")
    weather = json.loads((out / "weather.json").read_text())
    assert weather["family"] == "independent" and len(weather["views"]) == 4
    view = weather["views"][0]
    assert view["rain"]["class"] == "heavy" and view["fog"]["beta_per_m"] == pytest.approx(3.912 / 300.0)
    from metegs.data.images import load_image

    a, b, c = (load_image(sorted((d / "images").glob("*"))[0]) for d in (out, again, physical))
    assert np.array_equal(a, b)  # reproducible from the seed
    assert np.abs(a - c).mean() > 0.02  # not the physical family's images
    assert (out / "preview.png").is_file()


def test_in_memory_degrade_takes_the_family():
    from metegs.data.parsers.base import parse_scene
    from metegs.weather.conditions import ConditionsConfig, theta_for_cameras
    from metegs.weather.degrade import degrade_scene

    scene = parse_scene(None, None, TINY)
    theta = theta_for_cameras(ConditionsConfig(precip_mm_h=20.0, visibility_m=300.0), scene.cameras, 10.0)
    degraded, records = degrade_scene(scene, theta, kinds="rain+fog", family="independent")
    assert all(r["family"] == "independent" for r in records)
    assert np.abs(degraded.images[0] - degraded.clean_images[0]).mean() > 0.05
    with pytest.raises(Exception, match="family='nope'"):
        degrade_scene(scene, theta, family="nope")
