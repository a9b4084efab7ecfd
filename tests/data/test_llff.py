"""LLFF parser: the real ethiopianhead scene from ../shared, plus tiny synthetic folders."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

import metegs.builtins  # noqa: F401  (registers the parsers)
from metegs.data.config import DatasetConfig
from metegs.data.parsers.base import parse_scene
from metegs.data.parsers.llff import LLFFParser
from metegs.errors import DataError

SCENE = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "scenes" / "ethiopianhead-llff"


@pytest.fixture(scope="module")
def head():
    if not (SCENE / "poses_bounds.npy").is_file():
        pytest.skip(f"real LLFF scene not found at {SCENE} (needs ../shared beside the repository)")
    return parse_scene(SCENE, None, DatasetConfig())


def common_point(c2w: np.ndarray) -> np.ndarray:
    """Least-squares point closest to all optical axes (OpenCV +z of each [4, 4] camera-to-world)."""
    A, b = np.zeros((3, 3)), np.zeros(3)
    for c, d in zip(c2w[:, :3, 3], c2w[:, :3, 2], strict=True):
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ c
    return np.linalg.solve(A, b)


@pytest.mark.data
def test_ethiopianhead_cameras(head):
    assert head.parser == "llff" and len(head) == 66
    assert head.names[0] == "DSC_0007.jpg" and head.names == sorted(head.names)
    assert head.cameras.width.unique().tolist() == [500] and head.cameras.height.unique().tolist() == [500]
    raw = np.load(SCENE / "poses_bounds.npy")
    focal_4000 = raw[0, 14]
    assert head.cameras.fx[0].item() == pytest.approx(focal_4000 * 500 / 4000, rel=1e-5)
    assert head.cameras.cx[0].item() == 250.0 and head.cameras.cy[0].item() == 250.0
    assert head.points is None and len(head.mask_paths) == 66
    assert head.test_indices == list(range(0, 66, 8))

    # The cameras look at one common point (the object), at a depth on the scale of each view's near/far bounds.
    c2w = head.cameras.camera_to_worlds.double().numpy()
    target = common_point(c2w)
    to_target = target - c2w[:, :3, 3]
    depth = np.einsum("ij,ij->i", to_target, c2w[:, :3, 2])
    cos = depth / np.linalg.norm(to_target, axis=1)
    assert (np.degrees(np.arccos(np.clip(cos, -1, 1))) < 10).all()
    near, far = raw[:, 15], raw[:, 16]
    assert ((depth > 0.75 * near) & (depth < 1.25 * far)).all()


@pytest.mark.data
def test_ethiopianhead_masks_agree_with_poses(head):
    """Carve a visual hull from the masks: consistent poses give hull silhouettes that match the masks well.

    A wrong axis convention (e.g. a 180 degree roll, or swapped down/right columns) gives a mean IoU
    around 0.2-0.3 instead of about 0.55 at this coarse resolution.
    """
    size = 125
    masks = np.stack(
        [
            cv2.resize(cv2.imread(str(p), cv2.IMREAD_GRAYSCALE), (size, size), interpolation=cv2.INTER_AREA) > 127
            for p in head.mask_paths
        ]
    )
    cams = head.cameras.resized(size, size)
    K = cams.intrinsics()[0].double().numpy()
    w2c = cams.world_to_cameras().double().numpy()
    target = common_point(cams.camera_to_worlds.double().numpy())
    g = np.linspace(-1.5, 1.5, 48)
    X = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3) + target
    pix = []
    inside = np.ones(len(X), dtype=bool)
    for i in range(len(w2c)):
        pc = X @ w2c[i, :3, :3].T + w2c[i, :3, 3]
        uvw = pc @ K.T
        u = np.floor(uvw[:, 0] / uvw[:, 2]).astype(int)
        v = np.floor(uvw[:, 1] / uvw[:, 2]).astype(int)
        ok = (u >= 0) & (u < size) & (v >= 0) & (v < size) & (pc[:, 2] > 0)
        hit = np.zeros(len(X), dtype=bool)
        hit[ok] = masks[i][v[ok], u[ok]]
        inside &= hit
        pix.append((u, v, ok))
    ious = []
    for i, (u, v, ok) in enumerate(pix):
        sil = np.zeros((size, size), dtype=bool)
        sil[v[inside & ok], u[inside & ok]] = True
        ious.append((sil & masks[i]).sum() / (sil | masks[i]).sum())
    assert np.mean(ious) > 0.45


def write_llff(root: Path, n_poses: int, n_images: int, folder: str = "images_4", size=(40, 30)) -> None:
    """Synthetic LLFF scene: identity-ish poses, H=120, W=160, focal=100 at full resolution."""
    rows = []
    for i in range(n_poses):
        m = np.zeros((3, 5))
        m[:, :3] = [[0, 1, 0], [1, 0, 0], [0, 0, -1]]  # [down, right, backwards] of an OpenCV identity camera
        m[:, 3] = [0.1 * i, 0.0, -4.0]
        m[:, 4] = [120, 160, 100]
        rows.append(np.concatenate([m.reshape(-1), [1.0, 10.0]]))
    np.save(root / "poses_bounds.npy", np.array(rows))
    (root / folder).mkdir()
    for i in range(n_images):
        cv2.imwrite(str(root / folder / f"im_{i:03d}.png"), np.zeros((size[1], size[0], 3), np.uint8))


def test_synthetic_llff_conversion_and_focal(tmp_path):
    write_llff(tmp_path, 3, 3)
    assert LLFFParser.can_parse(tmp_path)
    scene = LLFFParser().parse(tmp_path, DatasetConfig())
    np.testing.assert_allclose(scene.cameras.camera_to_worlds[0, :3, :3].numpy(), np.eye(3), atol=1e-7)
    assert scene.cameras.fx[0].item() == pytest.approx(25.0) and scene.cameras.fy[0].item() == pytest.approx(25.0)
    assert scene.cameras.cx[0].item() == 20.0 and scene.cameras.cy[0].item() == 15.0
    assert scene.mask_paths is None


def test_count_mismatch(tmp_path):
    write_llff(tmp_path, 4, 3)
    with pytest.raises(DataError, match=r"3 images found but poses_bounds.npy has 4 poses"):
        LLFFParser().parse(tmp_path, DatasetConfig())


def test_prefers_images_then_smallest_n(tmp_path):
    write_llff(tmp_path, 2, 2, folder="images_8", size=(20, 15))
    (tmp_path / "images_2").mkdir()
    for i in range(2):
        cv2.imwrite(str(tmp_path / "images_2" / f"im_{i:03d}.png"), np.zeros((60, 80, 3), np.uint8))
    scene = LLFFParser().parse(tmp_path, DatasetConfig())
    assert scene.image_paths[0].parent.name == "images_2" and scene.cameras.width[0] == 80


def test_bad_poses_file(tmp_path):
    np.save(tmp_path / "poses_bounds.npy", np.zeros((3, 15)))
    with pytest.raises(DataError, match=r"poses_bounds.npy.*\[N, 17\]"):
        LLFFParser().parse(tmp_path, DatasetConfig())


@pytest.mark.data
def test_ethiopianhead_dataset(head):
    from metegs.data.dataset import Dataset

    ds = Dataset(head, DatasetConfig(auto_max_side=160, use_masks=True))
    assert ds.downscale == 4 and len(ds.images) == 66 and ds.images[0].shape == (125, 125, 3)
    assert ds.cameras.fx[0].item() == pytest.approx(head.cameras.fx[0].item() / 4, rel=1e-6)
    assert len(ds.masks) == 66 and ds.masks[0].shape == (125, 125)
    assert 0.0 <= ds.images[0].min().item() and ds.images[0].max().item() <= 1.0
