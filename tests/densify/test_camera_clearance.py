"""Camera clearance: Gaussians beside or behind a training camera go, with their Adam moments; what a camera sees
and everything around an object stays."""

from __future__ import annotations

import math

import torch

from metegs.cameras import Cameras
from metegs.densify import camera_clearance
from metegs.densify.camera_clearance import CameraClearance, camera_spacing, unseen_near_cameras
from metegs.densify.depth_prune import camera_depths
from metegs.engine.optim import OptimConfig, make_optimizers
from metegs.gaussians.model import GaussianModel
from tests.densify.test_depth_prune import cameras_at


def test_spacing_is_the_median_distance_to_the_nearest_other_camera():
    walk = torch.tensor([[0.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0], [5.0, 0, 0]])  # nearest: 1, 1, 1, 3
    assert math.isclose(camera_spacing(walk), 1.0)
    assert camera_spacing(walk[:1]) == 0.0


def test_unseen_near_cameras_matches_a_plain_loop_across_chunks(monkeypatch):
    monkeypatch.setattr(camera_clearance, "_PAIRS_PER_CHUNK", 7)  # 2 means per chunk: many chunks
    g = torch.Generator().manual_seed(0)
    cams = cameras_at([[0.0, 0, 0], [2.0, 0, 0], [4.0, 1, 0]])
    means = torch.rand(200, 3, generator=g) * torch.tensor([6.0, 3.0, 4.0]) - torch.tensor([1.0, 1.0, 2.0])
    z, seen = camera_depths(means, cams)
    centers = cams.camera_to_worlds[:, :3, 3]
    expected = []
    for n, m in enumerate(means):
        near = [c for c in range(3) if float((m - centers[c]).norm()) < 0.9]
        expected.append(bool(near) and not any(bool(seen[c, n]) for c in near))
    expected = torch.tensor(expected)
    assert expected.any() and not expected.all()
    assert torch.equal(unseen_near_cameras(means, cams, 0.9), expected)
    assert not unseen_near_cameras(means, cams, 0.0).any()


def test_prune_removes_the_gaussians_beside_and_behind_the_cameras_and_their_moments():
    walk = torch.tensor([[float(i), 0.0, 0.0] for i in range(5)])  # a street: cameras a step apart, looking along +z
    cams = cameras_at(walk.tolist())
    behind = walk + torch.tensor([0.1, -0.2, -0.2])  # floaters a fifth of a step behind each camera
    seen = walk + torch.tensor([0.0, 0.0, 0.3])  # in front of each camera, in its photo: kept
    ahead = walk + torch.tensor([0.0, 0.0, 3.0])  # the scene, 3 steps in front
    model = GaussianModel.from_points(torch.cat([behind, seen, ahead]), sh_degree=1)
    optimizers = make_optimizers(model.params, OptimConfig(), extent=1.0)
    model.params["means"].sum().backward()
    for opt in optimizers.values():
        opt.step()
    clearance = CameraClearance(cams, fraction=0.5, typical_depth=30.0)
    assert math.isclose(clearance.radius, 0.5)
    assert clearance.prune(model, optimizers) == 5
    assert torch.allclose(model.means.detach(), torch.cat([seen, ahead]), atol=1e-3)  # moved by the one Adam step
    assert optimizers["means"].state[model.params["means"]]["exp_avg"].shape == (10, 3)


def test_around_an_object_nothing_is_pruned():
    angles = torch.linspace(0, 2 * math.pi, 13)[:-1]
    ring = torch.stack([3 * angles.cos(), 3 * angles.sin(), torch.zeros(12)], dim=-1)  # cameras 3 units out
    c2w = torch.stack([cameras_at([e.tolist()], forward=(-e).tolist()).camera_to_worlds[0] for e in ring])
    cams = Cameras.create(c2w, 100.0, 100.0, 100.0, 100.0, 200, 200)  # each looking at the object
    obj = torch.randn(500, 3, generator=torch.Generator().manual_seed(1)) * 0.4
    model = GaussianModel.from_points(obj, sh_degree=0)
    optimizers = make_optimizers(model.params, OptimConfig(), extent=1.0)
    assert CameraClearance(cams, fraction=0.5, typical_depth=30.0).prune(model, optimizers) == 0
    assert len(model) == 500


def test_the_radius_stays_under_a_tenth_of_the_typical_depth():
    sparse = cameras_at([[0.0, 0, 0], [4.0, 0, 0], [8.0, 0, 0]])  # a few cameras far apart
    assert math.isclose(CameraClearance(sparse, fraction=0.5, typical_depth=100.0).radius, 2.0)
    assert math.isclose(CameraClearance(sparse, fraction=0.5, typical_depth=6.0).radius, 0.6)
