"""The torch rasteriser against a brute-force per-pixel compositor, finite differences, and degenerate input."""

import math

import pytest
import torch

from metegs.gaussians.model import GaussianSet
from metegs.render.base import ALPHA_MAX, ALPHA_MIN, T_MIN, RenderSettings
from metegs.render.pipeline import gaussian_colors
from metegs.render.projection import project_gaussians
from metegs.render.torch_backend import TorchRasterizer
from metegs.testing import camera, random_scene


def brute_force(g: GaussianSet, cam, bg, sh_degree):
    """Per pixel, every projected Gaussian in depth order; the plain 3DGS compositing rules."""
    W, H = int(cam.width[0]), int(cam.height[0])
    viewmat = cam.world_to_cameras()[0].to(g.means)
    K = cam.intrinsics()[0].to(g.means)
    proj = project_gaussians(g.means, g.quats, g.scales, viewmat, K, W, H, opacities=g.opacities)
    colors = gaussian_colors(g, cam.centers[0].to(g.means), sh_degree)
    order = [i for i in torch.argsort(proj.depths).tolist() if proj.radii[i] > 0]
    img = torch.zeros(H, W, 3, dtype=g.means.dtype)
    alpha_img = torch.zeros(H, W, dtype=g.means.dtype)
    for y in range(H):
        for x in range(W):
            T, c = 1.0, torch.zeros(3, dtype=g.means.dtype)
            for i in order:
                dx = x + 0.5 - proj.means2d[i, 0]
                dy = y + 0.5 - proj.means2d[i, 1]
                a, b, cc = proj.conics[i]
                power = -0.5 * (a * dx * dx + cc * dy * dy) - b * dx * dy
                alpha = min(ALPHA_MAX, float(g.opacities[i] * math.exp(min(float(power), 0.0))))
                if alpha < ALPHA_MIN:
                    continue
                if T * (1 - alpha) < T_MIN:
                    break
                c = c + alpha * T * colors[i]
                T = T * (1 - alpha)
            img[y, x] = c + T * bg
            alpha_img[y, x] = 1 - T
    return img, alpha_img


@pytest.mark.parametrize("chunk", [3, 32])
def test_matches_brute_force(chunk):
    g = random_scene(60, seed=1, dtype=torch.float64, sh_degree=2)
    cam = camera(37, 29)  # not a multiple of the tile size
    bg = torch.tensor([0.2, 0.4, 0.6], dtype=torch.float64)
    out = TorchRasterizer(chunk=chunk).render(g, cam, RenderSettings(background=bg, sh_degree=2))
    ref_rgb, ref_alpha = brute_force(g, cam, bg, 2)
    assert out.rgb.shape == (29, 37, 3)
    assert torch.allclose(out.rgb, ref_rgb, atol=1e-10)
    assert torch.allclose(out.alpha, ref_alpha, atol=1e-10)


@pytest.mark.parametrize("chunk", [1, 2, 32])
def test_stopped_pixels_stay_stopped_across_chunks(chunk):
    """Opaque Gaussians stop a pixel; fainter ones behind them (in later chunks) must not resume it."""
    n = 7
    means = torch.tensor([[0.0, 0.0, 2.0 + 0.1 * i] for i in range(n)], dtype=torch.float64)
    opac = torch.tensor([0.999, 0.999, 0.999, 0.3, 0.3, 0.3, 0.3], dtype=torch.float64)
    g = GaussianSet(
        means,
        torch.tensor([[1.0, 0, 0, 0]] * n, dtype=torch.float64),
        torch.full((n, 3), 0.4, dtype=torch.float64),
        opac,
        torch.rand(n, 1, 3, dtype=torch.float64),
    )
    cam = camera(16, 16)
    out = TorchRasterizer(chunk=chunk).render(g, cam)
    ref, ref_alpha = brute_force(g, cam, torch.zeros(3, dtype=torch.float64), 0)
    assert torch.allclose(out.rgb, ref, atol=1e-12)
    assert torch.allclose(out.alpha, ref_alpha, atol=1e-12)


def test_early_termination_with_opaque_stack():
    """Many nearly opaque Gaussians on one pixel: compositing stops once T would drop below 1e-4."""
    n = 12
    means = torch.tensor([[0.0, 0.0, 2.0 + 0.1 * i] for i in range(n)], dtype=torch.float64)
    g = GaussianSet(
        means,
        torch.tensor([[1.0, 0, 0, 0]] * n, dtype=torch.float64),
        torch.full((n, 3), 0.5, dtype=torch.float64),
        torch.full((n,), 0.999, dtype=torch.float64),
        torch.rand(n, 1, 3, dtype=torch.float64),
    )
    cam = camera(16, 16)
    out = TorchRasterizer().render(g, cam)
    ref, ref_alpha = brute_force(g, cam, torch.zeros(3, dtype=torch.float64), 0)
    assert torch.allclose(out.rgb, ref, atol=1e-10)
    # alpha clamps at 0.99, and compositing stops before T would fall below T_MIN: T ends in [T_MIN, 0.01].
    T_end = 1 - float(out.alpha[8, 8])
    assert T_MIN * (1 - 1e-9) <= T_end <= 0.01 + 1e-12


def test_gradients_match_finite_differences():
    g = random_scene(6, seed=3, dtype=torch.float64, sh_degree=1, max_opacity=0.7)
    cam = camera(24, 20, f=20.0)
    target = torch.rand(20, 24, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    rast = TorchRasterizer(chunk=4)

    def loss(means, quats, scales, opac, sh):
        out = rast.render(GaussianSet(means, quats, scales, opac, sh), cam, RenderSettings(sh_degree=1))
        return ((out.rgb - target) ** 2).sum() + out.depth.mean() * 0.01 + out.alpha.sum() * 0.1

    inputs = tuple(t.clone().requires_grad_(True) for t in (g.means, g.quats, g.scales, g.opacities, g.sh))
    assert torch.autograd.gradcheck(loss, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_expected_depth_of_a_single_opaque_layer():
    """A wall of overlapping Gaussians at z = 3 renders depth 3 wherever it is opaque."""
    xs, ys = torch.meshgrid(torch.linspace(-2, 2, 21), torch.linspace(-2, 2, 21), indexing="ij")
    n = xs.numel()
    means = torch.stack([xs.flatten(), ys.flatten(), torch.full((n,), 3.0)], 1)
    g = GaussianSet(
        means,
        torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
        torch.full((n, 3), 0.3),
        torch.full((n,), 0.9),
        torch.zeros(n, 1, 3),
    )
    out = TorchRasterizer().render(g, camera(32, 24, f=20.0))
    solid = out.alpha > 0.99
    assert solid.float().mean() > 0.9
    assert torch.allclose(out.depth[solid], torch.tensor(3.0), atol=1e-4)
