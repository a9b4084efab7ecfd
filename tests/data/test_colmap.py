"""COLMAP parser: small models written with pycolmap (binary and text) plus synthetic PNG images."""

from __future__ import annotations

import warnings
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest

import metegs.builtins  # noqa: F401  (registers the parsers)
from metegs.data.config import DatasetConfig
from metegs.data.images import load_image
from metegs.data.parsers.base import parse_scene
from metegs.data.parsers.colmap import ColmapParser
from metegs.data.undistort import CACHE_DIR
from metegs.errors import DataError

W, H = 160, 120
POINTS = np.array([[0.0, 0.0, 0.0], [0.3, -0.2, 0.1], [-0.25, 0.15, -0.3]])


def look_at_w2c(center: np.ndarray, target=np.zeros(3), up=np.array([0.0, 0.0, 1.0])) -> np.ndarray:
    """[3, 4] world-to-camera (OpenCV axes) of a camera at ``center`` looking at ``target``."""
    z = target - center
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return np.concatenate([R, (-R @ center)[:, None]], axis=1)


def make_model(
    root: Path,
    model: str = "PINHOLE",
    params=None,
    n_images: int = 3,
    text: bool = False,
    folder: str = "sparse/0",
    write_images: bool = True,
) -> pycolmap.Reconstruction:
    """Write a COLMAP model with ``n_images`` cameras on a circle around the origin into ``root/folder``."""
    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera.create_from_model_name(1, model, 100.0, W, H)
    if params is not None:
        cam.params = params
    rec.add_camera_with_trivial_rig(cam)
    for i in range(n_images):
        angle = 2 * np.pi * i / max(n_images, 1)
        center = np.array([3.0 * np.cos(angle), 3.0 * np.sin(angle), 0.5 + 0.1 * i])
        w2c = look_at_w2c(center)
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(w2c[:, :3]), w2c[:, 3])
        # Names deliberately not in id order, to test sorting.
        image = pycolmap.Image(name=f"img_{n_images - i:02d}.png", camera_id=1, image_id=i + 1)
        rec.add_image_with_trivial_frame(image, pose)
    for k, p in enumerate(POINTS):
        rec.add_point3D(p, pycolmap.Track(), np.array([255, 10 * k, 0], dtype=np.uint8))
    out = root / folder
    out.mkdir(parents=True, exist_ok=True)
    (rec.write_text if text else rec.write)(str(out))
    if write_images:
        (root / "images").mkdir(exist_ok=True)
        for im in rec.images.values():
            img = np.full((H, W, 3), 40 + 10 * im.image_id, dtype=np.uint8)
            cv2.imwrite(str(root / "images" / im.name), img)
    return rec


def project(scene, i: int, xyz: np.ndarray) -> np.ndarray:
    """Pixel (u, v) of world point ``xyz`` in view ``i`` with our pinhole Cameras (pixel centres at +0.5)."""
    w2c = scene.cameras.world_to_cameras()[i].double().numpy()
    pc = w2c[:3, :3] @ xyz + w2c[:3, 3]
    K = scene.cameras.intrinsics()[i].double().numpy()
    uvw = K @ pc
    return uvw[:2] / uvw[2]


@pytest.mark.parametrize("text", [False, True], ids=["binary", "text"])
def test_pinhole_model_round_trip(tmp_path, text):
    rec = make_model(tmp_path, "PINHOLE", [110.0, 105.0, 81.0, 59.5], text=text)
    scene = parse_scene(tmp_path, None, DatasetConfig(test_every=2))
    assert scene.parser == "colmap"
    assert scene.names == ["img_01.png", "img_02.png", "img_03.png"]
    assert [p.name for p in scene.image_paths] == scene.names
    assert scene.train_indices == [1] and scene.test_indices == [0, 2]
    assert scene.cameras.fx[0] == pytest.approx(110.0) and scene.cameras.fy[0] == pytest.approx(105.0)
    assert scene.cameras.cx[0] == pytest.approx(81.0) and scene.cameras.cy[0] == pytest.approx(59.5)
    assert scene.cameras.width.tolist() == [W] * 3 and scene.cameras.height.tolist() == [H] * 3
    by_name = {im.name: im for im in rec.images.values()}
    for i, name in enumerate(scene.names):
        for xyz in POINTS:
            expected = by_name[name].project_point(xyz)
            np.testing.assert_allclose(project(scene, i, xyz), expected, atol=2e-3)
        center = by_name[name].projection_center()
        np.testing.assert_allclose(scene.cameras.centers[i].numpy(), center, atol=1e-5)
    np.testing.assert_allclose(np.sort(scene.points[:, 0]), np.sort(POINTS[:, 0]), atol=1e-6)
    assert scene.point_colors.max() == pytest.approx(1.0) and scene.point_colors.dtype == np.float32
    assert scene.up @ np.array([0.0, 0.0, 1.0]) > 0.9  # cameras were upright about world +z
    assert scene.metric_scale is None


