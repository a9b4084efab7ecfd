"""Rigid rotation of Gaussians (positions, orientations, SH colour) and scene.ply written upright for viewers."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from metegs.cameras import Cameras
from metegs.errors import DataError
from metegs.gaussians.model import PARAM_NAMES, GaussianModel
from metegs.gaussians.ply import WORLD_TO_FILE, load_ply, save_ply
from metegs.gaussians.rotate import FILE_UP, rotate_state, sh_rotation, upright_rotation
from metegs.gaussians.sh import eval_sh, num_sh_bases
from metegs.render import RenderSettings
from metegs.render.select import make_rasterizer
from metegs.testing import camera, random_scene


@pytest.mark.parametrize("up", [(0, 0, 1), (0, 0, -1), (0, 1, 0), (0, -1, 0), (1, 0, 0), (-1, 0, 0), (0.2, -0.3, 0.9)])
def test_upright_rotation_takes_the_nearest_axis_of_up_to_minus_y(up):
    r = upright_rotation(np.array(up, float))
    assert np.allclose(r @ r.T, np.eye(3)) and np.linalg.det(r) == pytest.approx(1.0)
    assert set(np.abs(r).reshape(-1)) <= {0.0, 1.0}  # a signed permutation: axis-aligned files stay axis-aligned
    axis = np.zeros(3)
    i = int(np.argmax(np.abs(up)))
    axis[i] = np.sign(up[i])
    assert np.allclose(r @ axis, FILE_UP)
    if tuple(up) == (0, -1, 0):  # COLMAP / INRIA worlds are written as they are
        assert np.array_equal(r, np.eye(3))


@pytest.mark.parametrize("degree", [1, 2, 3])
def test_rotated_sh_shows_the_same_colour_towards_the_rotated_direction(degree):
    r = Rotation.random(random_state=degree).as_matrix()
    m = sh_rotation(r, degree)
    k = num_sh_bases(degree)
    g = torch.Generator().manual_seed(degree)
    c = torch.randn(20, k, 3, generator=g, dtype=torch.float64)
    d = torch.nn.functional.normalize(torch.randn(20, 3, generator=g, dtype=torch.float64), dim=1)
    turned = torch.einsum("ij,njc->nic", m, c)
    rd = d @ torch.as_tensor(r).T
    assert torch.allclose(eval_sh(degree, turned, rd), eval_sh(degree, c, d), atol=1e-12)
    assert torch.allclose(m @ sh_rotation(r.T, degree), torch.eye(k, dtype=torch.float64), atol=1e-12)


def test_a_rotated_scene_seen_from_the_rotated_camera_renders_the_same_image():
    scene = random_scene(300, seed=3, dtype=torch.float64, sh_degree=3)
    state = {"means": scene.means, "quats": scene.quats, "shN": scene.sh[:, 1:]}
    r = Rotation.from_euler("xyz", [30, -50, 110], degrees=True).as_matrix()
    turned = rotate_state(state, r)
    cam = camera(48, 36)
    c2w = cam.camera_to_worlds[0].double().clone()
    c2w[:3, :3] = torch.as_tensor(r) @ c2w[:3, :3]
    c2w[:3, 3] = torch.as_tensor(r) @ c2w[:3, 3]
    turned_cam = Cameras.create(c2w[None].float(), cam.fx[0], cam.fy[0], cam.cx[0], cam.cy[0], 48, 36)
    raster = make_rasterizer("torch")
    settings = RenderSettings(sh_degree=3)
    before = raster.render(scene, cam, settings).rgb
    after_set = type(scene)(turned["means"], turned["quats"], scene.scales, scene.opacities,
                            torch.cat([scene.sh[:, :1], turned["shN"]], 1))  # fmt: skip
    after = raster.render(after_set, turned_cam, settings).rgb
    assert before.std() > 0.02
    assert torch.allclose(after.double(), before.double(), atol=1e-4)


def _model(n: int = 50, degree: int = 3) -> GaussianModel:
    g = torch.Generator().manual_seed(1)
    params = {
        "means": torch.randn(n, 3, generator=g) * 3,
        "scales": torch.randn(n, 3, generator=g) - 3,
        "quats": torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=1),
        "opacities": torch.randn(n, generator=g),
        "sh0": torch.randn(n, 1, 3, generator=g),
        "shN": torch.randn(n, num_sh_bases(degree) - 1, 3, generator=g) * 0.3,
    }
    return GaussianModel(params, degree)


def test_a_z_up_scene_is_written_y_down_and_read_back_in_its_own_world(tmp_path):
    model = _model()
    r = upright_rotation(np.array([0.0, 0.0, 1.0]))
    save_ply(model, tmp_path / "scene.ply", world_to_file=r)
    header = (tmp_path / "scene.ply").read_bytes().split(b"end_header")[0].decode("ascii")
    assert f"comment {WORLD_TO_FILE} " in header
    from metegs.gaussians.ply import read_ply_vertices

    v = read_ply_vertices(tmp_path / "scene.ply")
    means = model.params["means"].detach().numpy()
    assert np.allclose(v["y"], -means[:, 2], atol=1e-6) and np.allclose(v["z"], means[:, 1], atol=1e-6)
    back = load_ply(tmp_path / "scene.ply")
    for k in PARAM_NAMES:
        a, b = back.params[k].detach(), model.params[k].detach()
        if k == "quats":  # q and −q are the same rotation
            a = a * torch.sign((a * b).sum(-1, keepdim=True))
        assert torch.allclose(a, b, atol=1e-5), k


def test_files_without_the_comment_load_as_they_are_and_a_bad_one_is_named(tmp_path):
    model = _model(degree=1)
    save_ply(model, tmp_path / "peer.ply")
    assert WORLD_TO_FILE.encode() not in (tmp_path / "peer.ply").read_bytes()[:2000]
    assert torch.equal(load_ply(tmp_path / "peer.ply").params["means"], model.params["means"].detach())
    save_ply(model, tmp_path / "bad.ply", comments=[f"{WORLD_TO_FILE} 1 0 0 0 1 0 0 0 2"])
    with pytest.raises(DataError, match=r"bad\.ply.*not a rotation"):
        load_ply(tmp_path / "bad.ply")


def test_run_scene_ply_of_the_z_up_builtin_scene_is_written_upright(tmp_path):
    from metegs.data.config import DatasetConfig, SyntheticSceneConfig
    from metegs.engine.config import TrainConfig

    ds = DatasetConfig(synthetic=SyntheticSceneConfig(width=32, height=24, num_views=6, num_points=200))
    cfg = TrainConfig(max_steps=2, output_dir=tmp_path, experiment_name="r", progress=False, dataset=ds,
                      checkpoint_every=0, save_renders=False, device="cpu")  # fmt: skip
    trainer = cfg.setup()
    trainer.train()
    assert np.allclose(trainer.scene.up, [0, 0, 1])
    ply = trainer.run_dir / "scene.ply"
    header = ply.read_bytes().split(b"end_header")[0].decode("ascii")
    assert "Vertical Axis: y" in header and WORLD_TO_FILE in header
    back = load_ply(ply)
    assert torch.allclose(back.params["means"], trainer.model.params["means"].detach().cpu(), atol=1e-5)

    # the same file saved by another tool, which drops the header comment: turned back by the cameras' view
    from metegs.engine.run import load_run
    from metegs.gaussians.ply import read_ply_vertices

    rows = np.array(read_ply_vertices(ply))
    lines = ["ply", "format binary_little_endian 1.0", f"element vertex {len(rows)}"]
    lines += [f"property float {n}" for n in rows.dtype.names] + ["end_header"]
    (tmp_path / "edited.ply").write_bytes(("\n".join(lines) + "\n").encode() + rows.tobytes())
    with pytest.warns(UserWarning, match=r"edited\.ply: no 'metegs world_to_file' comment.*turned back"):
        reopened = load_run(trainer.run_dir, ply=tmp_path / "edited.ply")
    got = reopened.model.params["means"].detach().cpu()
    assert torch.allclose(got, trainer.model.params["means"].detach().cpu(), atol=1e-5)
    with warnings.catch_warnings():  # a file in the run's own frame is left as it is, without a word
        warnings.simplefilter("error")
        load_run(trainer.run_dir, ply=ply)
