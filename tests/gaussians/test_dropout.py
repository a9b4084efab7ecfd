"""Random Gaussian dropping while training: the schedule, the draw, its gradients and the trainer's use of it."""

import math

import pytest
import torch

from metegs.gaussians.dropout import drop_gaussians, drop_rate_at
from metegs.render import RenderSettings
from metegs.render.torch_backend import TorchRasterizer
from metegs.testing import camera, random_scene
from metegs.weather.conditions import ConditionsConfig
from tests.engine.test_trainer import tiny_config


def test_rate_rises_linearly_to_the_final_share():
    assert drop_rate_at(0, 3000, 0.1) == 0.0
    assert drop_rate_at(1500, 3000, 0.1) == pytest.approx(0.05)
    assert drop_rate_at(3000, 3000, 0.1) == pytest.approx(0.1)
    assert drop_rate_at(4000, 3000, 0.1) == pytest.approx(0.1)  # a resumed run past its end stays at the share
    assert drop_rate_at(10, 3000, 0.0) == 0.0


def test_drop_leaves_out_the_share_and_keeps_the_expected_cover():
    n, rate = 40000, 0.2
    g = random_scene(n, seed=0)
    dropped = drop_gaussians(g, rate, torch.Generator().manual_seed(3))
    out = dropped.opacities == 0
    share = float(out.float().mean())
    assert abs(share - rate) < 4 * math.sqrt(rate * (1 - rate) / n)  # binomial, 4 sigma
    torch.testing.assert_close(dropped.opacities[~out], g.opacities[~out] / (1 - rate))
    # the expected opacity of each Gaussian is unchanged: E[keep / (1 - r)] = 1
    assert float(dropped.opacities.sum() / g.opacities.sum()) == pytest.approx(1.0, abs=0.02)
    for name in ("means", "quats", "scales", "sh"):
        assert getattr(dropped, name) is getattr(g, name)
    again = drop_gaussians(g, rate, torch.Generator().manual_seed(3))
    assert torch.equal(again.opacities, dropped.opacities)
    assert drop_gaussians(g, 0.0, torch.Generator()) is g
    with pytest.raises(ValueError, match="no Gaussian"):
        drop_gaussians(g, 1.0, torch.Generator())


def test_dropped_gaussians_take_no_gradient():
    g = random_scene(300, seed=1, sh_degree=0)
    for t in (g.means, g.scales, g.opacities, g.sh):
        t.requires_grad_(True)
    dropped = drop_gaussians(g, 0.3, torch.Generator().manual_seed(0))
    out_mask = dropped.opacities.detach() == 0
    render = TorchRasterizer().render(dropped, camera(48, 40), RenderSettings(background=torch.zeros(3), sh_degree=0))
    render.rgb.square().sum().backward()
    for t in (g.means, g.scales, g.sh, g.opacities):
        assert float(t.grad[out_mask].abs().max()) == 0.0
    assert float(g.sh.grad[~out_mask].abs().max()) > 0.0  # the kept ones are fitted


def test_trainer_drops_in_training_renders_only(tmp_path):
    trainer = tiny_config(tmp_path, drop_gaussians=0.5).setup()
    trainer.step = trainer.config.max_steps // 2  # rate 0.25 here
    first, second = trainer.step_gaussians(), trainer.step_gaussians()
    torch.testing.assert_close(first.opacities, second.opacities)  # every render of a step draws the same
    left_out = float((first.opacities == 0).float().mean())
    assert 0.1 < left_out < 0.4
    trainer.step += 1
    assert not torch.equal(trainer.step_gaussians().opacities, first.opacities)  # a new draw each step
    with torch.no_grad():
        eval_render = trainer.render(0).rgb
        full = trainer.rasterizer.render(
            trainer.model.activated(), trainer.dataset.cameras[0], RenderSettings(background=torch.zeros(3))
        ).rgb
        photo = trainer.photo_render(0, torch.zeros(3)).rgb
    torch.testing.assert_close(eval_render, full)  # evaluation sees every Gaussian
    assert float((photo - trainer.as_photographed(eval_render, 0)).abs().max()) > 1e-3  # the step's photo fit not
    off = tiny_config(tmp_path / "off", drop_gaussians=0.0).setup()
    off.step = 30
    torch.testing.assert_close(off.step_gaussians().opacities, off.model.activated().opacities)


@pytest.mark.parametrize(
    ("conditions", "dropped", "why"),
    [
        (ConditionsConfig(), True, "on"),  # no weather stated: the photos are taken as clear
        (ConditionsConfig(precip_mm_h=0.5), True, "on"),  # light rain neither blurs nor shows
        (ConditionsConfig(precip_mm_h=20.0), False, "rain"),
        (ConditionsConfig(precip_mm_h=0.0, visibility_m=100.0), False, "medium taking"),
    ],
)
def test_drop_is_off_where_the_photos_show_weather(tmp_path, conditions, dropped, why):
    trainer = tiny_config(tmp_path, drop_gaussians=0.1, conditions=conditions).setup()
    assert trainer.drop_rate == (0.1 if dropped else 0.0)
    decision = trainer.decisions["drop gaussians"]
    assert decision.startswith("on" if dropped else "off") and why in decision
