"""The procedural default scene: determinism, exact depth, points on surfaces, valid cameras."""

import numpy as np
import pytest
import torch

from metegs.data.config import DatasetConfig, SyntheticSceneConfig
from metegs.data.parsers.base import parse_scene
from metegs.errors import DataError


def build(**kw):
    return parse_scene(
        None,
        None,
        DatasetConfig(
            synthetic=SyntheticSceneConfig(**{"width": 64, "height": 48, "num_views": 16, "num_points": 500, **kw})
        ),
    )


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
    assert scene.metric_scale == SyntheticSceneConfig().metres_per_unit and np.allclose(scene.up, [0, 0, 1])
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
    assert not np.allclose(a.points, c.points)


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
    """Initialisation points are exact surface points, each seen through a pixel centre of a training view."""
    points = scene.points.astype(np.float64)
    assert surface_distance(points).max() < 1e-3
    found = np.zeros(len(points), dtype=bool)
    for view in scene.train_indices:
        uv, z = project(scene, view, points)
        pix = np.round(uv - 0.5).astype(int)
        inside = (pix[:, 0] >= 0) & (pix[:, 0] < 64) & (pix[:, 1] >= 0) & (pix[:, 1] < 48) & (z > 0)
        centred = inside & (np.abs(uv - 0.5 - pix).max(axis=1) < 1e-3)
        observed = scene.depths[view][pix[centred, 1], pix[centred, 0]]
        found[np.flatnonzero(centred)[np.abs(observed - z[centred]) < 1e-4 * z[centred]]] = True
    assert found.all()
    assert 0.0 <= scene.point_colors.min() and scene.point_colors.max() <= 1.0


def test_depth_is_consistent_across_views(scene):
    """A pixel back-projected with its depth and re-projected into the next view lands where that view sees it."""
    rows, cols = np.meshgrid(np.arange(2, 46, 2), np.arange(2, 62, 2), indexing="ij")
    for a, b in ((1, 2), (5, 6), (9, 10)):
        pts = backproject(scene, a, rows.ravel(), cols.ravel())
        uv, z = project(scene, b, pts)
        x, y = uv[:, 0] - 0.5, uv[:, 1] - 0.5  # continuous pixel-centre coordinates
        inside = (x >= 0) & (x < 63) & (y >= 0) & (y < 47) & (z > 0)
        x, y, z = x[inside], y[inside], z[inside]
        x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
        fx, fy = x - x0, y - y0
        dm = scene.depths[b].astype(np.float64)
        corners = np.stack([dm[y0, x0], dm[y0, x0 + 1], dm[y0 + 1, x0], dm[y0 + 1, x0 + 1]])
        seen = (
            corners[0] * (1 - fx) * (1 - fy)
            + corners[1] * fx * (1 - fy)
            + corners[2] * (1 - fx) * fy
            + corners[3] * fx * fy
        )
        smooth = corners.max(0) < 1.1 * corners.min(0)  # away from silhouettes and occlusion boundaries
        rel = (seen - z)[smooth] / z[smooth]
        assert smooth.sum() > 0.5 * inside.sum()
        # Most points are seen right where they are; the rest are occluded in view b (seen nearer), never farther.
        assert np.median(np.abs(rel)) < 1e-3 and (np.abs(rel) < 0.01).mean() > 0.5
        assert rel.max() < 0.05


def test_orbit_covers_360_degrees_and_fov():
    """Cameras ring the scene (every test view lies between training views) with a ~60 degree horizontal FOV."""
    sc = build(num_views=48, width=32, height=24, num_points=10)
    centers = sc.cameras.centers.double().numpy()
    radius = np.hypot(centers[:, 0], centers[:, 1])
    assert (radius >= 6.0 - 1e-4).all() and (radius <= 9.0 + 1e-4).all()
    assert (centers[:, 2] >= 1.5 - 1e-4).all() and (centers[:, 2] <= 3.5 + 1e-4).all()
    azimuth = np.sort(np.arctan2(centers[:, 1], centers[:, 0]))
    gaps = np.diff(np.concatenate([azimuth, azimuth[:1] + 2 * np.pi]))
    assert gaps.max() < 2 * (2 * np.pi / 48)
    forward = sc.cameras.camera_to_worlds[:, :3, 2].double().numpy()  # optical axes point at the scene centre
    to_center = -centers / np.linalg.norm(centers, axis=1, keepdims=True)
    assert (np.einsum("ij,ij->i", forward, to_center) > 0.9).all()
    hfov = 2 * np.degrees(np.arctan(16 / sc.cameras.fx.double().numpy()))
    assert np.allclose(hfov, 60.0, atol=0.01)


def test_parser_protocol_and_fields(scene):
    from metegs.data.parsers.synthetic import SyntheticParser

    assert SyntheticParser.priority == 1000 and SyntheticParser.can_parse(None) is False
    assert scene.parser == "synthetic" and scene.source is None and scene.image_space == "srgb"
    assert scene.names[:2] == ["view_000", "view_001"] and len(scene.names) == 16
    assert all(c is i for c, i in zip(scene.clean_images, scene.images))
    assert scene.image_paths is None


def test_no_test_views_and_no_points():
    sc = parse_scene(
        None,
        "synthetic",
        DatasetConfig(test_every=0, synthetic=SyntheticSceneConfig(width=16, height=12, num_views=3, num_points=0)),
    )
    assert sc.test_indices == [] and sc.train_indices == [0, 1, 2]
    assert sc.points.shape == (0, 3) and sc.point_colors.shape == (0, 3)


def test_bad_size_is_a_clear_error():
    with pytest.raises(DataError, match="width and height"):
        build(width=0)