def test_simple_pinhole_and_legacy_layout(tmp_path):
    """SIMPLE_PINHOLE, and a pre-3.12 model (no rigs/frames files) directly in sparse/."""
    make_model(tmp_path, "SIMPLE_PINHOLE", [90.0, 80.0, 60.0], folder="sparse")
    for extra in ("rigs.bin", "frames.bin"):
        (tmp_path / "sparse" / extra).unlink()
    assert ColmapParser.can_parse(tmp_path)
    scene = ColmapParser().parse(tmp_path, DatasetConfig())
    assert len(scene) == 3
    assert scene.cameras.fx.tolist() == scene.cameras.fy.tolist() == [90.0] * 3


def test_picks_model_with_most_registered_images(tmp_path):
    make_model(tmp_path, n_images=2, folder="sparse/0")
    make_model(tmp_path, n_images=4, folder="sparse/1")
    scene = ColmapParser().parse(tmp_path, DatasetConfig())
    assert len(scene) == 4


def test_missing_image_files_are_skipped_with_one_warning(tmp_path):
    make_model(tmp_path, n_images=3)
    (tmp_path / "images" / "img_02.png").unlink()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        scene = ColmapParser().parse(tmp_path, DatasetConfig())
    assert scene.names == ["img_01.png", "img_03.png"]
    assert len(caught) == 1 and "img_02.png" in str(caught[0].message)


def test_missing_image_folder(tmp_path):
    make_model(tmp_path, write_images=False)
    with pytest.raises(DataError, match="images"):
        ColmapParser().parse(tmp_path, DatasetConfig())


def _blob(u: float, v: float, sigma: float = 1.5) -> np.ndarray:
    """H x W float image with a Gaussian blob centred on COLMAP pixel coordinates (u, v)."""
    xs = np.arange(W) + 0.5
    ys = np.arange(H) + 0.5
    return np.exp(-((xs[None, :] - u) ** 2 + (ys[:, None] - v) ** 2) / (2 * sigma**2))


def _centroid(grey: np.ndarray) -> np.ndarray:
    w = np.clip(grey - 0.05, 0.0, None)
    ys, xs = np.mgrid[:H, :W] + 0.5
    return np.array([(w * xs).sum(), (w * ys).sum()]) / w.sum()


@pytest.mark.parametrize("text", [False, True], ids=["binary", "text"])
def test_opencv_model_is_undistorted(tmp_path, text):
    params = [100.0, 102.0, 79.0, 61.0, -0.25, 0.05, 0.002, -0.001]
    rec = make_model(tmp_path, "OPENCV", params, n_images=2, text=text)
    target = np.array([0.6, 0.0, 0.55])  # a world point imaged far from the centre
    by_name = {im.name: im for im in rec.images.values()}
    distorted_uv = {}
    for name, im in by_name.items():
        distorted_uv[name] = im.project_point(target)  # pycolmap applies the distortion
        img = (np.repeat(_blob(*distorted_uv[name])[:, :, None], 3, axis=2) * 255).round().astype(np.uint8)
        cv2.imwrite(str(tmp_path / "images" / name), img)

    scene = ColmapParser().parse(tmp_path, DatasetConfig(undistort=True))
    for i, name in enumerate(scene.names):
        path = scene.image_paths[i]
        assert CACHE_DIR in path.parts and path.is_file()
        undistorted = load_image(path)
        assert undistorted.shape == (H, W, 3)
        expected = project(scene, i, target)
        assert np.linalg.norm(expected - distorted_uv[name]) > 2.0  # the distortion matters here
        np.testing.assert_allclose(_centroid(undistorted[:, :, 0]), expected, atol=0.3)

    # The cache is reused on the next parse (same files, not rewritten).
    mtimes = [p.stat().st_mtime_ns for p in scene.image_paths]
    again = ColmapParser().parse(tmp_path, DatasetConfig(undistort=True))
    assert again.image_paths == scene.image_paths
    assert [p.stat().st_mtime_ns for p in again.image_paths] == mtimes
    assert not list((tmp_path / CACHE_DIR).glob("*.tmp*")) and not list((tmp_path / CACHE_DIR).glob("tmp*"))


