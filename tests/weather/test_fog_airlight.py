"""The fog's direction-dependent airlight: constant at the start, learnable towards a sky brighter at the
horizon, and old checkpoints load with it at zero."""

from __future__ import annotations

import math

import torch

from metegs.meteo import theta_from_values
from metegs.render.base import RenderOutput, RenderSettings
from metegs.weather.fog_analytic import FogAnalytic, FogAnalyticConfig, ray_directions

from .test_weather_physics import H, W, cameras, spec, weather_scene


def _empty_view() -> RenderOutput:
    """A view that sees nothing but the distance (the sky): it shows the airlight alone."""
    zeros = torch.zeros(H, W)
    return RenderOutput(rgb=torch.zeros(H, W, 3), alpha=zeros, depth=zeros, radii=torch.zeros(0),
                        means2d=torch.zeros(0, 2), num_intersections=0, width=W, height=H)  # fmt: skip


def _fog(**kw) -> FogAnalytic:
    theta = theta_from_values(0.0, visibility_m=300.0, fog_kind="fog", camera=spec())
    return FogAnalytic(FogAnalyticConfig(airlight=(0.8, 0.8, 0.8), **kw), theta, weather_scene())


def test_ray_directions_are_unit_and_centred_on_the_axis():
    d = ray_directions(cameras(1)[0], H, W)
    assert torch.allclose(d.norm(dim=-1), torch.ones(H, W), atol=1e-6)
    centre = d[H // 2 - 1 : H // 2 + 1, W // 2 - 1 : W // 2 + 1].mean(dim=(0, 1))
    assert torch.allclose(centre / centre.norm(), torch.tensor([0.0, 0.0, 1.0]), atol=1e-3)


def test_the_airlight_starts_constant_and_learns_a_gradient_over_the_sky():
    fog = _fog()
    settings = RenderSettings(background=torch.zeros(3))
    sky = fog.apply(torch.zeros(H, W, 3), _empty_view(), 0, settings)
    assert torch.allclose(sky, torch.full((H, W, 3), 0.8), atol=1e-6)  # as the constant model
    # a sky brighter towards its bottom rows (the horizon below a camera looking up, +y is down)
    target = 0.7 + 0.2 * torch.linspace(0, 1, H)[:, None, None].expand(H, W, 3)
    opt = torch.optim.Adam([fog.airlight_logit, fog.airlight_dir], lr=0.05)
    for _ in range(300):
        opt.zero_grad()
        loss = (fog.apply(torch.zeros(H, W, 3), _empty_view(), 0, settings) - target).abs().mean()
        loss.backward()
        opt.step()
    assert float(loss) < 0.02
    assert fog.airlight_dir[:, 1].min() > 0  # brighter along +y, as the target


def test_a_constant_airlight_when_asked_and_for_old_checkpoints():
    fixed = _fog(directional_airlight=False)
    assert not fixed.airlight_dir.requires_grad
    old = {k: v for k, v in _fog().state_dict().items() if k != "airlight_dir"}
    fog = _fog()
    with torch.no_grad():
        fog.airlight_dir.fill_(math.pi)
    fog.load_state_dict(old)
    assert torch.equal(fog.airlight_dir, torch.zeros(3, 3))
