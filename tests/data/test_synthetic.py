"""The procedural default scene: determinism, exact depth, points on surfaces, valid cameras."""

import numpy as np
import pytest
import torch

from metegs.data.config import DatasetConfig, SyntheticSceneConfig
from metegs.data.parsers.base import parse_scene
from metegs.errors import DataError


def build(**kw):
    return parse_scene(None, None, DatasetConfig(synthetic=SyntheticSceneConfig(**{"width": 64, "height": 48, "num_views": 16, "num_points": 500, **kw})))


@pytest.fixture(scope="module")
def scene():
    return build()


def backproject(scene, view, rows, cols):
    """World points of pixel centres (rows, cols) of ``view`` at their exact depth. -> [K, 3]."""
    cam = scene.cameras[view]
    z = scene.depths[view][rows, cols].astype(np.float64)
    x = (cols + 0.5 - float(cam.cx[0])) / float(cam.fx[0]) * z
    y = (rows + 0.5 - float(cam.cy[0])) / float(cam.fy[0]) * z
    c2w = cam.camera_to_worlds[0].double().numpy()
    return np.stack([x, y, z], 1) @ c2w[:3, :3].T + c2w[:3, 3]


def project(scene, view, points):
    """Pixel coordinates and z-depths of world points in ``view``. -> ([K, 2], [K])."""
    w2c = scene.cameras[view].world_to_cameras()[0].double().numpy()
    p = points @ w2c[:3, :3].T + w2c[:3, 3]
    cam = scene.cameras[view]
    u = float(cam.fx[0]) * p[:, 0] / p[:, 2] + float(cam.cx[0])
    v = float(cam.fy[0]) * p[:, 1] / p[:, 2] + float(cam.cy[0])
    return np.stack([u, v], 1), p[:, 2]


def test_shapes_ranges_and_split(scene):
    assert len(scene) == 16 and len(scene.images) == 16
    assert scene.test_indices == [0, 8] and len(scene.train_indices) == 14
    for img, depth in zip(scene.images, scene.depths):
        assert img.shape == (48, 64, 3) and img.dtype == np.float32
        assert 0.0 <= img.min() and img.max() <= 1.0
        assert depth.shape == (48, 64) and np.isfinite(depth).all() and (depth > 0).all()
    assert scene.points.shape == (500, 3) and scene.point_colors.shape == (500, 3)
    assert scene.metric_scale == 1.0 and np.allclose(scene.up, [0, 0, 1])
    assert torch.allclose(scene.cameras.exposure_time_s, torch.tensor(1 / 250))
    scene.cameras.validate("synthetic")


def test_views_show_structure(scene):
    """Not a blank or flat image: enough contrast for reconstruction to mean something."""
    for img in scene.images:
        assert img.std() > 0.05


def test_deterministic_by_seed():
    a, b, c = build(seed=3), build(seed=3), build(seed=4)
    assert all(np.array_equal(x, y) for x, y in zip(a.images, b.images))
    assert np.array_equal(a.points, b.points)
    assert not np.allclose(a.images[1], c.images[1])


def test_ground_pixels_backproject_to_z_zero(scene):
    """Pixels looking down hit the ground plane z = 0 (the lower image rows, near the camera)."""
    view = 3
    rows, cols = np.meshgrid(np.arange(40, 48), np.arange(0, 64, 4), indexing="ij")
    pts = backproject(scene, view, rows.ravel(), cols.ravel())
    on_ground = np.abs(pts[:, 2]) < 0.05  # some of these pixels may show an object instead
    assert on_ground.mean() > 0.5
    assert np.abs(pts[on_ground, 2]).max() < 1e-4 * np.abs(pts[on_ground]).max()


def surface_distance(p: np.ndarray, seed: int = 0) -> np.ndarray:
    """Distance of world points [K, 3] to the nearest analytic surface of the scene built from ``seed``."""
    from metegs.data.parsers.synthetic import DOME_RADIUS, make_scene

    sc = make_scene(np.random.default_rng(seed))
    d = [np.abs(p[:, 2]), np.abs(np.linalg.norm(p, axis=1) - DOME_RADIUS)]
    d += [np.abs(np.linalg.norm(p - s.center, axis=1) - s.radius) for s in sc.spheres]
    for box in sc.boxes:
        q = np.abs(box.to_local(p - box.center)) - box.half  # signed distance to a box
        outside = np.linalg.norm(np.maximum(q, 0.0), axis=1)
        d.append(np.abs(outside + np.minimum(q.max(axis=1), 0.0)))
    return np.min(d, axis=0)


def test_every_pixel_depth_lands_on_a_surface(scene):
    """The exact depth of each pixel-centre ray back-projects onto an analytic surface (ground, dome, box, sphere)."""
    for view in (0, 5, 11):
        rows, cols = np.meshgrid(np.arange(48), np.arange(64), indexing="ij")
        pts = backproject(scene, view, rows.ravel(), cols.ravel())
        assert surface_distance(pts).max() < 1e-3  # metres; float32 cameras over a 20 m dome


def test_points_lie_on_visible_surfaces(scene):
    """Each initialisation point, seen from a training view in front of it, is at the depth that view records."""
    hits = 0
    for view in scene.train_indices[:6]:
        uv, z = project(scene, view, scene.points.astype(np.float64))
        inside = (uv[:, 0] >= 0) & (uv[:, 0] < 64) & (uv[:, 1] >= 0) & (uv[:, 1] < 48) & (z > 0)
        pix = np.floor(uv[inside]).astype(int)
        observed = scene.depths[view][pix[:, 1], pix[:, 0]]
        hits += int((np.abs(observed - z[inside]) < 0.03 * z[inside] + 0.05).sum())
    assert hits > 300


def test_bad_size_is_a_clear_error():
    with pytest.raises(DataError, match="width and height"):
        build(width=0)
