"""Learnable per-view weather: starts at the physical streaks, stays within bounds, learns from a render."""

import torch

from metegs.meteo import CameraSpec, theta_from_values
from metegs.render.base import RenderSettings
from metegs.render.torch_backend import TorchRasterizer
from metegs.weather.learnable import LearnableTransients, LearnableWeatherConfig, screen_footprints
from metegs.weather.rain_streaks import RainStreaks, RainStreaksConfig
from tests.weather.test_weather_physics import F, H, W, black_wall, weather_scene


def rain(views=2, max_count=300):
    theta = theta_from_values(20.0, camera=CameraSpec.from_intrinsics(F, W, H, exposure_s=1 / 60, far_m=4.0))
    return RainStreaks(RainStreaksConfig(max_count=max_count), theta, weather_scene(views))


def test_starts_exactly_at_the_physical_streaks_with_zero_prior():
    inner = rain(3)
    learn = LearnableTransients(inner, [0, 1])
    for v in (0, 1):
        base, start = inner.gaussians_for(v), learn.gaussians_for(v)
        assert len(base) > 50
        for a, b in ((base.means, start.means), (base.opacities, start.opacities), (base.scales, start.scales)):
            assert torch.allclose(a, b, atol=1e-6)
        assert torch.allclose(base.sh, start.sh, atol=1e-4)
        assert abs(learn.coverage_ratio(v).item() - 1.0) < 1e-6 and learn.prior(v).item() < 1e-12
    held_out = learn.gaussians_for(2)  # a view it was not built for: the physical streaks
    assert torch.equal(held_out.means, inner.gaussians_for(2).means)
    assert learn.prior(2) is None


def test_bounds_hold_for_any_parameter_values():
    learn = LearnableTransients(rain(1), [0], LearnableWeatherConfig(position_bound=1.0, opacity_bound=2.0))
    r = learn.views["0"]
    with torch.no_grad():
        for p in (r.offset, r.opacity_logit, r.colour_logit):
            p.normal_(0.0, 100.0)
    g = learn.gaussians_for(0)
    step = (g.means - r.means).abs()
    assert bool((step <= r.scales.amax(1, keepdim=True) + 1e-7).all())
    assert bool((g.opacities <= torch.clamp(2.0 * r.opacities, max=0.99) + 1e-7).all() and (g.opacities >= 0).all())
    rgb = g.sh[:, 0] * 0.28209479177387814 + 0.5
    assert bool((rgb >= -1e-6).all() and (rgb <= 1 + 1e-6).all())
    assert learn.coverage_ratio(0).item() <= 2.0 + 1e-6


def test_footprint_is_the_gaussian_screen_area():
    inner = rain(1)
    g = inner.gaussians_for(0)
    area = screen_footprints(g, inner.scene.cameras[0])
    z = g.means[:, 2]
    # near the optical axis a streak in the image plane covers 2π σ∥ σ⊥ (f/z)²
    expected = 2 * torch.pi * g.scales[:, 0] * g.scales[:, 1] * (F / z) ** 2
    central = (g.means[:, :2].abs() / z[:, None] < 0.1).all(1)
    drawn = (area > 0) & central
    assert int(drawn.sum()) > 5
    assert torch.allclose(area[drawn], expected[drawn], rtol=0.05)


def test_residuals_learn_from_a_render_and_the_prior_pulls_coverage_back():
    inner = rain(1, max_count=200)
    learn = LearnableTransients(inner, [0], LearnableWeatherConfig(coverage_weight=1.0))
    wall = black_wall(6.0)
    raster = TorchRasterizer()
    cam = inner.scene.cameras[0]
    opt = torch.optim.Adam(learn.param_groups())
    # the "photo": the wall with no rain at all -> the render asks for less rain; the prior resists
    target = torch.zeros(H, W, 3)
    for _ in range(30):
        from metegs.gaussians.model import GaussianSet

        g = GaussianSet.cat([wall, learn.gaussians_for(0)])
        rgb = raster.render(g, cam, RenderSettings()).rgb
        loss = (rgb - target).abs().mean() * 50 + learn.prior(0)
        opt.zero_grad()
        loss.backward()
        opt.step()
    ratio = learn.coverage_ratio(0).item()
    assert 0.2 < ratio < 0.999  # learned to thin the rain, but the prior kept a share of it
