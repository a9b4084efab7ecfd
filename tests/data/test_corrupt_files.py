"""Corrupt input files are refused with a DataError naming the file: images, .npy arrays, JSON numbers, PLY points."""

from __future__ import annotations

import json

import cv2
import numpy as np
import numpy.lib.format as npy_format
import pytest

import metegs.builtins  # noqa: F401  (registers the parsers)
from metegs.data.config import DatasetConfig
from metegs.data.dataset import Dataset
from metegs.data.images import load_image, load_mask
from metegs.data.parsers.blender import BlenderParser
from metegs.data.parsers.llff import LLFFParser
from metegs.data.parsers.nerfstudio import NerfstudioParser, read_ply_points
from metegs.data.sfm import list_photos, stage_masks
from metegs.errors import DataError
from tests.data.test_blender import write_split
from tests.data.test_images_dataset import files_scene
from tests.data.test_llff import write_llff
from tests.data.test_nerfstudio import write_ply, write_scene

RNG_IMAGE = (np.random.default_rng(0).random((48, 64, 3)) * 255).astype(np.uint8)


def encoded(suffix: str, *flags) -> bytes:
    return cv2.imencode(suffix, RNG_IMAGE, list(flags))[1].tobytes()


@pytest.mark.parametrize("suffix, flags", [(".jpg", ()), (".jpg", (cv2.IMWRITE_JPEG_PROGRESSIVE, 1)), (".png", ())])
@pytest.mark.parametrize("keep", [0.3, 0.8, 0.99])
def test_truncated_jpeg_and_png_are_refused(tmp_path, suffix, flags, keep):
    raw = encoded(suffix, *flags)
    path = tmp_path / f"cut{suffix}"
    path.write_bytes(raw[: int(len(raw) * keep)])
    with pytest.raises(DataError, match=rf"cut{suffix}: (JPEG|PNG) data is truncated") as info:
        load_image(path)
    assert info.value.path == path


def test_complete_images_with_trailing_bytes_still_load(tmp_path):
    for name, raw in [("zeros.jpg", encoded(".jpg") + bytes(64)), ("extra.jpg", encoded(".jpg") + b"trailer")]:
        (tmp_path / name).write_bytes(raw)
        assert load_image(tmp_path / name).shape == (48, 64, 3)


def test_empty_and_non_image_files_are_refused(tmp_path):
    (tmp_path / "empty.png").write_bytes(b"")
    with pytest.raises(DataError, match=r"empty.png: empty file \(0 bytes\)"):
        load_image(tmp_path / "empty.png")
    (tmp_path / "text.jpg").write_text("this is not a picture\n")
    with pytest.raises(DataError, match="text.jpg: cannot read image"):
        load_image(tmp_path / "text.jpg")


