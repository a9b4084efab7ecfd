"""Adaptive density control: clone / split / prune / reset, optimiser state kept aligned, schedule."""

import torch

from metegs.densify.adc import AdaptiveDensityControl, ADCConfig
from metegs.engine.optim import OptimConfig, make_optimizers
from metegs.gaussians.model import GaussianModel, inverse_sigmoid
from metegs.render.base import RenderOutput


def model_with(scales, opacities, n_extra_state=True):
    n = len(scales)
    params = GaussianModel.empty_params(n, sh_degree=1)
    params["means"] = torch.arange(n, dtype=torch.float32)[:, None].repeat(1, 3)
    params["scales"] = torch.log(torch.tensor(scales, dtype=torch.float32))[:, None].repeat(1, 3)
    params["opacities"] = inverse_sigmoid(torch.tensor(opacities, dtype=torch.float32))
    model = GaussianModel(params, sh_degree=1)
    opts = make_optimizers(model.params, OptimConfig(), extent=1.0)
    # One optimiser step so Adam has per-row moments to keep aligned.
    for p in model.params.values():
        p.grad = torch.ones_like(p)
    for o in opts.values():
        o.step()
        o.zero_grad()
    return model, opts


def fake_render(model, grad2d, width=100, height=50):
    """A RenderOutput whose means2d carries the given screen gradient (pixels)."""
    n = len(model)
    means2d = torch.zeros(n, 2, requires_grad=True)
    means2d.grad = torch.as_tensor(grad2d, dtype=torch.float32)
    return RenderOutput(
        rgb=torch.zeros(height, width, 3),
        alpha=torch.zeros(height, width),
        depth=torch.zeros(height, width),
        radii=torch.full((n,), 5, dtype=torch.int32),
        means2d=means2d,
        num_intersections=0,
        width=width,
        height=height,
    )


def test_schedule_is_a_fraction_of_the_run():
    adc = AdaptiveDensityControl(ADCConfig(), max_steps=3000, extent=1.0)
    assert adc.schedule() == {"start": 50, "stop": 1500, "every": 100, "reset_every": 300}
    adc = AdaptiveDensityControl(ADCConfig(), max_steps=30000, extent=1.0)
    assert adc.schedule() == {"start": 500, "stop": 15000, "every": 100, "reset_every": 3000}
    short = AdaptiveDensityControl(ADCConfig(), max_steps=300, extent=1.0).schedule()
    assert short["every"] == 14  # about 10 refinements even in a short run
    assert short["reset_every"] == 0  # 30-step reset periods would leave no time to recover


def test_horizon_keeps_a_longer_run_on_the_horizons_schedule():
    three_k = AdaptiveDensityControl(ADCConfig(), max_steps=3000, extent=1.0).schedule()
    long = AdaptiveDensityControl(ADCConfig(horizon=3000), max_steps=30000, extent=1.0)
    assert long.schedule() == three_k
    # No refinement and no reset after the horizon's window, however strong the gradients.
    model, opts = model_with([0.001, 0.5], [0.5, 0.5])
    for step in (3000, 6000, 15000):
        long.update_stats(model, fake_render(model, [[1e-3, 0]] * 2))
        assert long.step(model, opts, step) == {} and len(model) == 2
    # Inside the window it refines as the 3000-step run does.
    long.update_stats(model, fake_render(model, [[1e-3, 0]] * 2))
    assert long.step(model, opts, 1000)["clone"] == 1 and len(model) > 2
    # A run shorter than the horizon keeps its own schedule.
    capped = AdaptiveDensityControl(ADCConfig(horizon=3000), max_steps=2000, extent=1.0).schedule()
    assert capped == AdaptiveDensityControl(ADCConfig(), max_steps=2000, extent=1.0).schedule()


def test_refinement_waits_for_a_pass_over_the_views():
    adc = AdaptiveDensityControl(ADCConfig(), max_steps=3000, extent=1.0, num_train_views=42)
    assert adc.schedule() == {"start": 50, "stop": 1500, "every": 100, "reset_every": 300}
    adc = AdaptiveDensityControl(ADCConfig(), max_steps=600, extent=1.0, num_train_views=42)
    assert adc.schedule()["every"] == 42 and adc.schedule()["reset_every"] == 0
    adc = AdaptiveDensityControl(ADCConfig(), max_steps=50, extent=1.0, num_train_views=42)
    assert adc.schedule()["every"] == 42 > adc.schedule()["stop"]  # too short to refine at all


