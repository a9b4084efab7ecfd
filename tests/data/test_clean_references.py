"""Every parser exposes the clean references that metegs-synth writes next to degraded images (``<folder>_clean/``)."""

import json
import warnings
from pathlib import Path, PurePosixPath

import cv2
import numpy as np
import pycolmap
import pytest

from metegs.data.config import DatasetConfig
from metegs.data.dataset import Dataset
from metegs.data.parsers.base import parse_scene
from metegs.data.parsers.clean import clean_relative_path, find_clean_paths


def _img(path: Path, value: int, size=(32, 24)) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.full((size[1], size[0], 3), value, np.uint8))


def _cleans(root: Path, rel_images: list[str], value: int = 200) -> None:
    for rel in rel_images:
        _img(root / clean_relative_path(rel), value)


def llff(root: Path, n: int = 3) -> list[str]:
    rows = []
    for i in range(n):
        m = np.zeros((3, 5))
        m[:, :3] = [[0, 1, 0], [1, 0, 0], [0, 0, -1]]
        m[:, 3] = [0.1 * i, 0.0, -4.0]
        m[:, 4] = [24, 32, 30]
        rows.append(np.concatenate([m.reshape(-1), [1.0, 10.0]]))
    np.save(root / "poses_bounds.npy", np.array(rows))
    rels = [f"images_8/im_{i}.png" for i in range(n)]
    for r in rels:
        _img(root / r, 50)
    return rels


def nerfstudio(root: Path, n: int = 3) -> list[str]:
    rels = [f"images/frame_{i}.png" for i in range(n)]
    frames = []
    for i, r in enumerate(rels):
        m = np.eye(4)
        m[:3, 3] = [0.2 * i, 0.0, 3.0]
        frames.append({"file_path": r, "transform_matrix": m.tolist()})
        _img(root / r, 50)
    meta = {"frames": frames, "fl_x": 30.0, "fl_y": 30.0, "cx": 16.0, "cy": 12.0, "w": 32, "h": 24}
    (root / "transforms.json").write_text(json.dumps(meta))
    return rels


def blender(root: Path, n: int = 2) -> list[str]:
    rels = []
    for split in ("train", "test"):
        frames = []
        for i in range(n):
            m = np.eye(4)
            m[2, 3] = 4.0 + i
            frames.append({"file_path": f"./{split}/r_{i}", "transform_matrix": m.tolist()})
            rels.append(f"{split}/r_{i}.png")
            _img(root / rels[-1], 50)
        (root / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": 0.7, "frames": frames}))
    return rels


def colmap(root: Path, n: int = 3) -> list[str]:
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(pycolmap.Camera.create_from_model_name(1, "PINHOLE", 30.0, 32, 24))
    for i in range(n):
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(np.eye(3)), np.array([0.1 * i, 0.0, 3.0]))
        rec.add_image_with_trivial_frame(pycolmap.Image(name=f"img_{i}.png", camera_id=1, image_id=i + 1), pose)
    rec.add_point3D(np.zeros(3), pycolmap.Track(), np.array([255, 0, 0], dtype=np.uint8))
    (root / "sparse/0").mkdir(parents=True)
    rec.write(str(root / "sparse/0"))
    rels = [f"images/img_{i}.png" for i in range(n)]
    for r in rels:
        _img(root / r, 50)
    return rels


FORMATS = {"llff": llff, "nerfstudio": nerfstudio, "blender": blender, "colmap": colmap}


def test_clean_relative_path_convention():
    assert clean_relative_path("images_8/a.jpg") == PurePosixPath("images_8_clean/a.jpg")
    assert clean_relative_path("./train/r_0.png") == PurePosixPath("train_clean/r_0.png")
    assert clean_relative_path("images/cam1/a.png") == PurePosixPath("images_clean/cam1/a.png")
    assert clean_relative_path("a.png") == PurePosixPath("clean/a.png")


@pytest.mark.parametrize("fmt", sorted(FORMATS))
def test_parsers_expose_clean_references(tmp_path, fmt):
    rels = FORMATS[fmt](tmp_path)
    scene = parse_scene(tmp_path, None, DatasetConfig())
    assert scene.parser == fmt and scene.clean_image_paths is None
    _cleans(tmp_path, rels)
    scene = parse_scene(tmp_path, None, DatasetConfig())
    assert scene.clean_image_paths is not None and len(scene.clean_image_paths) == len(scene)
    for image, clean in zip(scene.image_paths, scene.clean_image_paths):
        assert clean == tmp_path / clean_relative_path(image.relative_to(tmp_path))
    ds = Dataset(scene, DatasetConfig(downscale=1))
    assert ds.clean_images is not None
    assert float(ds.clean_images[0].mean()) == pytest.approx(200 / 255, abs=1e-3)
    assert float(ds.images[0].mean()) == pytest.approx(50 / 255, abs=1e-3)


def test_partial_clean_references_are_ignored_with_a_warning(tmp_path):
    rels = llff(tmp_path)
    _cleans(tmp_path, rels[:2])
    with pytest.warns(UserWarning, match="1 of 3 views have none"):
        scene = parse_scene(tmp_path, None, DatasetConfig())
    assert scene.clean_image_paths is None


def test_images_outside_the_root_have_no_clean_reference(tmp_path):
    _img(tmp_path / "elsewhere/a.png", 1)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert find_clean_paths(tmp_path / "scene", [tmp_path / "elsewhere/a.png"]) is None


def test_nerfstudio_reads_npy_depth_maps(tmp_path):
    rels = nerfstudio(tmp_path)
    meta = json.loads((tmp_path / "transforms.json").read_text())
    for i, frame in enumerate(meta["frames"]):
        frame["depth_file_path"] = f"depths/{i}.npy"
        (tmp_path / "depths").mkdir(exist_ok=True)
        np.save(tmp_path / f"depths/{i}.npy", np.full((24, 32), 2.0 + i, np.float32))
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    scene = parse_scene(tmp_path, None, DatasetConfig())
    assert len(rels) == len(scene.depths) == 3
    assert [float(d[0, 0]) for d in scene.depths] == [2.0, 3.0, 4.0]
    np.save(tmp_path / "depths/1.npy", np.zeros((5, 5), np.float32))
    with pytest.raises(Exception, match=r"depth map has shape \[5, 5\], expected \[24, 32\]"):
        parse_scene(tmp_path, None, DatasetConfig())
