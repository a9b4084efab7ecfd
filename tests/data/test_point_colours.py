"""Points take their colours from the photos that see them: degraded copies carry nothing of the clean photos."""

from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest
import torch

from metegs.cameras import Cameras
from metegs.data.point_colours import UNSEEN_COLOUR, colours_seen, recolour_colmap_model

W, H = 32, 24


def two_cameras() -> Cameras:
    """OpenCV cameras at x = 0 and x = 1 looking down +z."""
    c2w = torch.eye(4).repeat(2, 1, 1)
    c2w[1, 0, 3] = 1.0
    return Cameras.create(c2w, 20.0, 20.0, W / 2, H / 2, W, H)


def test_a_point_takes_the_mean_colour_of_the_views_that_see_it_in_front_of_their_surface():
    images = [np.full((H, W, 3), 0.2, np.float32), np.full((H // 2, W // 2, 3), 0.6, np.float32)]  # any size
    points = np.array(
        [
            [0.5, 0.0, 5.0],  # both views see it
            [0.0, 0.0, 9.0],  # behind view 0's surface at 6: only view 1 (no depth there)
            [0.0, 0.0, -3.0],  # behind both cameras
            [40.0, 0.0, 5.0],  # outside both images
        ]
    )
    depths = [np.full((H, W), 6.0, np.float32), np.full((H, W), np.nan, np.float32)]
    got = colours_seen(points, two_cameras(), images, depths)
    np.testing.assert_allclose(got[0], 0.4, atol=1e-6)
    np.testing.assert_allclose(got[1], 0.6, atol=1e-6)
    np.testing.assert_allclose(got[2:], UNSEEN_COLOUR)
    np.testing.assert_allclose(colours_seen(points, two_cameras(), images)[1], 0.4, atol=1e-6)  # without depths


def test_through_a_medium_the_colour_is_the_least_squares_fit_of_t_c_plus_airlight():
    # two views see two points through a medium; each photo shows t·c + (1 − t)·A with the view's own t
    clean = np.array([[0.1, 0.5, 0.9], [0.3, 0.2, 0.7]])
    airlight = np.array([0.9, 0.85, 0.8])
    points = np.array([[0.5, 0.0, 5.0], [0.5, 0.0, 3.0]])
    t = np.array([[0.7, 0.2], [0.4, 0.9]])  # [view, point]
    cams = two_cameras()
    w2c = cams.world_to_cameras().numpy()
    images = []
    for i in range(2):
        image = np.zeros((H, W, 3), np.float32)
        for k, p in enumerate(points):
            x, y, z = w2c[i, :3, :3] @ p + w2c[i, :3, 3]
            u, v = int(20.0 * x / z + W / 2), int(20.0 * y / z + H / 2)
            image[v, u] = t[i, k] * clean[k] + (1 - t[i, k]) * airlight
        images.append(image)
    exact = colours_seen(points, cams, images, transmittance=lambda i: t[i], airlight=airlight, shrink=0.0)
    np.testing.assert_allclose(exact, clean, atol=1e-6)
    hazed = colours_seen(points, cams, images)  # no medium: the photos' mean, airlight and all
    assert np.abs(hazed - clean).max() > 0.2
    # where the medium hides a point from every view, the fit stays at the photos' mean instead of dividing by t
    hidden = colours_seen(points, cams, images, transmittance=lambda i: np.full(2, 1e-4), airlight=airlight)
    np.testing.assert_allclose(hidden, hazed, atol=1e-3)
    shrunk = colours_seen(points, cams, images, transmittance=lambda i: t[i], airlight=airlight)  # shrink 0.1
    assert np.abs(shrunk - clean).max() < np.abs(hazed - clean).max() / 2


def colmap_model(root: Path, text: bool) -> Path:
    """``root/images`` with three 32x24 photos (view i: value 40·(i+1) in every channel, plus 5 per column in red)
    and ``root/sparse/0``: 5 points coloured (200, 120, 40), the first 3 seen at (4.5 + 3k, 6.5) in every view."""
    (root / "images").mkdir(parents=True)
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(pycolmap.Camera.create_from_model_name(1, "PINHOLE", 30.0, W, H))
    for i in range(3):
        photo = np.full((H, W, 3), 40 * (i + 1), np.uint8)
        photo[..., 0] += (5 * np.arange(W)).astype(np.uint8)[None]
        cv2.imwrite(str(root / "images" / f"im_{i}.png"), cv2.cvtColor(photo, cv2.COLOR_RGB2BGR))
        pts = pycolmap.Point2DList([pycolmap.Point2D(np.array([4.5 + 3 * k, 6.5])) for k in range(3)])
        image = pycolmap.Image(name=f"im_{i}.png", points2D=pts, camera_id=1, image_id=i + 1)
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(np.eye(3)), np.array([0.1 * i, 0.0, 0.0]))
        rec.add_image_with_trivial_frame(image, pose)
    for k in range(5):
        track = pycolmap.Track()
        for i in range(3 if k < 3 else 0):
            track.add_element(i + 1, k)
        rec.add_point3D(np.array([0.1 * k, 0.0, 4.0]), track, np.array([200, 120, 40], np.uint8))
    (root / "sparse" / "0").mkdir(parents=True)
    (rec.write_text if text else rec.write_binary)(str(root / "sparse" / "0"))
    return root / "sparse" / "0"


@pytest.mark.parametrize("text", [False, True])
def test_a_colmap_models_points_take_the_mean_of_their_tracks_pixels(tmp_path, text):
    model_dir = colmap_model(tmp_path, text)
    found = recolour_colmap_model(model_dir, lambda name: tmp_path / "images" / name)
    assert found == 3
    assert (model_dir / ("points3D.txt" if text else "points3D.bin")).exists()
    assert not (model_dir / ("points3D.bin" if text else "points3D.txt")).exists()
    back = pycolmap.Reconstruction(str(model_dir))
    colours = {pid: p.color.tolist() for pid, p in back.points3D.items()}
    for k, pid in enumerate(sorted(colours)):
        if k < 3:  # column 4 + 3k, row 6 in views of value 40, 80, 120
            assert colours[pid] == [80 + 5 * (4 + 3 * k), 80, 80], k
        else:  # no track: nothing to read, and nothing of the old colour kept
            assert colours[pid] == [128, 128, 128]
    gone = recolour_colmap_model(model_dir, lambda name: None if name == "im_0.png" else tmp_path / "images" / name)
    assert gone == 3
    first = pycolmap.Reconstruction(str(model_dir)).points3D[sorted(colours)[0]].color.tolist()
    assert first == [100 + 5 * 4, 100, 100]  # views 1 and 2 only


def test_a_degraded_colmap_copy_colours_its_points_from_the_degraded_photos(tmp_path):
    from metegs.data.config import DatasetConfig
    from metegs.data.parsers.base import parse_scene
    from metegs.files import staged_output
    from metegs.meteo import theta_from_values
    from metegs.synth.writers import DatasetWriter
    from metegs.weather.conditions import camera_spec
    from metegs.weather.degrade import degrade_scene

    colmap_model(tmp_path / "scene", text=False)
    scene = parse_scene(tmp_path / "scene", None, DatasetConfig())
    theta = theta_from_values(
        0.0, visibility_m=5.0, fog_kind="fog", camera=camera_spec(scene.cameras, capture_width_px=0, far_m=5.0)
    )
    foggy, _ = degrade_scene(scene, theta, kinds="fog", depths=[np.full((H, W), 4.0, np.float32)] * 3)
    assert np.abs(foggy.point_colors - scene.point_colors).max() > 0.1  # in memory: the fog's colours
    with staged_output(tmp_path / "out") as tmp:
        writer = DatasetWriter(scene, tmp)
        for i in range(3):
            writer.write_view(i, foggy.images[i], foggy.clean_images[i])
        writer.finish()
    back = pycolmap.Reconstruction(str(tmp_path / "out" / "sparse" / "0"))
    photos = [cv2.imread(str(tmp_path / "out" / "images" / f"im_{i}.png"))[..., ::-1] for i in range(3)]
    for point in back.points3D.values():
        if point.track.length() == 0:
            continue
        k = int(round(point.xyz[0] / 0.1))
        expected = np.mean([p[6, 4 + 3 * k].astype(float) for p in photos], axis=0)
        assert np.abs(point.color.astype(float) - expected).max() <= 1.0, (k, point.color, expected)
        assert point.color.tolist() != [200, 120, 40]
    again = parse_scene(tmp_path / "out", None, DatasetConfig())
    assert np.abs(again.point_colors - scene.point_colors).max() > 0.1