def test_distorted_model_refused_without_undistort(tmp_path):
    make_model(tmp_path, "OPENCV", [100.0, 100.0, 80.0, 60.0, 0.1, 0.0, 0.0, 0.0])
    with pytest.raises(DataError) as err:
        ColmapParser().parse(tmp_path, DatasetConfig(undistort=False))
    msg = str(err.value)
    assert "cameras.bin" in msg and "camera 1" in msg and "OPENCV" in msg and "--dataset.undistort" in msg


def test_simple_radial_with_zero_distortion_needs_no_undistortion(tmp_path):
    make_model(tmp_path, "SIMPLE_RADIAL", [95.0, 80.0, 60.0, 0.0])
    scene = ColmapParser().parse(tmp_path, DatasetConfig(undistort=False))
    assert scene.cameras.fx[0] == pytest.approx(95.0)
    assert CACHE_DIR not in scene.image_paths[0].parts


def test_fisheye_model_is_refused(tmp_path):
    make_model(tmp_path, "OPENCV_FISHEYE", [100.0, 100.0, 80.0, 60.0, 0.1, 0.0, 0.0, 0.0], text=True)
    with pytest.raises(DataError, match="OPENCV_FISHEYE") as err:
        ColmapParser().parse(tmp_path, DatasetConfig())
    assert "cameras.txt" in str(err.value)


def test_corrupt_model_names_the_folder(tmp_path):
    (tmp_path / "sparse" / "0").mkdir(parents=True)
    (tmp_path / "sparse" / "0" / "cameras.txt").write_text("1 PINHOLE 10 10 not numbers\n")
    (tmp_path / "sparse" / "0" / "images.txt").write_text("")
    (tmp_path / "sparse" / "0" / "points3D.txt").write_text("")
    with pytest.raises(DataError, match="sparse"):
        parse_scene(tmp_path, None, DatasetConfig())


@pytest.mark.parametrize("habit", ["stem", "colmap"])
def test_masks_beside_the_images_are_read_by_either_naming_habit(tmp_path, habit):
    rec = make_model(tmp_path, n_images=3)
    (tmp_path / "masks").mkdir()
    names = sorted(im.name for im in rec.images.values())
    for name in names:  # nerfstudio/LLFF: a.png for a.jpg; COLMAP's mask_path: a.jpg.png
        mask = tmp_path / "masks" / (Path(name).stem + ".png" if habit == "stem" else name + ".png")
        cv2.imwrite(str(mask), np.full((H, W), 255, np.uint8))
    scene = parse_scene(tmp_path, None, DatasetConfig())
    assert [p.parent.name for p in scene.mask_paths] == ["masks"] * 3
    assert [p.name for p in scene.mask_paths] == [
        Path(n).stem + ".png" if habit == "stem" else n + ".png" for n in scene.names
    ]


def test_a_partial_set_of_masks_is_ignored_with_a_warning(tmp_path):
    rec = make_model(tmp_path, n_images=3)
    (tmp_path / "masks").mkdir()
    first = sorted(im.name for im in rec.images.values())[0]
    cv2.imwrite(str(tmp_path / "masks" / first), np.full((H, W), 255, np.uint8))
    with pytest.warns(UserWarning, match=r"masks: ignoring the masks, 2 image\(s\) have none"):
        scene = parse_scene(tmp_path, None, DatasetConfig())
    assert scene.mask_paths is None


def test_masks_of_distorted_views_are_undistorted_with_them(tmp_path):
    params = [100.0, 102.0, 79.0, 61.0, -0.25, 0.05, 0.002, -0.001]
    rec = make_model(tmp_path, "OPENCV", params, n_images=2)
    (tmp_path / "masks").mkdir()
    for im in rec.images.values():  # mask = image, an off-centre blob: undistorted alike, they must stay equal
        blob = (_blob(30.0 + 40 * im.image_id, 35.0) * 255).round().astype(np.uint8)
        cv2.imwrite(str(tmp_path / "images" / im.name), np.repeat(blob[:, :, None], 3, axis=2))
        cv2.imwrite(str(tmp_path / "masks" / im.name), blob)
    scene = parse_scene(tmp_path, None, DatasetConfig())
    for image, mask in zip(scene.image_paths, scene.mask_paths):
        assert CACHE_DIR in mask.parts and "masks" in mask.parts and mask != image
        undistorted = load_image(image)[..., 0]
        np.testing.assert_allclose(load_image(mask)[..., 0], undistorted, atol=1 / 255)
        assert undistorted.max() > 0.5
