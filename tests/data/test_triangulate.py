"""Points triangulated from known poses (pycolmap) or swept (plane sweep): on the surfaces of the synthetic scene,
cached, and a trainer that uses them when a scene has photos and poses but no points."""

from __future__ import annotations

import os
from dataclasses import replace

import numpy as np
import pytest
import torch

import metegs.data.triangulate as tri
from metegs.data.config import DatasetConfig, SyntheticSceneConfig
from metegs.data.images import save_image
from metegs.data.parsers.base import parse_scene
from metegs.data.sfm import SIFT_PEAK_THRESHOLD, photo_contrast
from metegs.data.triangulate import MIN_POINTS, triangulate_known_poses

VIEWS = 12
"""Consecutive views of the 48 on the synthetic orbit (7.5 degrees apart; SIFT does not match across 30)."""


@pytest.fixture(scope="module")
def photographed(tmp_path_factory):
    """The synthetic scene at 320x240 with its first `VIEWS` renders written as PNG files (a scene that has photos)."""
    config = SyntheticSceneConfig(width=320, height=240, num_views=48)
    scene = parse_scene(None, None, DatasetConfig(synthetic=config, test_every=4))
    folder = tmp_path_factory.mktemp("photos")
    paths = []
    for i, img in enumerate(scene.images[:VIEWS]):
        paths.append(folder / f"view_{i:03d}.png")
        save_image(paths[-1], img)
    return scene, paths


def relative_depth_error(scene, points: np.ndarray) -> np.ndarray:
    """Per point, the smallest |z - exact depth| / exact depth over the views it projects into. -> [P]."""
    return _depth_errors(scene, points, len(scene.cameras))[0].min(0)


