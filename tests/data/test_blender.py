"""Blender / NeRF-synthetic parser."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

import metegs.builtins  # noqa: F401  (registers the parsers)
from metegs.data.config import DatasetConfig
from metegs.data.dataset import Dataset
from metegs.data.parsers.base import parse_scene
from metegs.data.parsers.blender import BlenderParser
from metegs.errors import DataError

ANGLE_X = 0.6911112070083618  # the NeRF-synthetic lego value


def gl_pose(z: float) -> list[list[float]]:
    """OpenGL camera-to-world at (0, 0, z) looking down -z toward the origin (identity rotation)."""
    m = np.eye(4)
    m[2, 3] = z
    return m.tolist()


def write_split(root: Path, split: str, n: int, size=(40, 40)) -> None:
    (root / split).mkdir(parents=True, exist_ok=True)
    frames = []
    for i in range(n):
        frames.append({"file_path": f"./{split}/r_{i}", "rotation": 0.0, "transform_matrix": gl_pose(4.0 + i)})
        rgba = np.zeros((size[1], size[0], 4), np.uint8)
        rgba[..., 2] = 255  # red in BGRA
        rgba[: size[1] // 2, :, 3] = 255  # top half opaque red, bottom half fully transparent
        cv2.imwrite(str(root / split / f"r_{i}.png"), rgba)
    (root / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": ANGLE_X, "frames": frames}))


def test_blender_scene(tmp_path):
    write_split(tmp_path, "train", 3)
    write_split(tmp_path, "val", 2)
    write_split(tmp_path, "test", 2)
    scene = parse_scene(tmp_path, None, DatasetConfig())
    assert scene.parser == "blender"
    assert scene.names == ["train/r_0.png", "train/r_1.png", "train/r_2.png", "test/r_0.png", "test/r_1.png"]
    assert scene.train_indices == [0, 1, 2] and scene.test_indices == [3, 4]
    assert scene.cameras.fx[0].item() == pytest.approx(0.5 * 40 / math.tan(0.5 * ANGLE_X), rel=1e-6)
    assert scene.cameras.cx[0].item() == 20.0 and scene.cameras.width[0].item() == 40
    # OpenGL -> OpenCV: the origin is in front of the cameras (positive z).
    origin_z = scene.cameras.world_to_cameras()[:, 2, 3]
    np.testing.assert_allclose(origin_z.numpy(), [4.0, 5.0, 6.0, 4.0, 5.0], atol=1e-5)


def test_val_is_test_without_test_file(tmp_path):
    write_split(tmp_path, "train", 2)
    write_split(tmp_path, "val", 1)
    scene = BlenderParser().parse(tmp_path, DatasetConfig())
    assert scene.names[-1] == "val/r_0.png" and scene.test_indices == [2]


def test_rgba_is_composited_on_white(tmp_path):
    write_split(tmp_path, "train", 1)
    ds = Dataset(BlenderParser().parse(tmp_path, DatasetConfig()), DatasetConfig(downscale=1))
    img = ds.images[0]
    assert img.shape == (40, 40, 3)
    assert img[:20].sub(torch.tensor([1.0, 0.0, 0.0])).abs().max() < 1e-6  # opaque red
    assert (img[20:] == 1.0).all()  # transparent -> white


def test_missing_camera_angle(tmp_path):
    write_split(tmp_path, "train", 1)
    meta = json.loads((tmp_path / "transforms_train.json").read_text())
    del meta["camera_angle_x"]
    (tmp_path / "transforms_train.json").write_text(json.dumps(meta))
    with pytest.raises(DataError, match="transforms_train.json.*camera_angle_x"):
        BlenderParser().parse(tmp_path, DatasetConfig())
