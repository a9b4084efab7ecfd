"""Extra-point compensation: count rule and caps, IDW colours, distance cut-off, optimiser alignment, parity."""

from __future__ import annotations

import math

import pytest
import torch

from metegs.densify.extra_points import ExtraPointCompensation, ExtraPointsConfig, knn, robust_box
from metegs.engine.optim import OptimConfig, make_optimizers
from metegs.gaussians.model import GaussianModel, inverse_sigmoid


def grid_points(nx=10, ny=10, nz=10, size=(2.0, 1.0, 1.0)) -> torch.Tensor:
    axes = [torch.linspace(0, s, n) for s, n in zip(size, (nx, ny, nz))]
    return torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


def trained_model(means: torch.Tensor, seed: int = 0):
    """A model (SH degree 1) with random colours and one Adam step taken, so every row has moments."""
    g = torch.Generator().manual_seed(seed)
    n = means.shape[0]
    params = GaussianModel.empty_params(n, sh_degree=1)
    params["means"] = means.float()
    params["scales"] = torch.log(torch.rand(n, 3, generator=g) * 0.1 + 0.01)
    params["quats"] = torch.randn(n, 4, generator=g)
    params["opacities"] = inverse_sigmoid(torch.rand(n, generator=g) * 0.8 + 0.1)
    params["sh0"] = torch.randn(n, 1, 3, generator=g)
    params["shN"] = torch.randn(n, 3, 3, generator=g)
    model = GaussianModel(params, sh_degree=1)
    opts = make_optimizers(model.params, OptimConfig(), extent=1.0)
    for p in model.params.values():
        p.grad = torch.randn(p.shape, generator=g)
    for o in opts.values():
        o.step()
        o.zero_grad()
    return model, opts


def reference_colours(new_means, old_means, old_sh, k, t_d, proportional=False):
    """Plain loop: K nearest old Gaussians of each new point, those at >= t_d dropped, weighted mean."""
    out = []
    for p in new_means.double():
        d = [(float((p - q.double()).norm()), j) for j, q in enumerate(old_means)]
        d = [(dist, j) for dist, j in sorted(d)[:k] if dist < t_d]
        if proportional:
            total = sum(dist for dist, _ in d)
            w = [dist / total for dist, _ in d]
        else:
            inv = [1.0 / dist for dist, _ in d]
            w = [x / sum(inv) for x in inv]
        out.append(sum(wi * old_sh[j].double() for wi, (_, j) in zip(w, d)))
    return torch.stack(out)


def test_count_follows_the_volume_rule_and_the_caps():
    pts = grid_points()  # box 2 x 1 x 1: each coordinate value is shared by >= 100 points -> robust box = box
    low, high = robust_box(pts)
    assert low.tolist() == [0, 0, 0] and high.tolist() == [2, 1, 1]
    epc = ExtraPointCompensation(ExtraPointsConfig(rate=0.1), max_steps=1000, extent=1.0, initial_points=pts)
    assert epc.volume == pytest.approx(2.0)
    assert epc.planned_count(current=10_000) == 2000  # 2 / 0.1³
    assert epc.planned_count(current=500) == 500  # at most 1x the current count
    capped = ExtraPointCompensation(ExtraPointsConfig(rate=0.1, max_points=300), 1000, 1.0, pts)
    assert capped.planned_count(current=10_000) == 300
    relative = ExtraPointCompensation(ExtraPointsConfig(rate=0.1, max_relative=0.05), 1000, 1.0, pts)
    assert relative.planned_count(current=10_000) == 500
    scaled = ExtraPointCompensation(ExtraPointsConfig(rate=0.1), 1000, extent=2.0, initial_points=pts)
    assert scaled.planned_count(current=10_000) == 250  # spacing relative to the extent
    fixed = ExtraPointCompensation(ExtraPointsConfig(rate=0.0, max_points=700), 1000, 1.0, pts)
    assert fixed.planned_count(current=10_000) == 700