def visible_pixels(scene, points: np.ndarray, views: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per point, (view, row, column) of the first ``views`` view where its depth is nearest the exact depth: the
    view that sees it. -> three [P] int arrays."""
    err, rows, cols = _depth_errors(scene, points, views)
    view = err.argmin(0)
    pick = np.arange(len(points))
    return view, rows[view, pick], cols[view, pick]


def _depth_errors(scene, points: np.ndarray, views: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """|z - exact depth| / exact depth of each point in each of the first ``views`` views (inf outside it), and its
    pixel's row and column there. -> three [V, P] arrays."""
    errs, rows, cols = [], [], []
    for v in range(views):
        cam = scene.cameras[v]
        w2c = cam.world_to_cameras()[0].double().numpy()
        p = points.astype(np.float64) @ w2c[:3, :3].T + w2c[:3, 3]
        z = p[:, 2]
        u = float(cam.fx[0]) * p[:, 0] / z + float(cam.cx[0])
        r = float(cam.fy[0]) * p[:, 1] / z + float(cam.cy[0])
        h, w = scene.depths[v].shape
        inside = (z > 0) & (u >= 0) & (u < w) & (r >= 0) & (r < h)
        gt = scene.depths[v][r[inside].astype(int), u[inside].astype(int)]
        err = np.full(len(points), np.inf)
        err[inside] = np.abs(z[inside] - gt) / gt
        errs.append(err)
        rows.append(np.clip(np.nan_to_num(r), 0, h - 1).astype(int))
        cols.append(np.clip(np.nan_to_num(u), 0, w - 1).astype(int))
    return np.stack(errs), np.stack(rows), np.stack(cols)


def test_points_lie_on_the_scene_surfaces(photographed, tmp_path):
    scene, paths = photographed
    found = triangulate_known_poses(paths, scene.cameras[list(range(VIEWS))], tmp_path / "cache")
    assert len(found.points) >= MIN_POINTS
    assert found.num_views == VIEWS and found.reprojection_error_px < 1.5
    err = relative_depth_error(scene, found.points)
    assert np.median(err) < 0.01, np.median(err)
    assert (err < 0.05).mean() > 0.9
    assert found.colors.shape == found.points.shape and 0.0 <= found.colors.min() and found.colors.max() <= 1.0
    assert found.colors.std() > 0.05


def _points_or_none(paths, cameras, opts=None) -> int:
    """How many points triangulation finds (0 where it finds too few to return)."""
    try:
        return len(triangulate_known_poses(paths, cameras, None, opts).points)
    except RuntimeError:
        return 0


def test_hazed_photos_lower_sifts_contrast_threshold_and_keep_their_points(photographed, tmp_path):
    """Fog leaves a third of a clear photo's contrast, and SIFT's fixed threshold drops features with it; the
    threshold scaled by the photos' span finds them again, on the scene's surfaces."""
    scene, paths = photographed
    cams = scene.cameras[list(range(VIEWS))]
    clear = [torch.as_tensor(scene.images[i]) for i in range(VIEWS)]
    assert tri.contrast_options(photo_contrast(clear)).peak_threshold == 0  # COLMAP's own for clear photos
    hazed = [0.3 * image + 0.6 for image in clear]
    hazed_paths = [tmp_path / p.name for p in paths]
    for path, image in zip(hazed_paths, hazed):
        save_image(path, image)
    opts = tri.contrast_options(photo_contrast(hazed))
    assert 0 < opts.peak_threshold < 0.5 * SIFT_PEAK_THRESHOLD
    default = _points_or_none(hazed_paths, cams)
    scaled = triangulate_known_poses(hazed_paths, cams, None, opts)
    assert len(scaled.points) > 1.5 * default, (len(scaled.points), default)
    assert len(scaled.points) > 0.5 * _points_or_none(paths, cams)
    assert np.median(relative_depth_error(scene, scaled.points)) < 0.01


def test_cache_is_reused_and_invalidated_by_a_changed_photo(photographed, tmp_path, monkeypatch):
    scene, paths = photographed
    cams = scene.cameras[list(range(VIEWS))]
    first = triangulate_known_poses(paths, cams, tmp_path)
    assert first.cache is not None and first.cache.is_file()

    def must_not_run(*args, **kwargs):
        raise AssertionError("triangulated again although the photos are unchanged")

    monkeypatch.setattr(tri, "_triangulate", must_not_run)
    again = triangulate_known_poses(paths, cams, tmp_path)
    assert np.array_equal(again.points, first.points) and np.array_equal(again.colors, first.colors)
    stat = paths[0].stat()
    os.utime(paths[0], ns=(stat.st_atime_ns, stat.st_mtime_ns + 10**9))
    with pytest.raises(AssertionError, match="triangulated again"):
        triangulate_known_poses(paths, cams, tmp_path)


def test_a_new_pipeline_version_triangulates_again(photographed, tmp_path, monkeypatch):
    """Points cached by an earlier pipeline are not served to a run of a changed one."""
    scene, paths = photographed
    cams = scene.cameras[list(range(VIEWS))]
    points = np.random.default_rng(0).normal(size=(MIN_POINTS, 3)).astype(np.float32)
    calls = []

    def fake(*args, **kwargs):
        calls.append(1)
        return tri.TriangulatedPoints(points, np.full_like(points, 0.5), VIEWS, 0.5)

    monkeypatch.setattr(tri, "_triangulate", fake)
    first = triangulate_known_poses(paths, cams, tmp_path)
    triangulate_known_poses(paths, cams, tmp_path)
    assert len(calls) == 1
    monkeypatch.setattr(tri, "PIPELINE_VERSION", tri.PIPELINE_VERSION + "-next")
    again = triangulate_known_poses(paths, cams, tmp_path)
    assert len(calls) == 2 and again.cache != first.cache


def test_an_unreadable_cache_is_named_in_a_warning_and_rewritten(photographed, tmp_path, monkeypatch):
    scene, paths = photographed
    cams = scene.cameras[list(range(VIEWS))]
    points = np.random.default_rng(1).normal(size=(MIN_POINTS, 3)).astype(np.float32)
    calls = []

    def fake(image_paths, cameras, opts):
        calls.append(len(image_paths))
        return tri.TriangulatedPoints(points, np.full_like(points, 0.5), len(image_paths), 0.5)

    monkeypatch.setattr(tri, "_triangulate", fake)
    first = triangulate_known_poses(paths, cams, tmp_path)
    first.cache.write_bytes(b"not an npz file")
    with pytest.warns(UserWarning, match="unreadable cached triangulation"):
        again = triangulate_known_poses(paths, cams, tmp_path)
    assert calls == [VIEWS, VIEWS] and np.array_equal(again.points, points)
    assert np.array_equal(triangulate_known_poses(paths, cams, tmp_path).points, points) and len(calls) == 2


def test_featureless_photos_are_a_clear_failure(photographed, tmp_path):
    scene, _ = photographed
    paths = []
    for i in range(4):
        paths.append(tmp_path / f"grey_{i}.png")
        save_image(paths[-1], np.full((240, 320, 3), 0.5, dtype=np.float32))
    with pytest.raises(RuntimeError, match="points could be triangulated"):
        triangulate_known_poses(paths, scene.cameras[list(range(4))], None)


def test_a_failed_triangulation_is_remembered_until_the_photos_change(photographed, tmp_path, monkeypatch):
    scene, paths = photographed
    cams = scene.cameras[list(range(VIEWS))]
    few = np.zeros((3, 3), np.float32)
    calls = []

    def fake(image_paths, cameras, opts):
        calls.append(len(image_paths))
        return tri.TriangulatedPoints(few, few + 0.5, len(image_paths), 0.5)

    monkeypatch.setattr(tri, "_triangulate", fake)
    for _ in range(2):
        with pytest.raises(RuntimeError, match=r"only 3 points .* remembered in .*points-.*\.npz \(delete it"):
            triangulate_known_poses(paths, cams, tmp_path)
    assert calls == [VIEWS]  # the second run read the failure from the cache
    stat = paths[0].stat()
    os.utime(paths[0], ns=(stat.st_atime_ns, stat.st_mtime_ns + 10**9))
    with pytest.raises(RuntimeError, match="only 3 points"):
        triangulate_known_poses(paths, cams, tmp_path)
    assert calls == [VIEWS, VIEWS]


def heavy_rain(image: np.ndarray, seed: int) -> torch.Tensor:
    """``image`` [H, W, 3] under the independent family's heavy rain (streak layers of its own, per view)."""
    from metegs.weather.independent import rain_view

    return torch.from_numpy(rain_view(np.random.default_rng(seed), image, "heavy", 10.0, np.full(3, 0.8))[0])


@pytest.mark.parametrize("weather", ["clear", "heavy rain"])
def test_plane_sweep_points_lie_on_the_scene_surfaces(photographed, weather):
    """Under streaks drawn anew in every view the sweep still finds the surfaces: what one photo holds alone does
    not correlate with its neighbours."""
    from metegs.data.plane_sweep import plane_sweep_points

    scene, _ = photographed
    clean = [np.asarray(im, np.float32) for im in scene.images[:VIEWS]]
    photos = (
        [torch.from_numpy(im) for im in clean]
        if weather == "clear"
        else [heavy_rain(im, i) for i, im in enumerate(clean)]
    )
    cams = scene.cameras[list(range(VIEWS))]
    points, colours = plane_sweep_points(photos, cams, max_points=5000)
    assert 1000 <= len(points) <= 5000 and colours.shape == points.shape
    err = relative_depth_error(scene, points)
    assert np.median(err) < 0.01 and np.quantile(err, 0.9) < 0.05, (np.median(err), np.quantile(err, 0.9))

    # colours against the photo of the view in which each point is visible (its depth there the exact one)
    view, row, col = visible_pixels(scene, points, VIEWS)
    seen = np.stack([photos[v].numpy()[r, c] for v, r, c in zip(view, row, col)])
    assert np.abs(colours - seen).mean() < 0.1, np.abs(colours - seen).mean()


def test_a_trainer_sweeps_the_views_where_triangulation_fails(photographed, tmp_path, monkeypatch):
    """Rain that leaves SIFT a few dozen points: the Gaussians start from the sweep's points (cached like a
    triangulation), not from random ones."""
    from metegs.engine.config import TrainConfig

    scene, paths = photographed
    photos = []
    for i, path in enumerate(paths):
        photos.append(tmp_path / "rain" / path.name)
        photos[-1].parent.mkdir(exist_ok=True)
        save_image(photos[-1], heavy_rain(np.asarray(scene.images[i], np.float32), i).numpy())

    def failing(*args, **kwargs):
        raise RuntimeError("only 36 points could be triangulated")

    monkeypatch.setattr(tri, "triangulate_known_poses", failing)
    config = TrainConfig(max_steps=1, progress=False, output_dir=tmp_path / "runs")
    config = replace(config, model=replace(config.model, init_random_points=3000))
    rainy = subset(scene, photos, source=tmp_path / "rain")
    trainer = config.setup(scene=rainy)
    assert not trainer.random_init and 1000 <= len(trainer.model) <= 3000
    assert "plane sweep" in trainer.decisions["init"] and "only 36 points" in trainer.decisions["init"]
    err = relative_depth_error(scene, trainer.model.means.detach().numpy())
    assert np.median(err) < 0.02
    cached = list((tmp_path / "rain" / tri.CACHE_DIR).glob("sweep-*.npz"))
    assert len(cached) == 1
    again = config.setup(scene=rainy)
    assert torch.equal(again.model.means, trainer.model.means) and "plane sweep" in again.decisions["init"]
    assert trainer.swept_init and again.swept_init
    trainer.step = 1
    resumed = replace(config, max_steps=2, load_checkpoint=trainer.save()).setup(scene=rainy)
    assert resumed.swept_init and not resumed.random_init, "a resumed run must decide as its start did"


def subset(scene, paths, source):
    """The photographed views as a scene with photo files and poses but no points (like an LLFF capture)."""
    views = list(range(len(paths)))
    return replace(
        scene,
        cameras=scene.cameras[views],
        names=scene.names[: len(views)],
        images=None,
        image_paths=paths,
        depths=None,
        clean_images=None,
        points=None,
        point_colors=None,
        source=source,
        train_indices=[v for v in views if v % 4],
        test_indices=[v for v in views if v % 4 == 0],
    )


@pytest.fixture
def fake_triangulation(monkeypatch):
    """Replaces triangulate_known_poses by one returning 500 fixed points; -> (calls [(views, cache dir)], points)."""
    calls = []
    points = np.random.default_rng(0).normal(size=(500, 3)).astype(np.float32)

    def fake(image_paths, cameras, cache_dir, opts=None):
        calls.append((len(image_paths), cache_dir))
        return tri.TriangulatedPoints(points, np.full_like(points, 0.5), len(image_paths), 0.5, cache=None)

    monkeypatch.setattr(tri, "triangulate_known_poses", fake)
    return calls, points


def test_trainer_starts_from_triangulated_points_when_the_scene_has_none(photographed, tmp_path, fake_triangulation):
    from metegs.engine.config import TrainConfig

    scene, paths = photographed
    posed_only = subset(scene, paths, source=tmp_path)
    calls, points = fake_triangulation
    config = TrainConfig(max_steps=1, progress=False, output_dir=tmp_path / "runs")
    config = replace(config, model=replace(config.model, sweep_init=False))
    trainer = config.setup(scene=posed_only)
    assert calls == [(len(trainer.dataset.train_indices), tmp_path / tri.CACHE_DIR)]
    assert not trainer.random_init and not trainer.swept_init and len(trainer.model) == len(points)
    assert "triangulated" in trainer.decisions["init"] and trainer.triangulated_points is None

    off = replace(config, model=replace(config.model, triangulate=False)).setup(scene=posed_only)
    assert off.random_init and len(calls) == 1
    assert "random Gaussians: --model.no-triangulate --model.no-sweep-init" in off.decisions["init"]


def test_no_triangulate_with_sweep_init_sweeps_without_triangulating(photographed, tmp_path, fake_triangulation):
    """`--model.no-triangulate` (the sweep on, as by default): the sweep's points, not random ones, and no
    triangulation."""
    from metegs.engine.config import TrainConfig

    scene, paths = photographed
    calls, _ = fake_triangulation
    config = TrainConfig(max_steps=1, progress=False, output_dir=tmp_path / "runs")
    model = replace(config.model, triangulate=False, init_random_points=3000)
    trainer = replace(config, model=model).setup(scene=subset(scene, paths, source=tmp_path))
    assert calls == [] and trainer.swept_init and not trainer.random_init
    assert trainer.triangulated_points is None
    assert "plane sweep" in trainer.decisions["init"] and "--model.no-triangulate" in trainer.decisions["init"]
    err = relative_depth_error(scene, trainer.model.means.detach().numpy())
    assert np.median(err) < 0.02, np.median(err)


def test_a_trainer_on_hazed_photos_triangulates_at_their_contrast(photographed, tmp_path, monkeypatch):
    from metegs.engine.config import TrainConfig

    scene, paths = photographed
    hazed = []
    for path, image in zip(paths, scene.images):
        hazed.append(tmp_path / "hazed" / path.name)
        save_image(hazed[-1], 0.3 * torch.as_tensor(image) + 0.6)
    seen = []

    def fake(image_paths, cameras, cache_dir, opts=None):
        seen.append(opts)
        points = np.random.default_rng(0).normal(size=(500, 3)).astype(np.float32)
        return tri.TriangulatedPoints(points, np.full_like(points, 0.5), len(image_paths), 0.5, cache=None)

    monkeypatch.setattr(tri, "triangulate_known_poses", fake)
    config = TrainConfig(max_steps=1, progress=False, output_dir=tmp_path / "runs")
    config = replace(config, model=replace(config.model, sweep_init=False))
    config.setup(scene=subset(scene, paths, source=tmp_path / "clear"))
    trainer = config.setup(scene=subset(scene, hazed, source=tmp_path / "hazed"))
    clear_opts, hazed_opts = seen
    assert clear_opts.peak_threshold == 0  # COLMAP's own
    assert 0 < hazed_opts.peak_threshold < 0.5 * SIFT_PEAK_THRESHOLD
    assert "SIFT's contrast threshold" in trainer.decisions["init"] and "spans 0.20" in trainer.decisions["init"]


@pytest.mark.parametrize("clean_supervision", [True, False])
def test_a_run_given_clean_references_triangulates_from_them(photographed, tmp_path, monkeypatch, clean_supervision):
    """Rain and haze take the features triangulation matches; MeteGS trained on clean references starts from their
    points, blind MeteGS (and 3DGS) from the photos'."""
    from metegs.engine.metegs_config import MeteGSConfig

    scene, paths = photographed
    clean = []
    for path in paths:
        clean.append(tmp_path / "images_clean" / path.name)
        clean[-1].parent.mkdir(exist_ok=True)
        clean[-1].write_bytes(path.read_bytes())
    seen = []

    def fake(image_paths, cameras, cache_dir, opts=None):
        seen.append(list(image_paths))
        points = np.random.default_rng(0).normal(size=(500, 3)).astype(np.float32)
        return tri.TriangulatedPoints(points, np.full_like(points, 0.5), len(image_paths), 0.5, cache=None)

    monkeypatch.setattr(tri, "triangulate_known_poses", fake)
    with_clean = replace(subset(scene, paths, source=tmp_path), clean_image_paths=clean)
    config = MeteGSConfig(
        max_steps=1, progress=False, output_dir=tmp_path / "runs", clean_supervision=clean_supervision
    )
    trainer = config.setup(scene=with_clean)
    train = trainer.dataset.train_indices
    expected = [clean[i] for i in train] if clean_supervision else [paths[i] for i in train]
    assert seen == [expected] and not trainer.random_init
    whose = "clean references" if clean_supervision else "photos"
    assert f"training views' {whose} at their known poses" in trainer.decisions["init"]


def test_a_read_only_scene_caches_its_points_in_the_user_cache(photographed, tmp_path, fake_triangulation, monkeypatch):
    """A dataset the user cannot write (a shared or mounted folder) is never written to: the points go to
    ``$XDG_CACHE_HOME/metegs/points/<digest of the scene's path>``, one folder per scene."""
    import os

    from metegs.engine.config import TrainConfig

    scene, paths = photographed
    calls, _ = fake_triangulation
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    writable = os.access
    monkeypatch.setattr(os, "access", lambda p, mode: False if "scene" in str(p) else writable(p, mode))
    config = TrainConfig(max_steps=1, progress=False, output_dir=tmp_path / "runs")
    for name in ("scene-a", "scene-b"):
        (tmp_path / name).mkdir()
        config.setup(scene=subset(scene, paths, source=tmp_path / name))
    (a, cache_a), (_, cache_b) = calls
    assert cache_a.parent == tmp_path / "cache" / "metegs" / "points" and cache_b.parent == cache_a.parent
    assert cache_a != cache_b
    assert not any((tmp_path / name / tri.CACHE_DIR).exists() for name in ("scene-a", "scene-b"))


def test_trainer_falls_back_to_random_points_when_triangulation_and_the_sweep_fail(photographed, tmp_path, monkeypatch):
    import metegs.data.plane_sweep as sweep
    from metegs.engine.config import TrainConfig

    scene, paths = photographed
    posed_only = subset(scene, paths, source=None)

    def failing(*args, **kwargs):
        raise RuntimeError("only 3 points could be triangulated")

    monkeypatch.setattr(tri, "triangulate_known_poses", failing)
    monkeypatch.setattr(sweep, "plane_sweep_points", lambda *a, **k: (np.zeros((7, 3), "f4"), np.zeros((7, 3), "f4")))
    trainer = TrainConfig(max_steps=1, progress=False, output_dir=tmp_path / "runs").setup(scene=posed_only)
    assert trainer.random_init and "only 3 points" in trainer.decisions["init"]
    assert "the plane sweep found 7 points" in trainer.decisions["init"]


def test_where_the_sweep_fails_the_triangulated_points_start(photographed, tmp_path, monkeypatch, fake_triangulation):
    """A sweep that finds too few points (a scene without texture) leaves the start to the triangulated points."""
    import metegs.data.plane_sweep as sweep
    from metegs.engine.config import TrainConfig

    scene, paths = photographed
    calls, points = fake_triangulation
    monkeypatch.setattr(sweep, "plane_sweep_points", lambda *a, **k: (np.zeros((7, 3), "f4"), np.zeros((7, 3), "f4")))
    config = TrainConfig(max_steps=1, progress=False, output_dir=tmp_path / "runs")
    trainer = config.setup(scene=subset(scene, paths, source=None))
    assert len(calls) == 1 and not trainer.random_init and not trainer.swept_init
    assert len(trainer.model) == len(points) and trainer.triangulated_points is None
    assert "500 points triangulated" in trainer.decisions["init"]
    assert "the plane sweep found too few: the plane sweep found 7 points" in trainer.decisions["init"]


def test_trainer_without_pycolmap_sweeps_the_views_and_says_why(photographed, tmp_path, monkeypatch):
    """A machine without pycolmap (a GPU image with only the training packages) starts from the plane sweep."""
    import sys

    from metegs.engine.config import TrainConfig

    scene, paths = photographed
    monkeypatch.setitem(sys.modules, "pycolmap", None)  # import pycolmap raises ImportError
    trainer = TrainConfig(max_steps=1, progress=False, output_dir=tmp_path / "runs").setup(
        scene=subset(scene, paths, source=None)
    )
    assert not trainer.random_init and "pycolmap is not installed" in trainer.decisions["init"]
    assert "plane sweep" in trainer.decisions["init"]


def test_resuming_or_reopening_a_run_does_not_triangulate_again(photographed, tmp_path, fake_triangulation):
    from metegs.engine.config import TrainConfig
    from metegs.gaussians.ply import load_ply, save_ply

    scene, paths = photographed
    posed_only = subset(scene, paths, source=tmp_path)
    calls, _ = fake_triangulation
    config = TrainConfig(max_steps=2, progress=False, output_dir=tmp_path / "runs")
    trainer = config.setup(scene=posed_only)
    trainer.train_step(trainer.dataset.train_indices[0])
    trainer.step = 1
    ckpt = trainer.save()
    assert len(calls) == 1

    resumed = replace(config, load_checkpoint=ckpt).setup(scene=posed_only)
    assert len(calls) == 1, "a resumed run rebuilt (triangulated) the initial Gaussians it then replaced"
    assert resumed.step == 1 and not resumed.random_init and len(calls) == 1
    for name, value in trainer.model.params.items():
        assert torch.equal(resumed.model.params[name], value), name

    save_ply(trainer.model, tmp_path / "scene.ply")
    reopened = config.setup(scene=posed_only, model=load_ply(tmp_path / "scene.ply"))
    assert len(calls) == 1 and len(reopened.model) == len(trainer.model)


def test_a_trainer_starts_from_the_sweep_and_keeps_the_triangulated_points(photographed, tmp_path, fake_triangulation):
    """By default a poses-only capture starts from the plane sweep's points where triangulation works but covers
    little of the views (500 points in a blob), says so, and keeps the triangulated points (for the weather's
    measures), also when the run is resumed."""
    from metegs.engine.config import TrainConfig

    scene, paths = photographed
    calls, points = fake_triangulation
    config = TrainConfig(max_steps=2, progress=False, output_dir=tmp_path / "runs")
    config = replace(config, model=replace(config.model, init_random_points=3000))
    posed_only = subset(scene, paths, source=tmp_path)
    trainer = config.setup(scene=posed_only)
    assert len(calls) == 1 and not trainer.random_init and trainer.swept_init
    assert np.array_equal(trainer.triangulated_points, points)
    assert "plane sweep" in trainer.decisions["init"] and "--model.no-sweep-init" in trainer.decisions["init"]
    assert f"the {len(points)} points triangulated from them, covering 0." in trainer.decisions["init"]
    assert "(under 0.55; the sweep's 0." in trainer.decisions["init"]
    assert 1000 <= len(trainer.model) <= 3000
    err = relative_depth_error(scene, trainer.model.means.detach().numpy())
    assert np.median(err) < 0.02, np.median(err)
    trainer.step = 1
    resumed = replace(config, load_checkpoint=trainer.save()).setup(scene=posed_only)
    assert len(calls) == 1 and resumed.swept_init and np.array_equal(resumed.triangulated_points, points)


def test_fog_is_measured_at_the_triangulated_points_beside_the_sweep(photographed, tmp_path, monkeypatch):
    """Blind in fog, a run that starts from the sweep reads how far apart the views see the scene at the
    triangulated points, as a triangulated start does (the fox in metegs's own 200 m fog: 24.08 dB, against 23.43
    with the spread left unmeasured and 24.04 from the triangulated points), not as from a sweep that replaced a
    failed triangulation."""
    from metegs.engine.metegs_config import MeteGSConfig
    from metegs.weather.conditions import ConditionsConfig

    scene, paths = photographed
    exact = np.asarray(scene.points, np.float32)

    def surface(image_paths, cameras, cache_dir, opts=None):
        return tri.TriangulatedPoints(exact, np.full_like(exact, 0.5), len(image_paths), 0.5, cache=None)

    monkeypatch.setattr(tri, "triangulate_known_poses", surface)
    config = MeteGSConfig(
        method="metegs-full",
        max_steps=1,
        progress=False,
        output_dir=tmp_path / "runs",
        compare_baseline=False,
        clean_supervision=False,
        conditions=ConditionsConfig(precip_mm_h=0.0, visibility_m=300.0, metres_per_unit=100.0),
    )
    config = replace(config, model=replace(config.model, init_random_points=3000, sweep_below_coverage=1.0))
    trainer = config.setup(scene=subset(scene, paths, source=tmp_path))
    assert trainer.swept_init
    seen = trainer.decisions["dark channel prior"]  # 12 neighbouring views: the medium's rule says what they see
    assert "plane sweep" not in seen and "the views see a scene point from distances 1.3" in seen, seen


def test_view_coverage_counts_the_cells_that_hold_a_point(photographed):
    """Points on the rays of the left half of a 320x240 view's pixels cover half its 32x24 cells; points behind
    the camera or outside the image cover none."""
    from metegs.data.plane_sweep import _rays, view_coverage

    scene, _ = photographed
    cam = scene.cameras[[0]]
    origin, dirs = _rays(cam, 0, 240, 320)
    left = dirs.reshape(240, 320, 3)[:, :160].reshape(-1, 3)
    assert view_coverage((origin + 2.0 * left).numpy(), cam) == pytest.approx(0.5)
    assert view_coverage((origin - 2.0 * left).numpy(), cam) == 0.0
    every = (origin + 3.0 * dirs).numpy()
    assert view_coverage(every, cam) == pytest.approx(1.0)
    assert view_coverage(every, scene.cameras[[0, 0]], cells=8) == pytest.approx(1.0)
    # rows just under the image fall in its last, partial row of cells (7 along 320 px: 45.7 px each), but not in it
    origin, below = _rays(cam, 0, 250, 320)
    below = below.reshape(250, 320, 3)[240:].reshape(-1, 3)
    assert view_coverage((origin + 2.0 * below).numpy(), cam, cells=7) == 0.0


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_the_start_reads_cameras_on_the_training_device(photographed):
    """A CUDA run's cameras live on the GPU: the coverage, the caches' keys and the sweep read them there as on the
    CPU (a lent H100 found all three refusing them)."""
    from metegs.data.plane_sweep import _rays, plane_sweep_points, view_coverage

    scene, paths = photographed
    cams = scene.cameras[list(range(VIEWS))]
    origin, dirs = _rays(cams, 0, 240, 320)
    points = (origin + 2.0 * dirs.reshape(240, 320, 3)[:, :160].reshape(-1, 3)).numpy()
    assert view_coverage(points, cams.to("cuda")) == view_coverage(points, cams)
    assert tri.cache_key(paths, cams.to("cuda"), "v", "") == tri.cache_key(paths, cams, "v", "")
    images = [img.cuda() for img in scene.images[:VIEWS]]
    swept = plane_sweep_points(images, cams.to("cuda"), max_points=500)
    assert np.array_equal(swept[0], plane_sweep_points(scene.images[:VIEWS], cams, max_points=500)[0])


@pytest.mark.parametrize("dense", [True, False])
def test_triangulated_points_that_cover_the_views_start_without_a_sweep(photographed, tmp_path, monkeypatch, dense):
    """The synthetic scene's 4000 surface points cover 0.73 of the views: the Gaussians start from them and no sweep
    runs; every 20th of them covers 0.13, and the sweep starts beside them (`model.sweep_below_coverage`)."""
    import metegs.data.plane_sweep as sweep
    from metegs.engine.config import TrainConfig

    scene, paths = photographed
    exact = np.asarray(scene.points, np.float32)[:: 1 if dense else 20]

    def surface(image_paths, cameras, cache_dir, opts=None):
        return tri.TriangulatedPoints(exact, np.full_like(exact, 0.5), len(image_paths), 0.5, cache=None)

    swept = []
    real_sweep = sweep.plane_sweep_points
    monkeypatch.setattr(tri, "triangulate_known_poses", surface)
    monkeypatch.setattr(sweep, "plane_sweep_points", lambda *a, **k: swept.append(1) or real_sweep(*a, **k))
    config = TrainConfig(max_steps=1, progress=False, output_dir=tmp_path / "runs")
    config = replace(config, model=replace(config.model, init_random_points=3000))
    trainer = config.setup(scene=subset(scene, paths, source=None))
    decision = trainer.decisions["init"]
    assert trainer.swept_init == (not dense) and bool(swept) == (not dense)
    if dense:
        assert len(trainer.model) == len(exact) and trainer.triangulated_points is None
        assert "no sweep" in decision and "--model.sweep-below-coverage 0.55" in decision, decision
    else:
        assert np.array_equal(trainer.triangulated_points, exact) and "plane sweep" in decision
        assert "covering 0.1" in decision and "(under 0.55; the sweep's 0." in decision, decision


def test_sparse_triangulated_points_start_where_the_sweep_covers_no_more(photographed, tmp_path, monkeypatch):
    """A sweep whose points cover less of the views than sparse triangulated points (a street whose views look along
    it: the Lund street without its SfM points triangulates about 1100 covering 0.14-0.15, its sweep's 2322 cover
    0.12) does not replace them."""
    import metegs.data.plane_sweep as sweep
    from metegs.engine.config import TrainConfig

    scene, paths = photographed
    sparse = np.asarray(scene.points, np.float32)[::20]  # covers 0.13 of the views

    def surface(image_paths, cameras, cache_dir, opts=None):
        return tri.TriangulatedPoints(sparse, np.full_like(sparse, 0.5), len(image_paths), 0.5, cache=None)

    one_spot = np.repeat(sparse[:1], 300, axis=0)  # 300 points, one cell of each view that sees them
    monkeypatch.setattr(tri, "triangulate_known_poses", surface)
    monkeypatch.setattr(sweep, "plane_sweep_points", lambda *a, **k: (one_spot, np.full_like(one_spot, 0.5)))
    config = TrainConfig(max_steps=1, progress=False, output_dir=tmp_path / "runs")
    trainer = config.setup(scene=subset(scene, paths, source=None))
    decision = trainer.decisions["init"]
    assert not trainer.swept_init and not trainer.random_init and len(trainer.model) == len(sparse)
    assert "the plane sweep's 300 points no more" in decision, decision