def test_clone_small_split_large_keep_quiet():
    # Gaussians 0, 1: large gradient, small scale -> clone; 2: large gradient, large scale -> split; 3: quiet.
    model, opts = model_with([0.001, 0.001, 0.5, 0.001], [0.5, 0.5, 0.5, 0.5])
    adc = AdaptiveDensityControl(ADCConfig(), max_steps=3000, extent=1.0)
    # NDC gradient = pixel gradient * (W/2, H/2): 1e-5 * 50 = 5e-4 > 2e-4.
    adc.update_stats(model, fake_render(model, [[1e-5, 0]] * 3 + [[1e-7, 0]]))
    parent = float(torch.exp(model.params["scales"][2, 0].detach()))
    report = adc.refine(model, opts, step=100)
    assert report == {"clone": 2, "split": 1, "prune": 1}
    assert len(model) == 4 + 2 + 2 - 1
    scales = torch.exp(model.params["scales"][:, 0])
    assert torch.isclose(scales, torch.tensor(parent / 1.6)).sum() == 2  # two children of the split one
    assert not torch.isclose(scales, torch.tensor(parent)).any()  # the parent is gone
    for name, p in model.params.items():  # optimiser points at the new tensors with aligned moments
        opt = opts[name]
        assert opt.param_groups[0]["params"][0] is p
        assert opt.state[p]["exp_avg"].shape == p.shape
    # New rows start with zero moments, kept rows keep theirs.
    m = opts["means"].state[model.params["means"]]["exp_avg"]
    assert (m[:2] != 0).all() and (m[-2:] == 0).all()


def test_split_children_are_sampled_from_the_parent():
    torch.manual_seed(0)
    model, opts = model_with([0.5], [0.5])
    adc = AdaptiveDensityControl(ADCConfig(split_samples=2000), max_steps=3000, extent=1.0)
    adc.update_stats(model, fake_render(model, [[1e-4, 0]]))
    adc.refine(model, opts, step=100)
    offsets = model.params["means"] - 0.0
    assert len(model) == 2000
    assert torch.allclose(offsets.std(0), torch.tensor(0.5), rtol=0.1)


def test_prune_transparent_and_reset_opacity():
    model, opts = model_with([0.01, 0.01, 0.01], [0.001, 0.5, 0.9])
    adc = AdaptiveDensityControl(ADCConfig(), max_steps=3000, extent=1.0)
    adc.update_stats(model, fake_render(model, [[0, 0]] * 3))
    assert adc.refine(model, opts, step=100)["prune"] == 1
    report = adc.step(model, opts, step=300)
    assert report.get("reset") == 1
    assert torch.allclose(torch.sigmoid(model.params["opacities"]), torch.tensor([0.01, 0.01]), atol=1e-6)
    st = opts["opacities"].state[model.params["opacities"]]
    assert (st["exp_avg"] == 0).all() and (st["exp_avg_sq"] == 0).all()


def test_no_reset_after_refinement_stops_and_budget_is_respected():
    model, opts = model_with([0.001] * 4, [0.5] * 4)
    adc = AdaptiveDensityControl(ADCConfig(max_gaussians=5), max_steps=3000, extent=1.0)
    adc.update_stats(model, fake_render(model, [[1e-5, 0], [2e-5, 0], [3e-5, 0], [4e-5, 0]]))
    report = adc.refine(model, opts, step=100)
    assert report["clone"] == 1 and len(model) == 5
    assert "reset" not in adc.step(model, opts, step=1800)


def test_weather_gaussians_do_not_enter_statistics():
    model, _ = model_with([0.01, 0.01], [0.5, 0.5])
    adc = AdaptiveDensityControl(ADCConfig(), max_steps=3000, extent=1.0)
    out = fake_render(model, [[1.0, 0], [1.0, 0]])
    # A render of 2 scene + 3 weather Gaussians: only the first two rows count.
    out.means2d = torch.zeros(5, 2, requires_grad=True)
    out.means2d.grad = torch.ones(5, 2)
    out.radii = torch.full((5,), 5, dtype=torch.int32)
    adc.update_stats(model, out, num_scene=2)
    assert adc.state.count.tolist() == [1.0, 1.0]


def test_after_the_first_reset_gaussians_larger_than_the_world_bound_are_pruned():
    model, opts = model_with([0.04, 0.3, 0.7], [0.9, 0.9, 0.9])  # extent 1: default bound 0.5
    adc = AdaptiveDensityControl(ADCConfig(), max_steps=3000, extent=1.0)
    assert adc.reset_every == 300
    adc.update_stats(model, fake_render(model, [[0, 0]] * 3))
    assert adc.refine(model, opts, step=200)["prune"] == 0  # before the first reset: none
    adc.update_stats(model, fake_render(model, [[0, 0]] * 3))
    assert adc.refine(model, opts, step=400)["prune"] == 1  # after it: only the one over half the extent
    kept = torch.exp(model.params["scales"][:, 0])
    assert torch.allclose(kept, torch.tensor([0.04, 0.3]), rtol=0.01)  # (moved by model_with's one Adam step)
    tight = AdaptiveDensityControl(ADCConfig(prune_scale3d=0.1), max_steps=3000, extent=1.0)
    tight.update_stats(model, fake_render(model, [[0, 0]] * 2))
    assert tight.refine(model, opts, step=400)["prune"] == 1  # the reference's 0.1 takes the 0.3 one too