def test_robust_box_ignores_outliers():
    g = torch.Generator().manual_seed(0)
    pts = torch.rand(1000, 3, generator=g)
    pts[:5] = 100.0  # stray points
    low, high = robust_box(pts)
    assert (high < 1.0).all() and (low >= 0).all()


def test_new_colours_are_the_inverse_distance_weighted_mean_of_the_neighbours():
    g = torch.Generator().manual_seed(1)
    model, opts = trained_model(torch.rand(12, 3, generator=g))
    old = {k: v.detach().clone() for k, v in model.params.items()}
    cfg = ExtraPointsConfig(rate=0.05, neighbours=3, max_distance=0.5, max_relative=2.0, seed=3)
    epc = ExtraPointCompensation(cfg, max_steps=100, extent=1.0, initial_points=old["means"])
    n_new = epc.add_points(model, opts)
    assert n_new > 5 and len(model) == 12 + n_new
    new_means = model.params["means"][12:].detach()
    for name in ("sh0", "shN"):
        ref = reference_colours(new_means, old["means"], old[name], k=3, t_d=0.5)
        assert torch.allclose(model.params[name][12:].detach().double(), ref, atol=1e-5)
    # new Gaussians: identity rotation, opacity 0.1, isotropic scale
    assert torch.equal(model.params["quats"][12:], torch.tensor([1.0, 0, 0, 0]).repeat(n_new, 1))
    assert torch.allclose(torch.sigmoid(model.params["opacities"][12:]), torch.full((n_new,), 0.1))
    s = model.params["scales"][12:]
    assert torch.equal(s[:, 0], s[:, 1]) and torch.isfinite(s).all()
    # existing Gaussians untouched
    for k, v in old.items():
        assert torch.equal(model.params[k][:12], v)


def test_parity_mode_uses_distance_proportional_weights_and_reinitialises_everything():
    g = torch.Generator().manual_seed(2)
    model, opts = trained_model(torch.rand(12, 3, generator=g))
    old = {k: v.detach().clone() for k, v in model.params.items()}
    cfg = ExtraPointsConfig(rate=0.05, neighbours=3, max_distance=0.5, max_relative=2.0, seed=3, parity=True)
    n_new = ExtraPointCompensation(cfg, 100, 1.0, old["means"]).add_points(model, opts)
    assert n_new > 5
    new_means = model.params["means"][12:].detach()
    ref = reference_colours(new_means, old["means"], old["sh0"], k=3, t_d=0.5, proportional=True)
    assert torch.allclose(model.params["sh0"][12:].detach().double(), ref, atol=1e-5)
    idw = reference_colours(new_means, old["means"], old["sh0"], k=3, t_d=0.5)
    assert not torch.allclose(ref, idw, atol=1e-3)  # the two rules really differ
    n = len(model)
    assert torch.equal(model.params["quats"], torch.tensor([1.0, 0, 0, 0]).repeat(n, 1))
    assert torch.allclose(torch.sigmoid(model.params["opacities"]), torch.full((n,), 0.1))
    means = model.params["means"].detach().double()
    d = torch.cdist(means, means).sort(dim=1).values[:, 1:4]
    expected = 0.5 * torch.log((d**2).mean(dim=1))
    assert torch.allclose(model.params["scales"][:, 0].double(), expected, atol=1e-5)
    assert all(len(o.state) == 0 for o in opts.values())  # optimiser state reset, as a new Adam


def test_no_point_is_added_beyond_max_distance_from_every_gaussian():
    # Two tight clusters 1 unit apart: the robust box spans the gap, where no neighbour is within t_d.
    g = torch.Generator().manual_seed(4)
    a = torch.rand(100, 3, generator=g) * 0.1
    b = torch.rand(100, 3, generator=g) * 0.1 + torch.tensor([1.0, 0.0, 0.0])
    model, opts = trained_model(torch.cat([a, b]))
    old_means = model.params["means"].detach().clone()
    cfg = ExtraPointsConfig(rate=0.02, max_distance=0.1, max_points=400, neighbours=4)
    epc = ExtraPointCompensation(cfg, 100, extent=1.0, initial_points=old_means)
    n_new = epc.add_points(model, opts)
    assert 0 < n_new < epc.last["requested"] == 200  # 1x the current count; points in the gap dropped
    nearest = torch.cdist(model.params["means"][200:].detach(), old_means).min(dim=1).values
    assert (nearest < 0.1).all()


