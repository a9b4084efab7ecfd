"""COLMAP model files are checked before pycolmap reads them: truncation, impossible counts, malformed lines."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pycolmap
import pytest

import metegs.builtins  # noqa: F401  (registers the parsers)
from metegs.data.config import DatasetConfig
from metegs.data.parsers.base import parse_scene
from metegs.data.parsers.colmap_files import check_model
from metegs.errors import DataError
from tests.data.test_colmap import make_model


def tracked_model(folder: Path, rig_sensors: bool = False) -> Path:
    """A binary model with 3 images of 4 2D points each and 4 points seen by every image (tracks of 3)."""
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(pycolmap.Camera.create_from_model_name(1, "PINHOLE", 100.0, 160, 120))
    for i in range(3):
        pts = pycolmap.Point2DList([pycolmap.Point2D(np.array([10.0 + k, 20.0])) for k in range(4)])
        rec.add_image_with_trivial_frame(
            pycolmap.Image(name=f"img_{i}.png", points2D=pts, camera_id=1, image_id=i + 1), pycolmap.Rigid3d()
        )
    for k in range(4):
        track = pycolmap.Track()
        for i in range(3):
            track.add_element(i + 1, k)
        rec.add_point3D(np.array([0.1 * k, 0.0, 1.0]), track, np.array([255, 0, 0], np.uint8))
    folder.mkdir(parents=True, exist_ok=True)
    rec.write(str(folder))
    return folder


def test_valid_models_pass(tmp_path):
    check_model(tracked_model(tmp_path / "bin"))
    make_model(tmp_path / "txt", text=True, write_images=False)
    check_model(tmp_path / "txt" / "sparse" / "0")


def test_rig_with_several_sensors_passes(tmp_path):
    rec = pycolmap.Reconstruction()
    rig = pycolmap.Rig(rig_id=1)
    for cam_id in (1, 2, 3):
        rec.add_camera(pycolmap.Camera.create_from_model_name(cam_id, "PINHOLE", 100.0, 160, 120))
    rig.add_ref_sensor(rec.cameras[1].sensor_id)
    rig.add_sensor(rec.cameras[2].sensor_id, pycolmap.Rigid3d())
    rig.add_sensor(rec.cameras[3].sensor_id, None)
    rec.add_rig(rig)
    rec.write(str(tmp_path))
    check_model(tmp_path)


@pytest.mark.parametrize("name", ["cameras", "images", "points3D", "rigs", "frames"])
@pytest.mark.parametrize("keep", [0.0, 0.1, 0.5, 0.9, 0.99])
def test_truncated_binary_is_named(tmp_path, name, keep):
    folder = tracked_model(tmp_path)
    path = folder / f"{name}.bin"
    raw = path.read_bytes()
    path.write_bytes(raw[: int(len(raw) * keep)])
    with pytest.raises(DataError, match=rf"{name}.bin: .*(empty file|past the end|impossible)") as info:
        check_model(folder)
    assert info.value.path == path


def test_truncated_record_names_the_record_and_field(tmp_path):
    folder = tracked_model(tmp_path)
    raw = (folder / "images.bin").read_bytes()
    (folder / "images.bin").write_bytes(raw[:-30])  # inside image 3's 2D points
    with pytest.raises(DataError, match=r"images.bin: image 3 \(img_2.png\): the 2D points: 4 x 24 bytes run past"):
        check_model(folder)
    tracked_model(folder)
    raw = (folder / "points3D.bin").read_bytes()
    (folder / "points3D.bin").write_bytes(raw[:-1])  # inside the last point's track
    with pytest.raises(DataError, match=r"points3D.bin: point 4 of 4: the track of 3 observations runs past"):
        check_model(folder)


@pytest.mark.parametrize("name, count", [("cameras", 5), ("images", 1 << 40), ("points3D", 10**12)])
def test_inflated_count_is_impossible_for_the_file_size(tmp_path, name, count):
    folder = tracked_model(tmp_path)
    path = folder / f"{name}.bin"
    path.write_bytes(struct.pack("<Q", count) + path.read_bytes()[8:])
    with pytest.raises(DataError, match=rf"{name}.bin: the number of \w+ is {count}, impossible"):
        check_model(folder)


def test_trailing_bytes_mean_a_wrong_count(tmp_path):
    folder = tracked_model(tmp_path)
    path = folder / "points3D.bin"
    path.write_bytes(struct.pack("<Q", 3) + path.read_bytes()[8:])
    with pytest.raises(DataError, match=r"points3D.bin: 75 bytes follow the last of the 3 points"):
        check_model(folder)


def test_unknown_camera_model_and_non_finite_pose(tmp_path):
    folder = tracked_model(tmp_path)
    raw = bytearray((folder / "cameras.bin").read_bytes())
    raw[12:16] = struct.pack("<i", 99)
    (folder / "cameras.bin").write_bytes(bytes(raw))
    with pytest.raises(DataError, match="cameras.bin: camera 1: unknown camera model id 99"):
        check_model(folder)
    tracked_model(folder)
    raw = bytearray((folder / "images.bin").read_bytes())
    raw[12:20] = struct.pack("<d", float("nan"))  # qw of image 1
    (folder / "images.bin").write_bytes(bytes(raw))
    with pytest.raises(DataError, match=r"images.bin: image 1: the pose \(qvec, tvec\) is not finite"):
        check_model(folder)


def test_truncated_points_through_the_parser_name_the_file(tmp_path):
    make_model(tmp_path)
    path = tmp_path / "sparse" / "0" / "points3D.bin"
    path.write_bytes(path.read_bytes()[:-20])
    with pytest.raises(DataError, match=r"sparse/0/points3D.bin: .*impossible"):
        parse_scene(tmp_path, None, DatasetConfig())


def test_non_finite_point_position_is_named(tmp_path):
    make_model(tmp_path)
    path = tmp_path / "sparse" / "0" / "points3D.bin"
    raw = bytearray(path.read_bytes())
    raw[16:24] = struct.pack("<d", float("inf"))  # x of the first point
    path.write_bytes(bytes(raw))
    with pytest.raises(DataError, match=r"points3D.bin: 1 of 3 points have a non-finite position"):
        parse_scene(tmp_path, None, DatasetConfig())


def test_incomplete_model_is_refused(tmp_path):
    folder = tracked_model(tmp_path / "sparse" / "0")
    (folder / "points3D.bin").unlink()
    with pytest.raises(DataError, match=r"incomplete COLMAP model: found cameras.bin, images.bin"):
        check_model(folder)


@pytest.mark.parametrize(
    "name, old, new, match",
    [
        ("cameras", "80 60", "80", r"line 4: model PINHOLE has 4 parameters, the line has 3"),
        ("cameras", "PINHOLE", "PINHOLX", r"line 4: expected CAMERA_ID MODEL"),
        ("cameras", "160 120", "160 abc", r"line 4: CAMERA_ID, WIDTH and HEIGHT must be integers"),
        ("images", "img_03.png", "", r"line 5: expected IMAGE_ID QW"),
        ("images", " 1 img_03", " x img_03", r"line 5: IMAGE_ID and CAMERA_ID must be integers"),
        ("points3D", " 255 0 0 ", " 255 999 0 ", r"line 4: R G B must be in 0..255"),
        ("points3D", " 255 0 0 ", " 255 0 ", r"line 4: expected POINT3D_ID X Y Z"),
    ],
)
def test_malformed_text_line_names_file_and_line(tmp_path, name, old, new, match):
    make_model(tmp_path, text=True, write_images=False)
    path = tmp_path / "sparse" / "0" / f"{name}.txt"
    text = path.read_text()
    assert old in text, text
    path.write_text(text.replace(old, new, 1))
    with pytest.raises(DataError, match=rf"{name}.txt: {match}"):
        check_model(tmp_path / "sparse" / "0")


def test_text_nan_pose_and_bad_2d_points(tmp_path):
    make_model(tmp_path, text=True, write_images=False)
    path = tmp_path / "sparse" / "0" / "images.txt"
    lines = path.read_text().splitlines()
    first = next(i for i, ln in enumerate(lines) if ln and not ln.startswith("#"))
    parts = lines[first].split()
    lines[first] = " ".join([parts[0], "nan", *parts[2:]])
    lines[first + 1] = "1.0 2.0"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(DataError, match=rf"images.txt: line {first + 1}: the pose .* must be finite"):
        check_model(tmp_path / "sparse" / "0")
    lines[first] = " ".join(parts)
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(
        DataError, match=rf"images.txt: line {first + 2}: expected POINTS2D\[\] as \(X, Y, POINT3D_ID\)"
    ):
        check_model(tmp_path / "sparse" / "0")
