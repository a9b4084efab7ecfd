"""GaussianModel initialisation / activation and the real SH basis in eval_sh."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from metegs.gaussians.model import GaussianModel
from metegs.gaussians.sh import SH_C1, eval_sh, num_sh_bases, rgb_to_sh, sh_to_rgb


def brute_knn_mean(points: np.ndarray, k: int = 3) -> np.ndarray:
    d = np.sqrt(((points[:, None, :] - points[None, :, :]) ** 2).sum(-1))
    return np.sort(d, axis=1)[:, 1 : k + 1].mean(axis=1)


def test_from_points_grid():
    h = 0.25
    axis = np.arange(4) * h
    pts = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3) + np.array([1.0, -2.0, 3.0])
    rng = np.random.default_rng(0)
    cols = rng.uniform(0, 1, (len(pts), 3))
    model = GaussianModel.from_points(pts, cols, sh_degree=2, init_opacity=0.3)
    n = len(pts)
    p = model.params
    assert len(model) == n and model.max_sh_degree == 2
    # every grid point has a neighbour at distance h along each axis -> mean 3-NN distance is h
    torch.testing.assert_close(p["scales"], torch.full((n, 3), math.log(h)), rtol=0, atol=1e-5)
    torch.testing.assert_close(torch.sigmoid(p["opacities"]), torch.full((n,), 0.3), rtol=0, atol=1e-5)
    torch.testing.assert_close(p["means"], torch.as_tensor(pts, dtype=torch.float32))
    torch.testing.assert_close(sh_to_rgb(p["sh0"][:, 0]), torch.as_tensor(cols, dtype=torch.float32))
    assert torch.equal(p["quats"], torch.tensor([1.0, 0, 0, 0]).repeat(n, 1))
    assert p["shN"].shape == (n, 8, 3) and not p["shN"].any()


def test_from_points_random_cloud_matches_brute_force():
    rng = np.random.default_rng(3)
    pts = rng.normal(size=(200, 3)) * np.array([1.0, 2.0, 0.5])
    model = GaussianModel.from_points(pts, None, sh_degree=0, scale_multiplier=2.0)
    expected = np.log(2.0 * brute_knn_mean(pts.astype(np.float32)))
    np.testing.assert_allclose(model.params["scales"].detach().numpy(), np.repeat(expected[:, None], 3, 1), atol=1e-4)
    # no colours -> grey
    torch.testing.assert_close(model.params["sh0"], rgb_to_sh(torch.full((200, 1, 3), 0.5)))
    assert model.params["shN"].shape == (200, 0, 3)


def test_activated_shapes_and_values():
    model = GaussianModel.random_in_box(np.zeros(3), np.ones(3), 50, sh_degree=3, seed=1)
    s = model.activated()
    assert len(s) == 50
    assert s.means.shape == (50, 3) and s.quats.shape == (50, 4) and s.scales.shape == (50, 3)
    assert s.opacities.shape == (50,) and s.sh.shape == (50, 1, 3)
    torch.testing.assert_close(s.scales, torch.exp(model.params["scales"]))
    torch.testing.assert_close(s.opacities, torch.sigmoid(model.params["opacities"]))
    for degree in range(4):
        model.active_sh_degree = degree
        assert model.activated().sh.shape == (50, num_sh_bases(degree), 3)
    # gradients flow back to the parameters
    model.activated().scales.sum().backward()
    assert model.params["scales"].grad is not None


# --- spherical harmonics -----------------------------------------------------------------------------


def fibonacci_sphere(m: int) -> torch.Tensor:
    """[m, 3] near-uniform unit directions (equal-area weights 4*pi/m)."""
    i = torch.arange(m, dtype=torch.float64) + 0.5
    z = 1 - 2 * i / m
    phi = math.pi * (1 + 5**0.5) * i
    r = torch.sqrt(1 - z * z)
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], -1)


def sh_basis(dirs: torch.Tensor, degree: int = 3) -> torch.Tensor:
    """[M, K] basis values, obtained from eval_sh with one-hot coefficients (channel 0)."""
    k = num_sh_bases(degree)
    out = []
    for i in range(k):
        coeffs = torch.zeros(dirs.shape[0], k, 3, dtype=dirs.dtype)
        coeffs[:, i, 0] = 1.0
        val = eval_sh(degree, coeffs, dirs) - 0.5
        assert torch.all(val[:, 1:] == 0)  # other channels are untouched
        out.append(val[:, 0])
    return torch.stack(out, 1)


def test_sh_basis_orthonormal_on_sphere():
    m = 40000
    dirs = fibonacci_sphere(m)
    b = sh_basis(dirs)  # [M, 16]
    gram = (b.T @ b) * (4 * math.pi / m)
    torch.testing.assert_close(gram, torch.eye(16, dtype=gram.dtype), rtol=0, atol=1e-2)


def test_sh_addition_theorem_per_band():
    # sum_m Y_lm(d)^2 = (2l+1) / (4 pi) at every direction
    g = torch.Generator().manual_seed(0)
    dirs = torch.nn.functional.normalize(torch.randn(500, 3, generator=g, dtype=torch.float64), dim=-1)
    b = sh_basis(dirs)
    for band in range(4):
        lo, hi = band**2, (band + 1) ** 2
        torch.testing.assert_close(
            (b[:, lo:hi] ** 2).sum(1), torch.full((500,), (2 * band + 1) / (4 * math.pi), dtype=torch.float64)
        )


def test_sh_degree1_explicit_and_truncation():
    dirs = torch.nn.functional.normalize(torch.randn(64, 3, generator=torch.Generator().manual_seed(1)), dim=-1)
    b = sh_basis(dirs, degree=1)
    x, y, z = dirs.unbind(-1)
    torch.testing.assert_close(b[:, 0], torch.full((64,), 0.28209479177387814))
    torch.testing.assert_close(b[:, 1], -SH_C1 * y)
    torch.testing.assert_close(b[:, 2], SH_C1 * z)
    torch.testing.assert_close(b[:, 3], -SH_C1 * x)
    # a lower degree ignores the higher coefficients
    coeffs = torch.randn(64, 16, 3)
    for degree in range(4):
        k = num_sh_bases(degree)
        padded = coeffs.clone()
        padded[:, k:] = 0
        torch.testing.assert_close(eval_sh(degree, coeffs, dirs), eval_sh(3, padded, dirs))


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_sh_linear_in_coefficients(degree):
    g = torch.Generator().manual_seed(degree)
    k = num_sh_bases(degree)
    dirs = torch.nn.functional.normalize(torch.randn(32, 3, generator=g), dim=-1)
    a, c = torch.randn(32, k, 3, generator=g), torch.randn(32, k, 3, generator=g)
    lhs = eval_sh(degree, 2 * a + c, dirs) - 0.5
    rhs = 2 * (eval_sh(degree, a, dirs) - 0.5) + (eval_sh(degree, c, dirs) - 0.5)
    torch.testing.assert_close(lhs, rhs, rtol=1e-5, atol=1e-5)
