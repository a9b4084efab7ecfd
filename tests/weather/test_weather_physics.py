"""Weather models against closed forms: fog transmittance, streak coverage and tilt, zero weather, view consistency."""

import functools
import math
from dataclasses import replace

import pytest
import torch

from metegs.cameras import Cameras
from metegs.gaussians.model import GaussianSet
from metegs.gaussians.sh import SH_C1, SH_C2, rgb_to_sh
from metegs.meteo import CameraSpec, theta_from_values
from metegs.render.base import RenderOutput, RenderSettings
from metegs.render.torch_backend import TorchRasterizer
from metegs.weather import WeatherScene, build_weather_models, render_with_weather
from metegs.weather.fog_analytic import FogAnalytic, FogAnalyticConfig, direction_basis, world_directions
from metegs.weather.fog_gaussians import FogGaussiansConfig
from metegs.weather.rain_streaks import RainStreaks, RainStreaksConfig

W = H = 48
F = 48.0


def cameras(n: int = 1, shift: float = 0.05) -> Cameras:
    """Cameras at the origin (+ x shifts) looking down +z (OpenCV); world up is -y."""
    c2w = torch.eye(4).repeat(n, 1, 1)
    c2w[:, 0, 3] = torch.arange(n) * shift
    return Cameras.create(c2w, F, F, W / 2, H / 2, W, H)


def spec(far_m: float | None = 4.0) -> CameraSpec:
    """This 48 px camera would see no streak beyond its near limit by the contrast rule: fix the far depth."""
    return CameraSpec.from_intrinsics(F, W, H, exposure_s=1 / 60, far_m=far_m)


def weather_scene(n_views: int = 1) -> WeatherScene:
    return WeatherScene(cameras(n_views), torch.tensor([0.0, -1.0, 0.0]), 1.0, None, seed=3)


def black_wall(depth: float, n_side: int = 40) -> GaussianSet:
    """An opaque black plane at camera depth ``depth`` filling the view."""
    half = depth * (W / 2) / F * 1.3
    xs = torch.linspace(-half, half, n_side)
    grid = torch.stack(torch.meshgrid(xs, xs, indexing="ij"), -1).reshape(-1, 2)
    n = len(grid)
    means = torch.cat([grid, torch.full((n, 1), depth)], 1)
    s = 2 * half / n_side
    return GaussianSet(
        means,
        torch.tensor([[1.0, 0, 0, 0]]).expand(n, 4),
        torch.tensor([s, s, s * 0.01]).expand(n, 3),
        torch.full((n,), 0.99),
        rgb_to_sh(torch.zeros(3)).expand(n, 1, 3),
    )


def flat_view(depth: float) -> RenderOutput:
    """An opaque black render at camera depth ``depth`` everywhere."""
    return RenderOutput(
        rgb=torch.zeros(H, W, 3),
        alpha=torch.ones(H, W),
        depth=torch.full((H, W), depth),
        radii=torch.zeros(0),
        means2d=torch.zeros(0, 2),
        num_intersections=0,
        width=W,
        height=H,
    )


