"""The training loss's SSIM map as one compiled op with its own backward (CPU), as fused-ssim is on CUDA.

Same values as `metegs.eval.metrics.ssim_map(pred, target, crop_border=False)` (zero-padded 'same' windows, the
3DGS reference loss) to float32 rounding, in two separable passes each way (``render/csrc/ssim.cpp``) instead of
about thirty torch ops and their autograd intermediates. The gradient flows to ``pred`` only: the photo is a
constant of the loss. Elsewhere (CUDA, a ``target`` that needs a gradient, no compiled extension) the torch
reference runs.
"""

from __future__ import annotations

import torch
from torch.autograd.function import once_differentiable

from metegs.eval.metrics import _K1, _K2, gaussian_kernel1d, ssim_map

WINDOW_SIZE, SIGMA = 11, 1.5
"""The training loss's Gaussian window (as `ssim_map`'s defaults)."""


class FusedSSIMMap(torch.autograd.Function):
    """SSIM map [B, H, W, C] of ``pred`` against ``target`` (both [B, H, W, C]); differentiable in ``pred``."""

    @staticmethod
    def forward(ctx, pred, target, window, c1, c2):
        from metegs.render.cpu_backend import load_extension

        ssim, partials = load_extension().ssim_forward(pred, target, window, c1, c2)
        ctx.save_for_backward(pred, target, window, partials)
        return ssim

    @staticmethod
    @once_differentiable
    def backward(ctx, g_map):
        from metegs.render.cpu_backend import load_extension

        pred, target, window, partials = ctx.saved_tensors
        return load_extension().ssim_backward(pred, target, window, partials, g_map), None, None, None, None


def fused_ssim_available(pred: torch.Tensor, target: torch.Tensor) -> bool:
    """Whether `training_ssim_map` runs the compiled op for these images: CPU floating-point tensors, ``target``
    without a gradient, and the ``cpu`` backend's extension loaded or buildable."""
    if pred.device.type != "cpu" or not pred.is_floating_point() or target.requires_grad:
        return False
    from metegs.render.cpu_backend import EXTENSION

    return EXTENSION.available()


def training_ssim_map(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """The training loss's SSIM map ``[..., H, W, C]`` of ``pred`` against ``target`` (``[..., H, W, C]``, same
    shape): the compiled op where `fused_ssim_available`, else `ssim_map(..., crop_border=False)`."""
    if pred.shape != target.shape or pred.ndim < 3 or not fused_ssim_available(pred, target):
        return ssim_map(pred, target, WINDOW_SIZE, SIGMA, crop_border=False)
    shape = pred.shape
    x = pred.reshape(-1, *shape[-3:])
    y = target.to(pred.dtype).reshape(-1, *shape[-3:]).contiguous()
    window = gaussian_kernel1d(WINDOW_SIZE, SIGMA, dtype=pred.dtype)
    return FusedSSIMMap.apply(x.contiguous(), y, window, _K1**2, _K2**2).reshape(shape)
