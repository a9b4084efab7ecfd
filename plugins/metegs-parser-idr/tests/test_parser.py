"""The IDR/NeuS parser: projection matrices decompose exactly, scenes round-trip, bad files are named."""

import numpy as np
import pytest
import torch
from idr_helpers import OFFSET, SCALE, write_scene
from metegs.data.config import DatasetConfig
from metegs.data.dataset import Dataset
from metegs.errors import DataError

from metegs_parser_idr.parser import IdrParser, decompose_projection, projection_matrix


def random_camera(gen: np.random.Generator):
    q = gen.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    R = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )
    K = np.array(
        [[gen.uniform(300, 900), 0, gen.uniform(100, 300)], [0, gen.uniform(300, 900), gen.uniform(80, 200)], [0, 0, 1]]
    )
    return K, R, gen.normal(size=3)


@pytest.mark.parametrize("scale", [1.0, 37.5, -0.02])
def test_projection_matrices_decompose_exactly_whatever_their_scale_and_sign(scale):
    gen = np.random.default_rng(1)
    for _ in range(20):
        K, R, t = random_camera(gen)
        P = scale * K @ np.concatenate([R, t[:, None]], 1)
        K2, R2, t2 = decompose_projection(P)
        assert np.allclose(K2, K, rtol=1e-9, atol=1e-7)
        assert np.allclose(R2, R, atol=1e-9) and np.allclose(t2, t, atol=1e-9)
        c2w = np.eye(4)
        c2w[:3, :3], c2w[:3, 3] = R.T, -R.T @ t
        assert np.allclose(projection_matrix(K, c2w)[:3], P / scale, atol=1e-9)


@pytest.mark.parametrize("camera_file", ["cameras_sphere.npz", "cameras.npz"])
def test_scene_round_trips_into_the_normalised_frame(tmp_path, camera_file):
    truth = write_scene(tmp_path, camera_file=camera_file)
    assert IdrParser.can_parse(tmp_path) and not IdrParser.can_parse(tmp_path / "image")
    scene = IdrParser().parse(tmp_path, DatasetConfig())
    cams, ref = scene.cameras, truth.cameras
    assert len(cams) == len(ref) == len(scene.image_paths)
    for name in ("fx", "fy", "cx", "cy", "width", "height"):
        assert torch.allclose(getattr(cams, name).double(), getattr(ref, name).double(), atol=1e-3), name
    c2w, c2w_ref = cams.camera_to_worlds.double(), ref.camera_to_worlds.double()
    assert torch.allclose(c2w[:, :3, :3], c2w_ref[:, :3, :3], atol=1e-5)
    expected_centres = (c2w_ref[:, :3, 3] - torch.from_numpy(OFFSET)) / SCALE
    assert torch.allclose(c2w[:, :3, 3], expected_centres, atol=1e-5)
    assert scene.metric_scale is None and scene.points is not None
    assert float(np.linalg.norm(scene.points, axis=1).max()) <= 1.0 + 1e-6
    assert len(scene.train_indices) + len(scene.test_indices) == len(cams)
    assert scene.mask_paths is not None and len(scene.mask_paths) == len(cams)
    data = Dataset(scene, DatasetConfig(use_masks=True))  # metegs loads the images and masks it found
    assert len(data.images) == len(cams) and data.masks is not None
    assert tuple(data.images[0].shape) == (30, 40, 3)


def test_without_scale_mats_the_world_frame_is_kept(tmp_path):
    truth = write_scene(tmp_path, masks=False)
    with np.load(tmp_path / "cameras_sphere.npz") as npz:
        world = {k: npz[k] for k in npz.files if k.startswith("world_mat")}
    np.savez(tmp_path / "cameras_sphere.npz", **world)
    scene = IdrParser().parse(tmp_path, DatasetConfig())
    assert torch.allclose(scene.cameras.camera_to_worlds, truth.cameras.camera_to_worlds, atol=1e-4)
    assert scene.points is None and scene.mask_paths is None


def test_bad_files_are_named(tmp_path):
    write_scene(tmp_path, views=3, masks=False)
    with np.load(tmp_path / "cameras_sphere.npz") as npz:
        mats = {k: npz[k] for k in npz.files}
    del mats["world_mat_2"]
    np.savez(tmp_path / "cameras_sphere.npz", **mats)
    with pytest.raises(DataError, match=r"cameras_sphere.npz.*view 2 \(000002.png\).*world_mat_2"):
        IdrParser().parse(tmp_path, DatasetConfig())
    mats["world_mat_2"] = mats["world_mat_1"].copy()
    mats["world_mat_2"][0, :3] += 0.2 * mats["world_mat_2"][1, :3]
    np.savez(tmp_path / "cameras_sphere.npz", **mats)
    with pytest.raises(DataError, match="skew"):
        IdrParser().parse(tmp_path, DatasetConfig())
    (tmp_path / "cameras_sphere.npz").write_text("not an npz")
    with pytest.raises(DataError, match="cannot read the camera file"):
        IdrParser().parse(tmp_path, DatasetConfig())
