"""Image loading (`metegs.data.images`) and the eager `Dataset`."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

import metegs.builtins  # noqa: F401  (registers the parsers)
from metegs.cameras import Cameras
from metegs.data.config import DatasetConfig
from metegs.data.dataset import Dataset, auto_downscale
from metegs.data.images import list_images, load_image, load_mask, resize_image
from metegs.data.parsers.base import parse_scene
from metegs.data.scene import SceneData
from metegs.errors import DataError


def test_load_image_formats(tmp_path):
    bgr = np.zeros((4, 5, 3), np.uint8)
    bgr[..., 2] = 255  # red
    cv2.imwrite(str(tmp_path / "c8.png"), bgr)
    cv2.imwrite(str(tmp_path / "c16.png"), (bgr.astype(np.uint16) * 257 // 2))
    cv2.imwrite(str(tmp_path / "g.png"), np.full((4, 5), 51, np.uint8))
    rgba = np.zeros((4, 5, 4), np.uint8)
    rgba[..., 0] = 255  # blue
    rgba[..., 3] = 128
    cv2.imwrite(str(tmp_path / "a.png"), rgba)

    img = load_image(tmp_path / "c8.png")
    assert img.dtype == np.float32 and img.shape == (4, 5, 3)
    np.testing.assert_allclose(img[0, 0], [1.0, 0.0, 0.0])
    np.testing.assert_allclose(load_image(tmp_path / "c16.png")[0, 0], [32767 / 65535, 0, 0], atol=1e-6)
    np.testing.assert_allclose(load_image(tmp_path / "g.png")[0, 0], [0.2, 0.2, 0.2], atol=1e-6)
    alpha = 128 / 255
    np.testing.assert_allclose(load_image(tmp_path / "a.png")[0, 0], [1 - alpha, 1 - alpha, 1.0], atol=1e-6)
    mask = load_mask(tmp_path / "g.png")
    assert mask.shape == (4, 5) and mask.dtype == np.float32


def test_corrupt_and_missing_images(tmp_path):
    bad = tmp_path / "broken.jpg"
    bad.write_bytes(b"\xff\xd8 definitely not a jpeg")
    with pytest.raises(DataError, match="broken.jpg.*cannot read image"):
        load_image(bad)
    with pytest.raises(DataError, match="nope.png.*does not exist"):
        load_image(tmp_path / "nope.png")


def test_resize_image():
    img = np.random.default_rng(0).random((8, 12, 3), dtype=np.float32)
    small = resize_image(img, 6, 4)
    assert small.shape == (4, 6, 3)
    np.testing.assert_allclose(small[0, 0], img[:2, :2].mean(axis=(0, 1)), atol=1e-6)
    assert resize_image(img, 12, 8) is img
    assert resize_image(img[..., :1], 6, 4).shape == (4, 6, 1)


def test_empty_and_missing_folders(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataError, match="no images found in"):
        list_images(tmp_path / "empty")
    # An LLFF scene whose image folder is empty.
    np.save(tmp_path / "poses_bounds.npy", np.ones((2, 17)))
    (tmp_path / "images").mkdir()
    with pytest.raises(DataError, match="no images found in"):
        parse_scene(tmp_path, None, DatasetConfig())
    with pytest.raises(DataError, match="does not exist"):
        parse_scene(tmp_path / "missing", None, DatasetConfig())
    with pytest.raises(DataError, match="cannot tell the scene format"):
        parse_scene(tmp_path / "empty", None, DatasetConfig())


def memory_scene(n=3, width=500, height=500, with_extras=True) -> SceneData:
    """In-memory scene: view i is filled with the value i / 10; depths equal 2 + i."""
    c2w = torch.eye(4).repeat(n, 1, 1)
    c2w[:, 2, 3] = torch.arange(n, dtype=torch.float32)
    cams = Cameras.create(c2w, 400.0, 420.0, width / 2, height / 2, width, height)
    images = [np.full((height, width, 3), i / 10, np.float32) for i in range(n)]
    return SceneData(
        cameras=cams,
        names=[f"v{i}" for i in range(n)],
        images=images,
        clean_images=[im + 0.05 for im in images] if with_extras else None,
        depths=[np.full((height, width), 2.0 + i, np.float32) for i in range(n)] if with_extras else None,
        train_indices=list(range(1, n)),
        test_indices=[0],
    )


def test_dataset_auto_downscale_in_memory():
    scene = memory_scene()
    ds = Dataset(scene, DatasetConfig(auto_max_side=160))
    assert ds.downscale == 4 and len(ds) == 3
    assert ds.images[1].shape == (125, 125, 3) and ds.images[1].dtype == torch.float32
    assert torch.allclose(ds.images[2], torch.full((125, 125, 3), 0.2))
    assert ds.clean_images[2][0, 0, 0].item() == pytest.approx(0.25)
    assert ds.depths[1].shape == (125, 125) and ds.depths[1][0, 0].item() == 3.0
    assert ds.masks is None
    assert ds.cameras.fx.tolist() == [100.0] * 3 and ds.cameras.fy.tolist() == [105.0] * 3
    assert ds.cameras.cx.tolist() == [62.5] * 3 and ds.cameras.width.tolist() == [125] * 3
    assert ds.scene.cameras.fx[0].item() == 400.0  # the scene's cameras are untouched
    assert ds.train_indices == [1, 2] and ds.test_indices == [0] and ds.names == ["v0", "v1", "v2"]


def test_dataset_explicit_downscale_and_no_extras():
    ds = Dataset(memory_scene(n=2, width=100, height=60, with_extras=False), DatasetConfig(downscale=3))
    assert ds.downscale == 3
    assert ds.images[0].shape == (20, 33, 3)  # round(60/3) x round(100/3)
    assert ds.cameras.fx[0].item() == pytest.approx(400.0 * 33 / 100)
    assert ds.clean_images is None and ds.depths is None
    assert auto_downscale(ds.scene.cameras, 1000) == 1


def test_dataset_size_mismatch(tmp_path):
    scene = memory_scene(n=2, width=40, height=30, with_extras=False)
    scene.images[1] = np.zeros((30, 41, 3), np.float32)
    with pytest.raises(DataError, match="v1.*41x30.*40x30"):
        Dataset(scene, DatasetConfig())


def files_scene(root: Path, n=2) -> SceneData:
    (root / "images").mkdir(parents=True)
    (root / "masks").mkdir()
    paths, masks = [], []
    for i in range(n):
        paths.append(root / "images" / f"{i}.png")
        cv2.imwrite(str(paths[-1]), np.full((32, 48, 3), 200, np.uint8))
        masks.append(root / "masks" / f"{i}.png")
        cv2.imwrite(str(masks[-1]), np.full((32, 48), 255, np.uint8))
    cams = Cameras.create(torch.eye(4).repeat(n, 1, 1), 50.0, 50.0, 24.0, 16.0, 48, 32)
    return SceneData(
        cameras=cams, names=[p.name for p in paths], image_paths=paths, mask_paths=masks, train_indices=list(range(n))
    )


def test_dataset_from_files_with_masks(tmp_path):
    ds = Dataset(files_scene(tmp_path), DatasetConfig(auto_max_side=24, use_masks=True))
    assert ds.downscale == 2
    assert ds.images[0].shape == (16, 24, 3)
    assert ds.images[0][0, 0, 0].item() == pytest.approx(200 / 255)
    assert len(ds.masks) == 2 and ds.masks[0].shape == (16, 24) and ds.masks[0].min().item() == 1.0
    assert Dataset(files_scene(tmp_path / "b"), DatasetConfig()).masks is None  # use_masks off


def test_dataset_corrupt_file_is_named(tmp_path):
    scene = files_scene(tmp_path)
    scene.image_paths[1].write_bytes(b"\x89PNG\r\n\x1a\n truncated")
    with pytest.raises(DataError, match="1.png"):
        Dataset(scene, DatasetConfig())


def test_dataset_file_size_mismatch_is_named(tmp_path):
    scene = files_scene(tmp_path)
    cv2.imwrite(str(scene.image_paths[0]), np.zeros((10, 10, 3), np.uint8))
    with pytest.raises(DataError, match=r"0.png.*10x10.*48x32"):
        Dataset(scene, DatasetConfig())


def test_the_default_image_size_follows_the_device():
    from metegs.data.config import auto_max_side

    assert auto_max_side(DatasetConfig(), "cuda") == auto_max_side(DatasetConfig(), "cuda:1") == 1600
    assert auto_max_side(DatasetConfig(), "cpu") == 640
    assert auto_max_side(DatasetConfig(auto_max_side=320), "cuda") == 320
    cams = Cameras.create(torch.eye(4)[None], 500.0, 500.0, 1000.0, 658.0, 2000, 1316)
    assert auto_downscale(cams, auto_max_side(DatasetConfig(), "cuda")) == 2  # 1000x658
    assert auto_downscale(cams, auto_max_side(DatasetConfig(), "cpu")) == 4  # 500x329
