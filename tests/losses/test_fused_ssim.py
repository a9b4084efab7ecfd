"""The compiled SSIM map of the training loss against the torch reference (`ssim_map`) and finite differences."""

import pytest
import torch

from metegs.eval.metrics import ssim_map
from metegs.losses import fused_ssim
from metegs.losses.fused_ssim import FusedSSIMMap, fused_ssim_available, training_ssim_map
from metegs.losses.photometric import PhotometricLoss
from metegs.render import cpu_backend
from metegs.render.cpu_backend import CpuExtensionError
from metegs.testing import autograd_graph_holds

try:
    cpu_backend.load_extension()
except CpuExtensionError as exc:  # no compiler / ninja on this machine
    pytest.skip(f"the cpu extension cannot be built here: {exc}", allow_module_level=True)


def images(shape, dtype=torch.float32, seed=0):
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(shape, dtype=dtype, generator=g)
    # a target that resembles the render (SSIM near 1 in places, as in training) plus pure noise elsewhere
    y = (x + 0.1 * torch.randn(shape, dtype=dtype, generator=g)).clamp(0, 1)
    y[..., : shape[-3] // 3, :, :] = torch.rand(y[..., : shape[-3] // 3, :, :].shape, dtype=dtype, generator=g)
    return x, y


def made_by_the_kernel(t: torch.Tensor) -> bool:
    """Whether ``t``'s autograd graph holds `FusedSSIMMap`."""
    return autograd_graph_holds(t, FusedSSIMMap)


@pytest.mark.parametrize("shape", [(37, 53, 3), (2, 24, 31, 3), (5, 7, 3), (40, 60, 1)])
def test_map_and_gradient_match_the_reference(shape):
    x, y = images(shape)
    upstream = torch.randn(shape, generator=torch.Generator().manual_seed(1))
    xr = x.clone().requires_grad_(True)
    ref = ssim_map(xr, y, crop_border=False)
    (g_ref,) = torch.autograd.grad((ref * upstream).sum(), xr)
    xf = x.clone().requires_grad_(True)
    assert fused_ssim_available(xf, y)
    out = training_ssim_map(xf, y)
    assert made_by_the_kernel(out)
    (g_out,) = torch.autograd.grad((out * upstream).sum(), xf)
    assert out.shape == ref.shape
    torch.testing.assert_close(out, ref, rtol=0, atol=1e-5)
    torch.testing.assert_close(g_out, g_ref, rtol=1e-4, atol=1e-5)


def test_gradient_against_finite_differences():
    x, y = images((9, 13, 3), torch.float64, seed=3)
    window = fused_ssim.gaussian_kernel1d(11, 1.5, dtype=torch.float64)
    assert torch.autograd.gradcheck(
        lambda a: FusedSSIMMap.apply(a, y[None], window, 1e-4, 9e-4),
        (x[None].requires_grad_(True),),
        eps=1e-6,
        atol=1e-6,
    )


def test_loss_values_unchanged_with_and_without_weights():
    x, y = images((30, 44, 3), seed=5)
    w = (torch.rand(30, 44, generator=torch.Generator().manual_seed(2)) > 0.3).float()
    loss = PhotometricLoss()
    lam = loss.config.ssim_lambda
    for weights in (None, w):
        ref_map = ssim_map(x, y, crop_border=False)
        diff = (x - y).abs()
        if weights is None:
            expected = (1 - lam) * diff.mean() + lam * (1 - ref_map.mean())
        else:
            denom = weights.sum() * 3
            expected = (1 - lam) * (diff * weights[..., None]).sum() / denom + lam * (
                1 - (ref_map * weights[..., None]).sum() / denom
            )
        torch.testing.assert_close(loss(x, y, weights), expected, rtol=0, atol=1e-6)


def test_a_target_with_a_gradient_takes_the_reference_path():
    x, y = images((20, 20, 3), seed=7)
    y.requires_grad_(True)
    assert not fused_ssim_available(x, y)
    training_ssim_map(x, y).sum().backward()
    assert y.grad is not None and y.grad.abs().sum() > 0


def test_without_the_extension_the_reference_runs(monkeypatch):
    x, y = images((20, 20, 3), seed=8)
    monkeypatch.setattr(cpu_backend.EXTENSION, "available", lambda: False)
    x.requires_grad_(True)
    out = training_ssim_map(x, y)
    assert out.grad_fn is not None and not made_by_the_kernel(out)
    torch.testing.assert_close(out, ssim_map(x, y, crop_border=False))


def test_bad_shapes_are_refused_by_the_kernel():
    ext = cpu_backend.load_extension()
    window = fused_ssim.gaussian_kernel1d()
    with pytest.raises(RuntimeError, match="shapes differ"):
        ext.ssim_forward(torch.rand(1, 8, 8, 3), torch.rand(1, 8, 9, 3), window, 1e-4, 9e-4)
    with pytest.raises(RuntimeError, match="odd length"):
        ext.ssim_forward(torch.rand(1, 8, 8, 3), torch.rand(1, 8, 8, 3), window[:10], 1e-4, 9e-4)