def test_fog_analytic_transmittance_is_exp_minus_beta_d():
    theta = theta_from_values(0.0, visibility_m=300.0, fog_kind="fog", camera=spec())
    fog = FogAnalytic(FogAnalyticConfig(airlight=(1.0, 1.0, 1.0)), theta, weather_scene())
    beta = fog.beta_rgb
    for d in (20.0, 60.0, 150.0):
        out = flat_view(d)
        rgb = fog.apply(out.rgb, out, 0, RenderSettings())
        t = 1.0 - rgb[H // 2, W // 2]  # the centre ray has length d
        expected = torch.exp(-beta * d)
        assert torch.allclose(t, expected, rtol=0.01, atol=1e-4)
        # what densification divides by: the same medium at a point on that ray, averaged over R, G, B
        point_t = fog.transmittance(torch.tensor([[0.0, 0.0, d]]), 0)
        assert point_t.shape == (1,) and float(point_t) == pytest.approx(float(t.mean().detach()), rel=0.01)
    assert float(beta.detach().mean()) == pytest.approx(math.log(20) / 300.0, rel=0.05)  # 5 % contrast rule


@functools.cache
def white_fog_gaussians():
    """(fog-gaussians with a white airlight at 300 m visibility, its one-camera scene), built once."""
    theta = theta_from_values(0.0, visibility_m=300.0, fog_kind="fog", camera=spec())
    scene = weather_scene()
    (fog,) = build_weather_models([FogGaussiansConfig(airlight=(1.0, 1.0, 1.0))], theta, scene)
    return fog, scene


@pytest.mark.parametrize("depth", [20.0, 60.0, 150.0])
def test_fog_gaussians_transmittance_within_one_percent(depth):
    """β·d = 0.2, 0.6, 1.5 at 300 m visibility: the medium in front of a black wall transmits e^{−β·d} within 1 %
    (measured +0.2 %, +0.2 %, −0.1 %)."""
    fog, scene = white_fog_gaussians()
    r = render_with_weather(TorchRasterizer(), black_wall(depth), [fog], 0, scene.cameras[0])
    rays = torch.sqrt(((torch.arange(W) + 0.5 - W / 2) / F) ** 2)[None, :] ** 2
    rays = torch.sqrt(rays + ((torch.arange(H) + 0.5 - H / 2) / F)[:, None] ** 2 + 1.0)
    measured = float((1.0 - r.rgb.mean(-1)).mean())
    expected = float(torch.exp(-fog.beta_per_m * depth * rays).mean())
    assert measured == pytest.approx(expected, rel=0.01)
    centre = float(1.0 - r.rgb[H // 2 - 1 : H // 2 + 1, W // 2 - 1 : W // 2 + 1].mean())
    assert float(fog.transmittance(torch.tensor([[0.0, 0.0, depth]]), 0)) == pytest.approx(centre, rel=0.02)


def test_zero_weather_renders_the_clean_image_and_adds_nothing():
    theta = theta_from_values(0.0, visibility_m=None, camera=spec())
    scene = weather_scene()
    models = build_weather_models(["rain-streaks", "fog-gaussians", "fog-analytic", "lens-droplets"], theta, scene)
    assert not any(m.active for m in models)
    wall = black_wall(5.0)
    wall = GaussianSet(wall.means, wall.quats, wall.scales, wall.opacities, rgb_to_sh(torch.rand(len(wall), 1, 3)))
    r = render_with_weather(TorchRasterizer(), wall, models, 0, scene.cameras[0])
    clean = TorchRasterizer().render(wall, scene.cameras[0])
    assert r.num_weather == 0 and torch.equal(r.rgb, clean.rgb)


def test_streak_tilt_follows_the_wind():
    theta = theta_from_values(10.0, wind_speed_m_per_s=4.0, wind_dir_deg_from=90.0, camera=spec())
    rain = RainStreaks(RainStreaksConfig(), theta, weather_scene())
    up = torch.tensor([0.0, -1.0, 0.0])
    angle = math.degrees(math.acos(float(-rain.fall_direction @ up)))
    expected = math.degrees(math.atan(theta.rain.wind_at_drop_height_m_per_s / theta.rain.fall_speed_m_per_s))
    assert angle == pytest.approx(expected, abs=2.0)
    assert angle == pytest.approx(theta.rain.tilt_deg, abs=2.0)


def rain_coverage(p_mm_h: float, views: int = 4) -> tuple[float, float]:
    """(measured mean alpha of rain alone, expected from the drops' projected areas)."""
    theta = theta_from_values(p_mm_h, camera=spec())
    scene = weather_scene(views)
    rain = RainStreaks(RainStreaksConfig(colour=(1.0, 1.0, 1.0)), theta, scene)
    r = theta.rain
    measured = 0.0
    for v in range(views):
        g = rain.gaussians_for(v)
        out = TorchRasterizer().render(g, scene.cameras[v])
        measured += float(out.alpha.mean()) / views
    near, far = r.near_m, r.far_m
    mean_inv_z2 = (far - near) / ((far**3 - near**3) / 3.0)
    d = r.diameter_mean_mm / 1000.0
    expected = r.expected_count * math.pi / 4 * (F * d) ** 2 * mean_inv_z2 / (W * H)
    return measured, expected


def test_streak_coverage_matches_projected_drop_area():
    measured, expected = rain_coverage(20.0)
    assert measured == pytest.approx(expected, rel=0.15)


def test_more_rain_more_coverage_across_wmo_classes():
    coverages = [rain_coverage(p, views=2)[0] for p in (0.5, 5.0, 20.0, 80.0)]
    assert all(b > a for a, b in zip(coverages, coverages[1:])), coverages


def test_two_views_share_the_fog_but_not_the_rain():
    theta = theta_from_values(20.0, visibility_m=300.0, fog_kind="fog", camera=spec())
    scene = weather_scene(2)
    rain, fog = build_weather_models(["rain-streaks", "fog-gaussians"], theta, scene)
    assert fog.gaussians_for(0) is fog.gaussians_for(1)
    a, b = rain.gaussians_for(0), rain.gaussians_for(1)
    assert not torch.equal(a.means[: min(len(a), len(b))], b.means[: min(len(a), len(b))])
    again = rain.gaussians_for(0)
    assert torch.equal(a.means, again.means)  # reproducible per view


def test_fog_record_prior_pulls_beta_back_to_theta_and_is_off_unless_asked():
    theta = theta_from_values(0.0, visibility_m=300.0, fog_kind="fog", camera=spec())
    fog = FogAnalytic(FogAnalyticConfig(record_prior="on", record_prior_weight=0.5), theta, weather_scene())
    start = fog.log_beta.detach().clone()
    assert float(fog.prior(0).detach()) == 0.0  # at θ's value
    with torch.no_grad():
        fog.log_beta += torch.tensor([0.2, -0.4, 0.0])
    prior = fog.prior(0)
    assert float(prior.detach()) == pytest.approx(0.5 * (0.2**2 + 0.4**2) / 3, rel=1e-5)
    prior.backward()
    assert torch.all(torch.sign(fog.log_beta.grad) == torch.sign(fog.log_beta.detach() - start))  # descent returns
    summary = fog.summary()
    assert summary["record_beta_per_m"] == pytest.approx(start.exp().tolist(), rel=1e-4)
    assert summary["beta_per_m"][0] > summary["record_beta_per_m"][0] > summary["beta_per_m"][1]
    assert FogAnalytic(FogAnalyticConfig(), theta, weather_scene()).prior(0) is None  # auto: the trainer decides
    fixed = FogAnalytic(FogAnalyticConfig(record_prior="on", learnable=False), theta, weather_scene())
    assert fixed.prior(0) is None


def test_height_fog_optical_depth_matches_the_integral_along_each_ray():
    theta = theta_from_values(0.0, visibility_m=300.0, fog_kind="fog", camera=spec())
    fog = FogAnalytic(FogAnalyticConfig(airlight=(1.0, 1.0, 1.0)), theta, weather_scene())
    d = 150.0
    uniform = fog.apply(torch.zeros(H, W, 3), flat_view(d), 0, RenderSettings()).detach()
    assert fog.learn_layers() and fog.layered
    assert torch.equal(fog.apply(torch.zeros(H, W, 3), flat_view(d), 0, RenderSettings()).detach(), uniform)
    k = 0.02  # ln β falls 0.02 per metre of height (scale height 50 m)
    with torch.no_grad():
        fog.height_rate.fill_(100 * k)
    rgb = fog.apply(torch.zeros(H, W, 3), flat_view(d), 0, RenderSettings())
    beta, a = fog.beta_rgb.detach(), fog.airlight.detach()
    for row, col in ((0, 0), (H // 2, W // 2), (H - 1, 5)):
        ray = torch.tensor([(col + 0.5 - W / 2) / F, (row + 0.5 - H / 2) / F, 1.0], dtype=torch.float64)
        length = d * float(ray.norm())
        rise = float(ray[1] * -1.0 / ray.norm())  # up is -y
        s = (torch.arange(4000, dtype=torch.float64) + 0.5) / 4000 * length
        tau = beta.double() * float(torch.exp(-k * rise * s).mean()) * length  # the integral, numerically
        t = 1.0 - rgb[row, col].detach().double() / a.double()
        assert torch.allclose(t, torch.exp(-tau), rtol=1e-3), (row, col)
        point = (ray * d).float()[None]  # the surface that pixel sees: the same medium in front of it
        assert float(fog.transmittance(point, 0)) == pytest.approx(float(t.mean()), rel=1e-3)
    t_up, t_down = (float(1 - rgb[row, W // 2, 0].detach() / a[0]) for row in (0, H - 1))
    assert t_up > t_down  # looking up, the fog thins: more of the scene shows
    rgb.sum().backward()
    assert float(fog.height_rate.grad.abs()) > 0  # the photos can move it
    assert fog.summary()["scale_height_m"] == pytest.approx(50.0)


def tilted_cameras(degrees: tuple[float, ...]) -> Cameras:
    """Cameras at the origin looking along +z tilted up by each of ``degrees`` (world up is -y)."""
    c2w = torch.eye(4).repeat(len(degrees), 1, 1)
    for i, a in enumerate(math.radians(d) for d in degrees):
        c2w[i, 1:3, 1:3] = torch.tensor([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    return Cameras.create(c2w, F, F, W / 2, H / 2, W, H)


def test_direction_basis_is_the_real_spherical_harmonics_without_the_constant():
    z, x = torch.tensor([0.0, 0.0, 1.0]), torch.tensor([1.0, 0.0, 0.0])
    assert direction_basis(1, z).tolist() == pytest.approx([0.0, SH_C1, 0.0])  # -C1·y, C1·z, -C1·x
    assert direction_basis(1, x).tolist() == pytest.approx([0.0, 0.0, -SH_C1])
    two = direction_basis(2, torch.stack([z, x]))
    assert two.shape == (2, 8) and two[0, 5].item() == pytest.approx(2 * SH_C2[2])  # (2z² − x² − y²)·C
    assert two[1, 7].item() == pytest.approx(SH_C2[4])  # (x² − y²)·C


def test_the_airlight_learns_how_it_changes_with_the_viewing_direction():
    """Where nothing is rendered a view shows the airlight. Under a sky brighter at the horizon than above and below it
    (real fog, and the independent family's), one airlight errs by the spread and the learned directions fit it; until
    they learn, the medium renders the one airlight exactly as before."""
    theta = theta_from_values(0.0, visibility_m=300.0, fog_kind="fog", camera=spec())
    tilts = (-40.0, -15.0, 0.0, 20.0, 45.0)
    scene = WeatherScene(tilted_cameras(tilts), torch.tensor([0.0, -1.0, 0.0]), 1.0, None, seed=3)
    fog = FogAnalytic(FogAnalyticConfig(airlight=(0.8, 0.8, 0.8), airlight_degree=2), theta, scene)
    sky = replace(flat_view(0.0), alpha=torch.zeros(H, W))
    assert torch.equal(fog.apply(torch.zeros(H, W, 3), sky, 0, RenderSettings()), fog.airlight.expand(H, W, 3))
    targets = []
    for i in range(len(tilts)):
        elevation = world_directions(scene.cameras[i], H, W) @ torch.tensor([0.0, -1.0, 0.0])
        targets.append(0.8 * (0.85 + 0.15 * (1.0 - elevation.abs())))
    one = torch.stack(targets).mean()
    one_error = float(torch.stack([(t - one).abs().mean() for t in targets]).mean())
    assert fog.learn_directions() and fog.directional
    optimiser = torch.optim.Adam([fog.airlight_sh, fog.airlight_logit], lr=0.05)
    for step in range(300):
        i = step % len(tilts)
        loss = (fog.apply(torch.zeros(H, W, 3), sky, i, RenderSettings())[..., 0] - targets[i]).abs().mean()
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
    with torch.no_grad():
        errors = [
            (fog.apply(torch.zeros(H, W, 3), sky, i, RenderSettings())[..., 0] - t).abs().mean()
            for i, t in enumerate(targets)
        ]
    assert float(torch.stack(errors).mean()) < 0.4 * one_error  # degree 2 rounds the kink at the horizon (0.31)
    low, high = fog.summary()["airlight_range"]
    assert high[0] - low[0] > 0.05  # the spread is reported
    fixed = FogAnalytic(FogAnalyticConfig(learnable=False, airlight_degree=2), theta, scene)
    assert (
        not fixed.learn_directions()
        and not FogAnalytic(FogAnalyticConfig(airlight_degree=0), theta, scene).learn_directions()
    )


def test_old_checkpoints_load_as_a_uniform_medium_and_layers_stay_off_when_asked():
    theta = theta_from_values(0.0, visibility_m=300.0, fog_kind="fog", camera=spec())
    fog = FogAnalytic(FogAnalyticConfig(), theta, weather_scene())
    old = {k: v for k, v in fog.state_dict().items() if k not in ("height_rate", "airlight_sh")}  # saved before both
    fog.learn_layers()
    with torch.no_grad():
        fog.height_rate.fill_(3.0)
    fog.load_state_dict(old)
    assert not fog.height_rate.detach() and "scale_height_m" in fog.summary()  # still learning: reported
    fresh = FogAnalytic(FogAnalyticConfig(), theta, weather_scene())
    fresh.load_state_dict(old)
    assert not fresh.layered and fresh.summary().keys() == {"beta_per_m", "record_beta_per_m", "airlight"}
    assert not fresh.directional  # one airlight for every direction
    fixed = FogAnalytic(FogAnalyticConfig(layered=False), theta, weather_scene())
    assert not fixed.learn_layers() and not fixed.height_rate.requires_grad


def test_distance_spread_is_the_median_far_over_near_ratio_of_points_seen_twice():
    from metegs.cameras import Cameras
    from metegs.weather.medium import distance_spread

    def cams(z_positions):  # OpenCV cameras on the z axis looking down +z
        c2w = torch.eye(4).repeat(len(z_positions), 1, 1)
        c2w[:, 2, 3] = torch.tensor(z_positions)
        return Cameras.create(c2w, 50.0, 50.0, 32.0, 24.0, 64, 48)

    points = torch.tensor([[0.0, 0.0, 4.0], [0.0, 0.0, 6.0], [0.0, 0.0, 10.0]])
    # views at z = 0 and z = 2: distances 4/2, 6/4, 10/8 -> ratios 2, 1.5, 1.25
    assert distance_spread(cams([0.0, 2.0]), points) == pytest.approx(1.5, rel=1e-5)
    assert distance_spread(cams([0.0, 0.0]), points) == pytest.approx(1.0)  # every view at one distance
    assert distance_spread(cams([0.0]), points) is None  # no point seen twice
    assert distance_spread(cams([0.0, 2.0]), None) is None
    seen = cams([0.0, 5.0]).sees(points)  # the second view has the first point behind it
    assert seen.tolist() == [[True, True, True], [False, True, True]]


def test_the_airlight_is_put_where_it_is_asked_and_learns_as_it_did():
    """`FogAnalytic.set_airlight` puts the airlight at the one given, clamped into (0, 1), and leaves whether it
    learns as it was."""
    theta = theta_from_values(0.0, visibility_m=300.0, fog_kind="fog", camera=spec())
    fog = FogAnalytic(FogAnalyticConfig(airlight=(0.9, 0.9, 0.9)), theta, weather_scene())
    fog.airlight_logit.requires_grad_(False)
    fog.set_airlight(torch.tensor([0.72, 0.70, 1.0]))
    assert torch.allclose(fog.airlight, torch.tensor([0.72, 0.70, 0.999]), atol=1e-5)
    assert not fog.airlight_logit.requires_grad
