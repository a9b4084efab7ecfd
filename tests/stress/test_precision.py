"""float32 against float64 gradients.

The reference is the `torch` backend in float64. Every usable backend in float32 must agree with it, per
parameter group, within a relative L2 error of ``GRAD_RTOL`` = 1e-4 (measured: 2e-7 to 5e-6 on these
scenes), and the float32 image within ``IMAGE_ATOL`` = 1e-5 (measured: ~5e-7). The loss is the training
loss (0.8·L1 + 0.2·(1 − SSIM)) plus small alpha and depth terms, on a sparse scene (60 Gaussians) and a dense,
nearly opaque one (400 Gaussians, opacity up to 0.99, about 28 layers per tile: early termination and
the alpha clamp are exercised).
"""

import pytest
import torch

from metegs.gaussians.model import GaussianSet
from metegs.losses.photometric import PhotometricLossConfig
from metegs.registry import registry
from metegs.render import RenderSettings
from metegs.render.select import backend_usable
from metegs.testing import camera, random_scene

GRAD_RTOL = 1e-4
IMAGE_ATOL = 1e-5
NAMES = ("means", "quats", "scales", "opacities", "sh")


def _grads(backend: str, dtype, seed: int, dense: bool):
    g = random_scene(400 if dense else 60, seed=seed, dtype=torch.float64, max_opacity=0.99 if dense else 0.9)
    scales = g.scales * (2.0 if dense else 1.0)
    params = [t.to(dtype).clone().requires_grad_(True) for t in (g.means, g.quats, scales, g.opacities, g.sh)]
    target = torch.rand(30, 40, 3, generator=torch.Generator().manual_seed(seed), dtype=torch.float64).to(dtype)
    out = (
        registry("rasterizer")
        .get(backend)()
        .render(GaussianSet(*params), camera(), RenderSettings(background=(0.1, 0.2, 0.3)))
    )
    loss_fn = PhotometricLossConfig().setup()
    loss = loss_fn(out.rgb, target) + 0.1 * out.alpha.mean() + 0.01 * out.depth.mean()
    loss.backward()
    return [p.grad.double() for p in params], out.rgb.detach().double()


def backends():
    return [
        pytest.param(n, id=n, marks=[] if backend_usable(n, "cpu") else [pytest.mark.skip(reason=f"{n} unavailable")])
        for n in registry("rasterizer").names()
    ]


@pytest.mark.parametrize("backend", backends())
@pytest.mark.parametrize("dense,seed", [(False, 0), (False, 1), (True, 0)], ids=["sparse-0", "sparse-1", "dense-0"])
def test_float32_gradients_agree_with_float64(backend, dense, seed):
    ref, ref_img = _grads("torch", torch.float64, seed, dense)
    got, img = _grads(backend, torch.float32, seed, dense)
    assert (img - ref_img).abs().max() <= IMAGE_ATOL
    for name, a, b in zip(NAMES, got, ref):
        assert torch.isfinite(a).all()
        rel = float((a - b).norm() / b.norm().clamp_min(1e-30))
        assert rel <= GRAD_RTOL, f"{backend} {name}: relative L2 error {rel:.2e} > {GRAD_RTOL:.0e}"
