"""`fog-gaussians`: the lattice's rules, its projection correction, several views, and agreement with `fog-analytic`."""

import math

import pytest
import torch

from metegs.cameras import Cameras, rotation_to_quat_wxyz
from metegs.data.config import DatasetConfig, SyntheticSceneConfig
from metegs.data.parsers.base import parse_scene
from metegs.gaussians.model import GaussianSet
from metegs.gaussians.sh import rgb_to_sh
from metegs.meteo import CameraSpec, theta_from_values
from metegs.meteo.physics import dilogarithm
from metegs.render.base import ALPHA_MIN
from metegs.render.torch_backend import TorchRasterizer
from metegs.weather import WeatherScene, render_with_weather
from metegs.weather.fog_analytic import FogAnalytic, FogAnalyticConfig
from metegs.weather.fog_gaussians import (
    FogGaussians,
    FogGaussiansConfig,
    LatticeViews,
    dilogarithm_tensor,
    nearest_camera,
    truncated_lattice_opacity,
    truncated_opacity,
    truncated_spread,
    uniform_spread_excess,
)

W, H, F = 64, 48, 60.0


@pytest.fixture(autouse=True)
def _one_thread():
    """One torch thread: OpenMP threads that busy-wait for a core taken by another process slow these renders
    down many times over on a loaded 2-core machine."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def fog_theta(visibility_m: float = 300.0):
    return theta_from_values(0.0, visibility_m=visibility_m, fog_kind="fog", camera=CameraSpec.from_intrinsics(F, W, H))


def side_by_side(n: int, spacing_m: float) -> Cameras:
    """n cameras along x (every other one raised by half a spacing), all looking down +z (OpenCV)."""
    c2w = torch.eye(4).repeat(n, 1, 1)
    c2w[:, 0, 3] = torch.arange(n) * spacing_m
    c2w[:, 1, 3] = (torch.arange(n) % 2) * spacing_m * 0.5
    return Cameras.create(c2w, F, F, W / 2, H / 2, W, H)


def black_wall(depth: float, cx: float, cy: float, n_side: int = 50) -> GaussianSet:
    """An opaque black plane at z = depth centred on (cx, cy), filling a view from there."""
    half = depth * (W / 2) / F * 1.3
    xs = torch.linspace(-half, half, n_side)
    grid = torch.stack(torch.meshgrid(xs, xs, indexing="ij"), -1).reshape(-1, 2) + torch.tensor([cx, cy])
    n, s = len(grid), 2 * half / n_side
    return GaussianSet(
        torch.cat([grid, torch.full((n, 1), depth)], 1),
        torch.tensor([[1.0, 0, 0, 0]]).expand(n, 4),
        torch.tensor([s, s, s * 0.01]).expand(n, 3),
        torch.full((n,), 0.99),
        rgb_to_sh(torch.zeros(3)).expand(n, 1, 3),
    )


def ray_lengths() -> torch.Tensor:
    xs = (torch.arange(W) + 0.5 - W / 2) / F
    ys = (torch.arange(H) + 0.5 - H / 2) / F
    return torch.sqrt(xs[None, :] ** 2 + ys[:, None] ** 2 + 1.0)


def test_dilogarithm_and_the_truncated_opacity_rule_invert_each_other():
    x = torch.tensor([0.0, 1e-3, 0.2, 0.5, 0.51, 0.8, 0.99])
    assert torch.allclose(dilogarithm_tensor(x), torch.tensor([dilogarithm(float(v)) for v in x], dtype=torch.float64))
    load = torch.tensor([1e-5, 1e-3, 0.02, 0.3, 1.2], dtype=torch.float64)
    o = truncated_opacity(load)
    assert torch.allclose(dilogarithm_tensor(o) - dilogarithm(ALPHA_MIN), load, rtol=1e-9, atol=1e-15)
    assert float(truncated_opacity(torch.tensor([5.0]))[0]) == pytest.approx(0.99)  # beyond reach: clamped
    # the lattice rule: (2πσ²/h³)(Li₂(o) − Li₂(α_min)) = β
    o1 = truncated_lattice_opacity(0.01, 2.0, 1.5)
    assert 2 * math.pi * 1.5**2 / 2.0**3 * (dilogarithm(o1) - dilogarithm(ALPHA_MIN)) == pytest.approx(0.01)
    # the truncated footprint is narrower than a Gaussian's, the more so the nearer o is to the cutoff
    kappa = truncated_spread(torch.tensor([0.005, 0.02, 0.2, 0.9]))
    assert float(kappa[0]) < float(kappa[1]) < float(kappa[2]) and bool(((kappa > 0) & (kappa < 1)).all())


def test_projection_excess_matches_its_closed_form_on_the_axis():
    """One camera, a Gaussian on the optical axis with σ = ρ/k: the rasteriser over-renders the medium there by
    (1 + ε/σ_px²)·(1 + ½·κ·12/k²) (dilation ε; A/m = 8 at the centre, +4 from the growth of σ with distance)."""
    assert float(uniform_spread_excess(torch.tensor(0.0, dtype=torch.float64))) == pytest.approx(8.0)
    cams = side_by_side(1, 0.0)
    views = LatticeViews.from_cameras(cams, torch.zeros(3, dtype=torch.float64), 1.0)
    k, rho = 10.0, 80.0
    d, s = views.projection_excess(
        torch.tensor([[0.0, 0.0, rho]], dtype=torch.float64), torch.tensor([rho / k]), k, 0.5, 0.3
    )
    sigma_px2 = (F / k) ** 2
    assert float(d[0]) == pytest.approx(1 + 0.3 / sigma_px2, rel=1e-6)
    assert float(s[0]) == pytest.approx(float(d[0]) * 0.5 * 12 / k**2, rel=1e-3)


def test_lattice_keeps_every_gaussian_small_next_to_its_distance_and_visible():
    theta = fog_theta()
    cams = side_by_side(3, 8.0)
    fog = FogGaussians(FogGaussiansConfig(), theta, WeatherScene(cams, torch.tensor([0.0, -1.0, 0.0]), 2.0, None))
    lat, c = fog.lattice, fog.config
    centres_m = (cams.centers.double() - cams.centers.double().mean(0)) * 2.0
    rho, _ = nearest_camera(lat.centres_m, centres_m)
    assert torch.allclose(lat.sigma_m, rho / c.distance_sigmas)  # accuracy: σ = ρ/k
    assert float(rho.min()) >= c.near_optical_depth / fog.beta_per_m - 1e-9
    assert float(rho.max()) <= c.optical_depth_limit / fog.beta_per_m + 1e-9
    assert float(lat.opacity.min()) > 1.5 * ALPHA_MIN and float(lat.opacity.max()) <= 0.6
    g = fog.gaussians_for(0)
    assert len(g) == len(lat.opacity) <= c.max_gaussians
    assert torch.allclose(g.scales[:, 0].double(), lat.sigma_m / 2.0, rtol=1e-6)  # scene units: 2 m each


def test_max_gaussians_coarsens_the_lattice():
    theta = fog_theta()
    scene = WeatherScene(side_by_side(1, 0.0), torch.tensor([0.0, -1.0, 0.0]), 1.0, None)
    fog = FogGaussians(FogGaussiansConfig(max_gaussians=4000), theta, scene)
    assert len(fog.gaussians_for(0)) <= 4000 and fog.distance_sigmas < FogGaussiansConfig().distance_sigmas


@pytest.mark.parametrize("view", [0, 2, 4])
def test_fog_gaussians_transmittance_in_several_views(view):
    """Five cameras 10 m apart share one medium; each sees e^{−βd} within 1 % (β·d = 0.6, 60 m at 300 m visibility)."""
    cams = side_by_side(5, 10.0)
    fog = FogGaussians(
        FogGaussiansConfig(airlight=(1.0, 1.0, 1.0)),
        fog_theta(),
        WeatherScene(cams, torch.tensor([0.0, -1.0, 0.0]), 1.0, None, seed=1),
    )
    depth = 0.6 / fog.beta_per_m
    c = cams.camera_to_worlds[view, :3, 3]
    r = render_with_weather(TorchRasterizer(), black_wall(depth, float(c[0]), float(c[1])), [fog], view, cams[view])
    measured = float((1.0 - r.rgb.mean(-1)).mean())
    expected = float(torch.exp(-fog.beta_per_m * depth * ray_lengths()).mean())
    assert measured == pytest.approx(expected, rel=0.01)


def depth_splats(camera: Cameras, depth, image) -> GaussianSet:
    """The view's exact depth as a wall of opaque camera-facing splats, one per pixel, coloured by the image."""
    h, w = depth.shape
    ys, xs = torch.meshgrid(torch.arange(h) + 0.5, torch.arange(w) + 0.5, indexing="ij")
    z = torch.as_tensor(depth).float()
    rays = torch.stack(
        [(xs - camera.cx[0]) / camera.fx[0], (ys - camera.cy[0]) / camera.fy[0], torch.ones_like(xs)], -1
    )
    c2w = camera.camera_to_worlds[0]
    means = (rays * z[..., None]).reshape(-1, 3) @ c2w[:3, :3].T + c2w[:3, 3]
    n, zz = len(means), z.reshape(-1)
    quat = rotation_to_quat_wxyz(c2w[:3, :3]).reshape(1, 4).expand(n, 4)
    scales = torch.stack([0.6 * zz / camera.fx[0], 0.6 * zz / camera.fy[0], 1e-4 * zz], -1)
    colours = rgb_to_sh(torch.as_tensor(image).reshape(-1, 3))[:, None, :]
    return GaussianSet(means, quat, scales, torch.full((n,), 0.99), colours)