def test_truncated_mask_and_dataset_image_are_named(tmp_path):
    scene = files_scene(tmp_path)
    raw = scene.image_paths[1].read_bytes()
    scene.image_paths[1].write_bytes(raw[: len(raw) // 2])
    with pytest.raises(DataError, match=r"images/1.png: PNG data is truncated"):
        Dataset(scene, DatasetConfig())
    raw = scene.mask_paths[0].read_bytes()
    scene.mask_paths[0].write_bytes(raw[:-12])  # the IEND chunk only
    with pytest.raises(DataError, match=r"masks/0.png: PNG data is truncated \(no IEND chunk\)"):
        load_mask(scene.mask_paths[0])


def test_process_images_refuses_truncated_photos_and_masks(tmp_path):
    photos, masks = tmp_path / "photos", tmp_path / "masks"
    photos.mkdir()
    masks.mkdir()
    (photos / "a.jpg").write_bytes(encoded(".jpg"))
    (photos / "b.jpg").write_bytes(encoded(".jpg")[:-100])
    with pytest.raises(DataError, match=r"b.jpg: JPEG data is truncated"):
        list_photos(photos)
    (photos / "b.jpg").unlink()
    cv2.imwrite(str(masks / "a.png"), np.full((48, 64), 255, np.uint8))
    (masks / "a.png").write_bytes((masks / "a.png").read_bytes()[:40])
    with pytest.raises(DataError, match=r"a.png: PNG data is truncated"):
        stage_masks(masks, list_photos(photos), tmp_path / "staged")


def test_llff_poses_that_are_not_a_plain_array(tmp_path):
    write_llff(tmp_path, 3, 3)
    source = tmp_path / "poses_bounds.npy"
    source.write_text("not numpy\n")
    with pytest.raises(DataError, match=r"poses_bounds.npy: the poses and bounds file is not a .npy array"):
        LLFFParser().parse(tmp_path, DatasetConfig())
    with open(source, "wb") as f:  # a header claiming 10^9 rows: refused without allocating them
        npy_format.write_array_header_1_0(f, {"descr": "<f8", "fortran_order": False, "shape": (10**9, 17)})
        f.write(bytes(3 * 17 * 8))
    with pytest.raises(DataError, match=r"poses_bounds.npy: cannot read the poses and bounds \(truncated"):
        LLFFParser().parse(tmp_path, DatasetConfig())
    np.save(source, np.array([{"pose": 1}] * 3, dtype=object), allow_pickle=True)
    with pytest.raises(DataError, match=r"poses_bounds.npy: cannot read"):
        LLFFParser().parse(tmp_path, DatasetConfig())


def test_llff_nan_pose_is_refused(tmp_path):
    write_llff(tmp_path, 3, 3)
    rows = np.load(tmp_path / "poses_bounds.npy")
    rows[1, 3] = np.nan
    np.save(tmp_path / "poses_bounds.npy", rows)
    with pytest.raises(DataError, match=r"poses_bounds.npy: contains non-finite values"):
        LLFFParser().parse(tmp_path, DatasetConfig())


@pytest.mark.parametrize(
    "extra, match",
    [
        ({"k1": "abc"}, r"the top level: 'k1' must be a finite number, got 'abc'"),
        ({"distortion_params": "x"}, r"'distortion_params' must be a list"),
        ({"metegs": {"metric_scale": "far"}}, r"metegs.metric_scale must be a finite number"),
        ({"metegs": {"exposure_time_s": [0.01, None, 0.01, 0.01]}}, r"metegs.exposure_time_s must be a finite"),
        ({"metegs": {"up": ["z", 0, 1]}}, r"metegs.up must be a finite number"),
    ],
)
def test_nerfstudio_non_numbers_are_named(tmp_path, extra, match):
    write_scene(tmp_path, **extra)
    with pytest.raises(DataError, match=rf"transforms.json: .*{match}"):
        NerfstudioParser().parse(tmp_path, DatasetConfig())


def test_nerfstudio_nan_intrinsic_and_truncated_depth(tmp_path):
    source = write_scene(tmp_path)
    meta = json.loads(source.read_text())
    meta["frames"][2]["fl_x"] = float("nan")
    source.write_text(json.dumps(meta))  # json writes NaN, which Python's json reads back
    with pytest.raises(DataError, match=r"transforms.json: frame 2: intrinsic 'fl_x' must be a finite number"):
        NerfstudioParser().parse(tmp_path, DatasetConfig())
    write_scene(tmp_path)
    meta = json.loads(source.read_text())
    for i, frame in enumerate(meta["frames"]):
        frame["depth_file_path"] = f"depth_{i}.npy"
        np.save(tmp_path / f"depth_{i}.npy", np.ones((24, 32), np.float32))
    source.write_text(json.dumps(meta))
    raw = (tmp_path / "depth_1.npy").read_bytes()
    (tmp_path / "depth_1.npy").write_bytes(raw[:-100])
    with pytest.raises(DataError, match=r"depth_1.npy: cannot read the depth map \(truncated"):
        NerfstudioParser().parse(tmp_path, DatasetConfig())


def test_ply_points_huge_count_and_nan(tmp_path):
    path = tmp_path / "pts.ply"
    write_ply(path, "binary_little_endian")
    path.write_bytes(path.read_bytes().replace(b"element vertex 3\n", b"element vertex 2000000000\n"))
    with pytest.raises(DataError, match=r"pts.ply: PLY data truncated: the header declares 2000000000 vertices"):
        read_ply_points(path)
    write_ply(path, "ascii")
    path.write_text(path.read_text().replace("-1.5", "nan"))
    with pytest.raises(DataError, match=r"pts.ply: property 'x' is NaN or infinite in 1 of 3 vertices"):
        read_ply_points(path)


def test_blender_non_number_size_and_angle(tmp_path):
    write_split(tmp_path, "train", 2)
    source = tmp_path / "transforms_train.json"
    meta = json.loads(source.read_text())
    source.write_text(json.dumps({**meta, "w": "wide", "h": 40}))
    with pytest.raises(DataError, match=r"transforms_train.json: 'w' must be a finite number, got 'wide'"):
        BlenderParser().parse(tmp_path, DatasetConfig())
    source.write_text(json.dumps({**meta, "camera_angle_x": [0.7]}))
    with pytest.raises(DataError, match=r"transforms_train.json: 'camera_angle_x' must be a finite number"):
        BlenderParser().parse(tmp_path, DatasetConfig())


def test_nerfstudio_split_lists_must_be_lists_that_match(tmp_path):
    write_scene(tmp_path, train_filenames="images/frame_000.png")
    with pytest.raises(DataError, match=r"transforms.json: 'train_filenames' must be a list of image paths"):
        NerfstudioParser().parse(tmp_path, DatasetConfig())
    write_scene(tmp_path, train_filenames=["elsewhere/a.png", "elsewhere/b.png"])
    with pytest.raises(DataError, match=r"transforms.json: none of the 'train_filenames' is the file_path of a frame"):
        NerfstudioParser().parse(tmp_path, DatasetConfig())
