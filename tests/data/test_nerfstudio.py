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
        frame = {"file_path": f"images/frame_{i:03d}.png",
                 "transform_matrix": gl_look_at([3 * np.cos(i), 3 * np.sin(i), 1.0])}
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
    write_scene(tmp_path, n=4, train_filenames=["images/frame_000.png", "./images/frame_002.png"],
                test_filenames=["images/frame_001.png"])
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


def test_distortion_is_refused(tmp_path):
    write_scene(tmp_path, n=2, k1=0.1)
    with pytest.raises(DataError, match="distortion is unsupported"):
        NerfstudioParser().parse(tmp_path, DatasetConfig())
    write_scene(tmp_path, n=2, k1=0.0, p2=0.0)
    assert len(NerfstudioParser().parse(tmp_path, DatasetConfig())) == 2
    write_scene(tmp_path, n=2, camera_model="OPENCV_FISHEYE")
    with pytest.raises(DataError, match="OPENCV_FISHEYE"):
        NerfstudioParser().parse(tmp_path, DatasetConfig())


XYZ = np.array([[0.0, 1.0, 2.0], [-1.5, 0.25, 3.0], [4.0, -2.0, 0.5]], dtype=np.float32)
RGB = np.array([[255, 0, 0], [0, 128, 0], [10, 20, 255]], dtype=np.uint8)


def write_ply(path: Path, fmt: str, colors: bool = True) -> None:
    props = ["property float x", "property float y", "property float z"]
    if colors:
        props += ["property uchar red", "property uchar green", "property uchar blue"]
    header = ["ply", f"format {fmt} 1.0", "comment test", f"element vertex {len(XYZ)}", *props,
              "element face 0", "property list uchar int vertex_indices", "end_header"]
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