def test_fog_gaussians_agree_with_fog_analytic_on_the_synthetic_scene():
    """Both fog models on the synthetic scene (10 m per unit, 220–290 m deep) at 300 m visibility: the scene is
    each view's exact depth as opaque splats; fog-gaussians rasterises the medium with them, fog-analytic
    applies C·t + A(1 − α·t) to their render. Mean abs difference ≤ 0.02 (measured ~0.004; the fog itself
    changes the images by ~0.2)."""
    data = parse_scene(None, None, DatasetConfig(synthetic=SyntheticSceneConfig(width=64, height=48, num_views=4)))
    theta = theta_from_values(0.0, visibility_m=300.0, fog_kind="fog")
    scene = WeatherScene(data.cameras, torch.as_tensor(data.up), float(data.metric_scale), None, seed=0)
    airlight = (0.8, 0.8, 0.82)
    gaussian_fog = FogGaussians(FogGaussiansConfig(airlight=airlight), theta, scene)
    analytic_fog = FogAnalytic(FogAnalyticConfig(airlight=airlight, learnable=False), theta, scene)
    rast = TorchRasterizer()
    diffs, effects = [], []
    with torch.no_grad():
        for v in range(len(data.cameras)):
            camera = data.cameras[v]
            splats = depth_splats(camera, data.depths[v], data.images[v])
            clean = rast.render(splats, camera).rgb
            a = render_with_weather(rast, splats, [analytic_fog], v, camera).rgb
            g = render_with_weather(rast, splats, [gaussian_fog], v, camera).rgb
            diffs.append(float((a - g).abs().mean()))
            effects.append(float((a - clean).abs().mean()))
    assert min(effects) > 0.1  # the fog is plainly there
    assert sum(diffs) / len(diffs) <= 0.02, diffs
