"""nerfstudio transforms.json parser."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest

import metegs.builtins  # noqa: F401  (registers the parsers)
from metegs.data.config import DatasetConfig
from metegs.data.parsers.base import parse_scene
from metegs.data.parsers.nerfstudio import NerfstudioParser, read_ply_points
from metegs.errors import DataError


def gl_look_at(center) -> list[list[float]]:
    """4x4 OpenGL camera-to-world at ``center`` looking at the origin (camera -z toward it, world +z up)."""
    center = np.asarray(center, dtype=np.float64)
    back = center / np.linalg.norm(center)
    right = np.cross([0.0, 0.0, 1.0], back)
    right /= np.linalg.norm(right)
    up = np.cross(back, right)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, up, back, center
    return m.tolist()


def write_scene(root: Path, n: int = 4, shared: bool = True, missing=(), **extra) -> Path:
    """transforms.json with ``n`` frames looking at the origin; images 32x24 (frames in ``missing`` have none)."""
    (root / "images").mkdir(parents=True, exist_ok=True)
    frames = []
    for i in range(n):
        frame = {
            "file_path": f"images/frame_{i:03d}.png",
            "transform_matrix": gl_look_at([3 * np.cos(i), 3 * np.sin(i), 1.0]),
        }
        if not shared:
            frame.update(fl_x=30.0 + i, fl_y=31.0 + i, cx=16.0, cy=12.0, w=32, h=24)
        if i not in missing:
            cv2.imwrite(str(root / frame["file_path"]), np.full((24, 32, 3), 100, dtype=np.uint8))
        frames.append(frame)
    meta = {"frames": frames, **extra}
    if shared:
        meta.update(fl_x=40.0, fl_y=41.0, cx=15.5, cy=12.5, w=32, h=24)
    (root / "transforms.json").write_text(json.dumps(meta))
    return root / "transforms.json"


def test_shared_intrinsics_and_detection(tmp_path):
    write_scene(tmp_path, n=9)
    scene = parse_scene(tmp_path, None, DatasetConfig())
    assert scene.parser == "nerfstudio"
    assert len(scene) == 9 and scene.names[0] == "images/frame_000.png"
    assert scene.cameras.fx.tolist() == [40.0] * 9 and scene.cameras.fy.tolist() == [41.0] * 9
    assert scene.cameras.cx[0] == 15.5 and scene.cameras.width[0] == 32 and scene.cameras.height[0] == 24
    assert scene.test_indices == [0, 8] and len(scene.train_indices) == 7
    assert scene.points is None


def test_json_file_path_and_per_frame_intrinsics(tmp_path):
    source = write_scene(tmp_path, n=3, shared=False)
    assert NerfstudioParser.can_parse(source)
    scene = parse_scene(source, None, DatasetConfig())
    assert scene.cameras.fx.tolist() == [30.0, 31.0, 32.0]
    assert scene.cameras.fy.tolist() == [31.0, 32.0, 33.0]


def test_per_frame_override_of_shared_intrinsics(tmp_path):
    source = write_scene(tmp_path, n=2)
    meta = json.loads(source.read_text())
    meta["frames"][1]["fl_x"] = 77.0
    source.write_text(json.dumps(meta))
    scene = NerfstudioParser().parse(tmp_path, DatasetConfig())
    assert scene.cameras.fx.tolist() == [40.0, 77.0]


def test_opengl_to_opencv_origin_in_front(tmp_path):
    write_scene(tmp_path, n=4)
    scene = NerfstudioParser().parse(tmp_path, DatasetConfig())
    w2c = scene.cameras.world_to_cameras()
    origin_cam = w2c[:, :3, 3]  # the world origin in camera coordinates
    assert (origin_cam[:, 2] > 2.5).all()  # straight ahead at distance ~3.16 (positive z in OpenCV)
    assert origin_cam[:, :2].abs().max() < 1e-5
    # World +z is up in the images: OpenCV camera y (down) points to world -z.
    assert (scene.cameras.camera_to_worlds[:, 2, 1] < 0).all()


def test_missing_frames_skipped_with_one_warning(tmp_path):
    write_scene(tmp_path, n=5, missing=(1, 3))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        scene = NerfstudioParser().parse(tmp_path, DatasetConfig())
    assert len(scene) == 3
    assert len(caught) == 1
    msg = str(caught[0].message)
    assert "images/frame_001.png" in msg and "images/frame_003.png" in msg and "frame_000" not in msg


def test_explicit_split_lists(tmp_path):
    write_scene(
        tmp_path,
        n=4,
        train_filenames=["images/frame_000.png", "./images/frame_002.png"],
        test_filenames=["images/frame_001.png"],
    )
    scene = NerfstudioParser().parse(tmp_path, DatasetConfig())
    assert scene.train_indices == [0, 2] and scene.test_indices == [1]


def test_missing_transform_matrix(tmp_path):
    source = write_scene(tmp_path, n=4)
    meta = json.loads(source.read_text())
    del meta["frames"][3]["transform_matrix"]
    source.write_text(json.dumps(meta))
    with pytest.raises(DataError, match="transforms.json.*frame 3 has no 'transform_matrix'"):
        NerfstudioParser().parse(tmp_path, DatasetConfig())


def test_missing_intrinsic_and_frames(tmp_path):
    source = write_scene(tmp_path, n=2)
    meta = json.loads(source.read_text())
    del meta["fl_y"]
    source.write_text(json.dumps(meta))
    with pytest.raises(DataError, match="transforms.json.*'fl_y'"):
        NerfstudioParser().parse(tmp_path, DatasetConfig())
    source.write_text(json.dumps({"fl_x": 1.0}))
    with pytest.raises(DataError, match="transforms.json.*'frames'"):
        NerfstudioParser().parse(tmp_path, DatasetConfig())
    source.write_text("{not json")
    with pytest.raises(DataError, match="transforms.json"):
        NerfstudioParser().parse(tmp_path, DatasetConfig())


def test_what_cannot_be_undistorted_is_refused(tmp_path):
    write_scene(tmp_path, n=2, k1=0.1)
    with pytest.raises(DataError, match="distorted; rerun with --dataset.undistort"):
        NerfstudioParser().parse(tmp_path, DatasetConfig(undistort=False))
    write_scene(tmp_path, n=2, k1=0.0, p2=0.0)
    assert len(NerfstudioParser().parse(tmp_path, DatasetConfig(undistort=False))) == 2  # zeros: nothing to do
    write_scene(tmp_path, n=2, k4=0.01)
    with pytest.raises(DataError, match="k4 is only supported with camera_model OPENCV_FISHEYE"):
        NerfstudioParser().parse(tmp_path, DatasetConfig())
    write_scene(tmp_path, n=2, camera_model="EQUIRECTANGULAR")
    with pytest.raises(DataError, match="the top level: camera_model EQUIRECTANGULAR is unsupported"):
        NerfstudioParser().parse(tmp_path, DatasetConfig())
    write_scene(tmp_path, n=2, distortion_params="0.1")
    with pytest.raises(
        DataError, match=r"the top level: 'distortion_params' must be a list \[k1, k2, k3, k4, p1, p2\]"
    ):
        NerfstudioParser().parse(tmp_path, DatasetConfig())
    write_scene(tmp_path, n=2, distortion_params=[0.1, "x"])
    with pytest.raises(DataError, match="'distortion_params'"):
        NerfstudioParser().parse(tmp_path, DatasetConfig())


def test_distortion_beside_depth_maps_is_refused(tmp_path):
    source = write_scene(tmp_path, n=2, k1=0.1)
    meta = json.loads(source.read_text())
    for i, frame in enumerate(meta["frames"]):
        np.save(tmp_path / f"d{i}.npy", np.ones((24, 32), dtype=np.float32))
        frame["depth_file_path"] = f"d{i}.npy"
    source.write_text(json.dumps(meta))
    with pytest.raises(DataError, match="depth maps beside lens distortion are unsupported"):
        NerfstudioParser().parse(tmp_path, DatasetConfig())


W, H = 160, 120
OFF_CENTRE = np.array([0.55, 0.4, 1.0]) * 2.0  # a point in OpenCV camera axes imaged near a corner


def _write_distorted_scene(root: Path, fisheye: bool, per_frame: bool) -> tuple[list[np.ndarray], float]:
    """Two views of a blob each, drawn where the distorted camera images OFF_CENTRE; with clean references."""
    fx, fy, cx, cy = 100.0, 102.0, 79.0, 61.0
    coeffs = (
        {"k1": 0.08, "k2": -0.02, "k3": 0.01, "k4": -0.004}
        if fisheye
        else {"k1": -0.25, "k2": 0.05, "p1": 0.002, "p2": -0.001, "k3": 0.01}
    )
    K = np.array([[fx, 0, cx - 0.5], [0, fy, cy - 0.5], [0, 0, 1]])
    for folder in ("images", "images_clean"):
        (root / folder).mkdir(parents=True, exist_ok=True)
    frames, targets = [], []
    for i in range(2):
        gl = np.array(gl_look_at([3 * np.cos(i), 3 * np.sin(i), 1.0]))
        right, up, back, centre = gl[:3, 0], gl[:3, 1], gl[:3, 2], gl[:3, 3]
        targets.append(centre + OFF_CENTRE[0] * right - OFF_CENTRE[1] * up - OFF_CENTRE[2] * back)
        pc = OFF_CENTRE.reshape(1, 1, 3)
        if fisheye:
            uv, _ = cv2.fisheye.projectPoints(pc, np.zeros(3), np.zeros(3), K, np.array(list(coeffs.values())))
        else:
            d = np.array([coeffs["k1"], coeffs["k2"], coeffs["p1"], coeffs["p2"], coeffs["k3"]])
            uv, _ = cv2.projectPoints(pc, np.zeros(3), np.zeros(3), K, d)
        u, v = uv.reshape(2) + 0.5
        ys, xs = np.mgrid[:H, :W] + 0.5
        blob = np.exp(-((xs - u) ** 2 + (ys - v) ** 2) / (2 * 2.0**2))
        img = (np.repeat(blob[:, :, None], 3, axis=2) * 255).round().astype(np.uint8)
        cv2.imwrite(str(root / "images" / f"f{i}.png"), img)
        cv2.imwrite(str(root / "images_clean" / f"f{i}.png"), img)
        frame = {"file_path": f"images/f{i}.png", "transform_matrix": gl.tolist()}
        if per_frame:
            frame.update(coeffs)
        frames.append(frame)
    meta = {"frames": frames, "fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy, "w": W, "h": H}
    if fisheye:
        meta["camera_model"] = "OPENCV_FISHEYE"
    if not per_frame:
        meta.update(coeffs)
    (root / "transforms.json").write_text(json.dumps(meta))
    naive = np.array([fx * OFF_CENTRE[0] / OFF_CENTRE[2] + cx, fy * OFF_CENTRE[1] / OFF_CENTRE[2] + cy])
    return targets, float(np.linalg.norm(naive - np.array([u, v])))


def _centroid(grey: np.ndarray) -> np.ndarray:
    w = np.clip(grey - 0.05, 0.0, None)
    ys, xs = np.mgrid[: grey.shape[0], : grey.shape[1]] + 0.5
    return np.array([(w * xs).sum(), (w * ys).sum()]) / w.sum()


@pytest.mark.parametrize(
    ("fisheye", "per_frame"),
    [(False, False), (False, True), (True, False)],
    ids=["opencv", "opencv-per-frame", "fisheye"],
)
def test_distorted_views_are_undistorted_once_to_the_pinhole_they_report(tmp_path, fisheye, per_frame):
    from metegs.data.images import load_image
    from metegs.data.undistort import CACHE_DIR

    targets, shift = _write_distorted_scene(tmp_path, fisheye, per_frame)
    assert shift > 5.0  # where the blob is drawn, the lens moves it this far from the original pinhole's projection
    scene = NerfstudioParser().parse(tmp_path, DatasetConfig())
    cams = scene.cameras
    for i, target in enumerate(targets):
        assert CACHE_DIR in scene.image_paths[i].parts and CACHE_DIR in scene.clean_image_paths[i].parts
        w2c = cams.world_to_cameras()[i].double().numpy()
        p = w2c[:3, :3] @ target + w2c[:3, 3]
        expected = np.array(
            [float(cams.fx[i]) * p[0] / p[2] + float(cams.cx[i]), float(cams.fy[i]) * p[1] / p[2] + float(cams.cy[i])]
        )
        for path in (scene.image_paths[i], scene.clean_image_paths[i]):
            image = load_image(path)
            assert image.shape == (H, W, 3)
            np.testing.assert_allclose(_centroid(image[:, :, 0]), expected, atol=0.35)
    stamps = [q.stat().st_mtime_ns for q in scene.image_paths]
    again = NerfstudioParser().parse(tmp_path, DatasetConfig())
    assert again.image_paths == scene.image_paths and [q.stat().st_mtime_ns for q in again.image_paths] == stamps


def test_a_read_only_scene_caches_its_undistorted_views_in_the_user_cache(tmp_path, monkeypatch):
    import os

    if os.geteuid() == 0:
        monkeypatch.setattr(os, "access", lambda path, mode: not str(path).startswith(str(tmp_path / "scene")))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    root = tmp_path / "scene"
    _write_distorted_scene(root, fisheye=False, per_frame=False)
    root.chmod(0o555)
    try:
        scene = NerfstudioParser().parse(root, DatasetConfig())
    finally:
        root.chmod(0o755)
    assert all(str(q).startswith(str(tmp_path / "cache" / "metegs" / "undistorted")) for q in scene.image_paths)
    assert not (root / ".metegs_undistorted").exists()


XYZ = np.array([[0.0, 1.0, 2.0], [-1.5, 0.25, 3.0], [4.0, -2.0, 0.5]], dtype=np.float32)
RGB = np.array([[255, 0, 0], [0, 128, 0], [10, 20, 255]], dtype=np.uint8)


def write_ply(path: Path, fmt: str, colors: bool = True) -> None:
    props = ["property float x", "property float y", "property float z"]
    if colors:
        props += ["property uchar red", "property uchar green", "property uchar blue"]
    header = [
        "ply",
        f"format {fmt} 1.0",
        "comment test",
        f"element vertex {len(XYZ)}",
        *props,
        "element face 0",
        "property list uchar int vertex_indices",
        "end_header",
    ]
    body = b""
    if fmt == "ascii":
        rows = [" ".join([*map(str, p), *(map(str, c) if colors else [])]) for p, c in zip(XYZ, RGB, strict=True)]
        body = ("\n".join(rows) + "\n").encode()
    else:
        order = "<" if fmt == "binary_little_endian" else ">"
        fields = [("x", order + "f4"), ("y", order + "f4"), ("z", order + "f4")]
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")] if colors else []
        arr = np.empty(len(XYZ), dtype=fields)
        arr["x"], arr["y"], arr["z"] = XYZ.T
        if colors:
            arr["red"], arr["green"], arr["blue"] = RGB.T
        body = arr.tobytes()
    path.write_bytes(("\n".join(header) + "\n").encode() + body)


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian", "binary_big_endian"])
def test_ply_points(tmp_path, fmt):
    write_ply(tmp_path / "sparse_pc.ply", fmt)
    write_scene(tmp_path, n=2, ply_file_path="sparse_pc.ply")
    scene = NerfstudioParser().parse(tmp_path, DatasetConfig())
    np.testing.assert_allclose(scene.points, XYZ, atol=1e-6)
    np.testing.assert_allclose(scene.point_colors, RGB / 255.0, atol=1e-6)
    assert scene.points.dtype == np.float32 and scene.point_colors.dtype == np.float32


def test_ply_without_colors_and_bad_ply(tmp_path):
    write_ply(tmp_path / "p.ply", "binary_little_endian", colors=False)
    xyz, rgb = read_ply_points(tmp_path / "p.ply")
    np.testing.assert_allclose(xyz, XYZ)
    assert rgb is None
    (tmp_path / "bad.ply").write_bytes(b"not a ply\n")
    with pytest.raises(DataError, match="bad.ply"):
        read_ply_points(tmp_path / "bad.ply")


def test_frame_masks_are_read_and_undistorted_with_their_view(tmp_path):
    from metegs.data.dataset import Dataset
    from metegs.data.undistort import CACHE_DIR

    source = write_scene(tmp_path, n=3)
    meta = json.loads(source.read_text())
    (tmp_path / "masks").mkdir()
    for i, frame in enumerate(meta["frames"]):
        mask = np.zeros((24, 32), np.uint8)
        mask[:, : 8 * (i + 1)] = 255
        cv2.imwrite(str(tmp_path / "masks" / f"m{i}.png"), mask)
        frame["mask_path"] = f"masks/m{i}.png"
    source.write_text(json.dumps(meta))
    scene = NerfstudioParser().parse(tmp_path, DatasetConfig())
    ds = Dataset(scene, DatasetConfig(use_masks=True, auto_max_side=32))
    assert [float(m.mean()) for m in ds.masks] == pytest.approx([0.25, 0.5, 0.75])

    del meta["frames"][1]["mask_path"]  # one frame without: no masks, said once
    source.write_text(json.dumps(meta))
    with pytest.warns(UserWarning, match="ignoring the masks, 1 frame"):
        assert NerfstudioParser().parse(tmp_path, DatasetConfig()).mask_paths is None

    meta["frames"][1]["mask_path"] = "masks/m1.png"
    meta.update(k1=-0.2)  # distorted: the masks follow their views into the cache
    source.write_text(json.dumps(meta))
    scene = NerfstudioParser().parse(tmp_path, DatasetConfig())
    assert all(CACHE_DIR in p.parts and "masks" in p.parts for p in scene.mask_paths)
    ds = Dataset(scene, DatasetConfig(use_masks=True, auto_max_side=32))
    assert 0.1 < float(ds.masks[0].mean()) < 0.4