def test_optimiser_state_stays_aligned_and_a_step_after_adding_works():
    g = torch.Generator().manual_seed(5)
    model, opts = trained_model(torch.rand(50, 3, generator=g))
    moments = {k: opts[k].state[p]["exp_avg"].clone() for k, p in model.params.items()}
    epc = ExtraPointCompensation(ExtraPointsConfig(rate=0.1, max_distance=0.5), 100, 1.0, model.means.detach())
    n_new = epc.add_points(model, opts)
    assert n_new > 0
    for k, p in model.params.items():
        state = opts[k].state[p]
        assert opts[k].param_groups[0]["params"][0] is p
        assert state["exp_avg"].shape == p.shape and state["exp_avg_sq"].shape == p.shape
        assert torch.equal(state["exp_avg"][:50], moments[k]) and not state["exp_avg"][50:].any()
    loss = sum(p.square().sum() for p in model.params.values())
    loss.backward()
    for o in opts.values():
        o.step()
    assert all(torch.isfinite(p).all() for p in model.params.values())


def test_runs_once_at_its_step_and_remembers_it():
    g = torch.Generator().manual_seed(6)
    model, opts = trained_model(torch.rand(40, 3, generator=g))
    cfg = ExtraPointsConfig(at=0.25, rate=0.1, max_distance=0.5)
    epc = cfg.setup(max_steps=400, extent=1.0, initial_points=model.means.detach())
    assert epc.step_at == 100
    assert epc.step(model, opts, 99) == {} and len(model) == 40
    report = epc.step(model, opts, 100)
    assert report["extra_points"] == len(model) - 40 > 0
    assert epc.step(model, opts, 101) == {}
    assert epc.state_dict() == {"done": True, "volume": epc.volume}
    # a resumed run builds its compensator from the checkpoint's Gaussians; the state restores the initial volume
    again = cfg.setup(max_steps=400, extent=1.0, initial_points=model.means.detach()[:5])
    assert again.volume != epc.volume
    again.load_state_dict(epc.state_dict())
    assert again.volume == epc.volume
    n = len(model)
    assert again.step(model, opts, 100) == {} and len(model) == n


def test_knn_backends_agree():
    g = torch.Generator().manual_seed(7)
    ref, query = torch.rand(300, 3, generator=g), torch.rand(50, 3, generator=g)
    d1, i1 = knn(query, ref, 4, max_distance=0.15, method="kdtree")
    d2, i2 = knn(query, ref, 4, max_distance=0.15, method="torch", chunk=16)
    assert torch.equal(torch.isinf(d1), torch.isinf(d2)) and torch.isinf(d1).any()
    finite = torch.isfinite(d1)
    assert torch.allclose(d1[finite], d2[finite], atol=1e-6) and torch.equal(i1[finite], i2[finite])
    d, _ = knn(query, ref[:2], 4)  # fewer reference points than K
    assert torch.isinf(d[:, 2:]).all() and torch.isfinite(d[:, :2]).all()


def test_empty_or_tiny_models_are_harmless():
    model, opts = trained_model(torch.zeros(0, 3))
    epc = ExtraPointCompensation(ExtraPointsConfig(), 100, 1.0, torch.zeros(0, 3))
    assert epc.step(model, opts, epc.step_at) == {"extra_points": 0} and len(model) == 0
    model, opts = trained_model(torch.tensor([[0.0, 0.0, 0.0]]))
    epc = ExtraPointCompensation(ExtraPointsConfig(rate=0.01), 100, 1.0, grid_points())
    assert epc.add_points(model, opts) == 1 and len(model) == 2  # a zero-size box samples the one point
    assert math.isfinite(float(model.params["scales"][1, 0].detach()))
