"""PSNR, SSIM and per-view evaluation of channels-last images in [0, 1].

Images are ``[H, W, 3]`` or batched ``[..., H, W, 3]`` (channels last, as rendered by metegs).

SSIM uses a separable Gaussian window (sigma 1.5, 11 taps by default), run as two 1D depthwise ``conv2d``
passes over the five stacked statistics ``x, y, x^2, y^2, xy``. Two border conventions:

- ``crop_border=True`` (default, the **metric**): only window positions fully inside the image are kept,
  which is what ``skimage.metrics.structural_similarity(..., gaussian_weights=True, sigma=1.5,
  use_sample_covariance=False, data_range=1.0)`` averages (it crops ``(win_size - 1) // 2`` pixels on each
  side, where its padding has no effect). Matches skimage to ~1e-6.
- ``crop_border=False`` (the **training loss** of the 3DGS reference, ``1 - ssim``): a 'same'-size map with
  zero padding, averaged over every pixel.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import torch
import torch.nn.functional as F

if TYPE_CHECKING:
    from metegs.eval.lpips import LPIPS

__all__ = ["evaluate_images", "gaussian_kernel1d", "psnr", "ssim", "ssim_map"]

_K1, _K2 = 0.01, 0.03


def psnr(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Peak signal-to-noise ratio (peak 1.0) in dB: ``-10 log10(MSE)``, the MSE over every element.

    Args:
        pred, target: ``[..., H, W, 3]`` in [0, 1], same shape.
        mask: optional weights broadcastable to ``pred`` (e.g. ``[..., H, W]`` bool/float, or
            ``[..., H, W, 1]``); the MSE is then ``sum(m * d^2) / sum(m)`` over the broadcast mask.

    Returns:
        scalar tensor (``inf`` for identical images).
    """
    if pred.shape != target.shape:
        raise ValueError(f"psnr: shapes differ, {tuple(pred.shape)} vs {tuple(target.shape)}")
    sq = (pred - target).pow(2)
    if mask is None:
        mse = sq.mean()
    else:
        m = mask.to(sq.dtype)
        if m.ndim == sq.ndim - 1:
            m = m.unsqueeze(-1)
        m = m.expand_as(sq)
        denom = m.sum()
        if denom <= 0:
            raise ValueError("psnr: mask selects no pixel")
        mse = (sq * m).sum() / denom
    return -10.0 * torch.log10(mse)


def gaussian_kernel1d(window_size: int = 11, sigma: float = 1.5, dtype=torch.float32, device=None) -> torch.Tensor:
    """Normalised 1D Gaussian ``[window_size]`` centred on the middle tap."""
    if window_size < 1 or window_size % 2 == 0:
        raise ValueError(f"window_size must be a positive odd integer, got {window_size}")
    x = torch.arange(window_size, dtype=torch.float64, device=device) - window_size // 2
    g = torch.exp(-(x**2) / (2.0 * sigma**2))
    return (g / g.sum()).to(dtype)


def _to_nchw(img: torch.Tensor, name: str) -> tuple[torch.Tensor, torch.Size]:
    """``[..., H, W, C]`` -> ``[B, C, H, W]`` and the leading batch shape."""
    if img.ndim < 3:
        raise ValueError(f"{name}: expected [..., H, W, C] (channels last), got shape {tuple(img.shape)}")
    batch = img.shape[:-3]
    h, w, c = img.shape[-3:]
    return img.reshape(-1, h, w, c).permute(0, 3, 1, 2), batch


def _separable_blur(x: torch.Tensor, g: torch.Tensor, crop_border: bool) -> torch.Tensor:
    """Depthwise Gaussian filter of ``x`` ``[B, C, H, W]`` with the 1D kernel ``g`` ``[K]``.

    'valid' convolution when ``crop_border`` (output ``[B, C, H-K+1, W-K+1]``), else zero-padded 'same'.
    """
    c, k = x.shape[1], g.numel()
    pad = 0 if crop_border else k // 2
    x = F.conv2d(x, g.view(1, 1, 1, k).expand(c, 1, 1, k), padding=(0, pad), groups=c)
    return F.conv2d(x, g.view(1, 1, k, 1).expand(c, 1, k, 1), padding=(pad, 0), groups=c)


def ssim_map(
    pred: torch.Tensor,
    target: torch.Tensor,
    window_size: int = 11,
    sigma: float = 1.5,
    crop_border: bool = True,
    data_range: float = 1.0,
) -> torch.Tensor:
    """Per-pixel, per-channel SSIM map (differentiable).

    Args:
        pred, target: ``[..., H, W, C]`` channels last, same shape.
        window_size: Gaussian taps (odd). skimage's default for sigma 1.5 (truncate 3.5) is 11.
        sigma: Gaussian standard deviation.
        crop_border: keep only windows fully inside the image (skimage parity); else zero-padded 'same' map
            (3DGS reference loss).
        data_range: dynamic range of the images (C1 = (0.01 R)^2, C2 = (0.03 R)^2).

    Returns:
        ``[..., H', W', C]`` with ``H' = H - window_size + 1`` when cropping, else ``H``.
    """
    if pred.shape != target.shape:
        raise ValueError(f"ssim: shapes differ, {tuple(pred.shape)} vs {tuple(target.shape)}")
    x, batch = _to_nchw(pred, "ssim pred")
    y, _ = _to_nchw(target, "ssim target")
    h, w = x.shape[-2:]
    if crop_border and min(h, w) < window_size:
        raise ValueError(f"ssim: image {h}x{w} is smaller than the {window_size}-tap window (crop_border=True)")
    if not x.is_floating_point():
        raise TypeError(f"ssim: expected floating-point images, got {x.dtype}")
    c = x.shape[1]
    g = gaussian_kernel1d(window_size, sigma, dtype=x.dtype, device=x.device)
    stats = _separable_blur(torch.cat([x, y, x * x, y * y, x * y], dim=1), g, crop_border)
    mu_x, mu_y, e_xx, e_yy, e_xy = stats.split(c, dim=1)
    var_x = e_xx - mu_x * mu_x
    var_y = e_yy - mu_y * mu_y
    cov = e_xy - mu_x * mu_y
    c1, c2 = (_K1 * data_range) ** 2, (_K2 * data_range) ** 2
    s = ((2 * mu_x * mu_y + c1) * (2 * cov + c2)) / ((mu_x * mu_x + mu_y * mu_y + c1) * (var_x + var_y + c2))
    s = s.permute(0, 2, 3, 1)
    return s.reshape(*batch, *s.shape[1:])


def ssim(
    pred: torch.Tensor,
    target: torch.Tensor,
    window_size: int = 11,
    sigma: float = 1.5,
    crop_border: bool = True,
    data_range: float = 1.0,
) -> torch.Tensor:
    """Mean SSIM (scalar tensor, differentiable) of ``[H, W, 3]`` or ``[B, H, W, 3]`` images.

    ``crop_border=True`` (default) reproduces ``skimage.metrics.structural_similarity(a, b, channel_axis=-1,
    data_range=1.0, gaussian_weights=True, sigma=1.5, use_sample_covariance=False)``; use
    ``crop_border=False`` for the 3DGS training loss ``1 - ssim(...)`` (zero-padded 'same' map, full mean).
    For a batch, the mean is over all images (equal to the mean of per-image SSIMs).
    """
    return ssim_map(pred, target, window_size, sigma, crop_border, data_range).mean()


def _as_views(images: torch.Tensor | Sequence[torch.Tensor], name: str) -> list[torch.Tensor]:
    if isinstance(images, torch.Tensor):
        if images.ndim == 3:
            return [images]
        if images.ndim == 4:
            return list(images.unbind(0))
        raise ValueError(f"{name}: expected [N, H, W, 3] or a sequence of [H, W, 3], got {tuple(images.shape)}")
    return list(images)


def evaluate_images(
    preds: torch.Tensor | Sequence[torch.Tensor],
    targets: torch.Tensor | Sequence[torch.Tensor],
    lpips_model: LPIPS | None = None,
    lpips_reason: str | None = None,
    clamp: bool = True,
) -> dict[str, Any]:
    """PSNR / SSIM / LPIPS per view, and their means over views.

    Args:
        preds, targets: ``[N, H, W, 3]`` or sequences of ``[H, W, 3]`` in [0, 1] (views may differ in size).
        lpips_model: a loaded `metegs.eval.lpips.LPIPS`; when ``None`` LPIPS is reported as ``None``.
        lpips_reason: why there is no LPIPS model (copied to the result when ``lpips_model`` is ``None``).
        clamp: clamp predictions to [0, 1] first (rendered colours may overshoot).

    Returns:
        ``{"psnr": float, "ssim": float, "lpips": float | None, "streak_energy": float, "contrast_ratio": float,
        "lpips_net": str | None, "lpips_reason": str | None, "num_views": int, "per_view": {"psnr": [float],
        "ssim": [float], "lpips": [float] | None, "streak_energy": [float], "contrast_ratio": [float]}}``
        (`metegs.eval.residual_weather`: rain and haze left in the prediction, against the target).
    """
    p_views, t_views = _as_views(preds, "preds"), _as_views(targets, "targets")
    if len(p_views) != len(t_views):
        raise ValueError(f"evaluate_images: {len(p_views)} predictions vs {len(t_views)} targets")
    if not p_views:
        raise ValueError("evaluate_images: no views")
    from metegs.eval.residual_weather import contrast_ratio, streak_energy

    per: dict[str, list[float] | None] = {
        "psnr": [],
        "ssim": [],
        "lpips": [] if lpips_model is not None else None,
        "streak_energy": [],
        "contrast_ratio": [],
    }
    with torch.no_grad():
        for i, (p, t) in enumerate(zip(p_views, t_views, strict=True)):
            if p.shape != t.shape:
                raise ValueError(f"evaluate_images: view {i} shapes differ, {tuple(p.shape)} vs {tuple(t.shape)}")
            p = p.float().clamp(0, 1) if clamp else p.float()
            t = t.float().to(p.device)
            per["psnr"].append(float(psnr(p, t)))
            per["ssim"].append(float(ssim(p, t)))
            per["streak_energy"].append(streak_energy(p, t))
            per["contrast_ratio"].append(contrast_ratio(p, t))
            if lpips_model is not None:
                model_device = next(lpips_model.parameters()).device
                per["lpips"].append(float(lpips_model(p.to(model_device), t.to(model_device))))

    def mean(values: list[float] | None) -> float | None:
        return None if values is None else math.fsum(values) / len(values)

    return {
        "psnr": mean(per["psnr"]),
        "ssim": mean(per["ssim"]),
        "lpips": mean(per["lpips"]),
        "streak_energy": mean(per["streak_energy"]),
        "contrast_ratio": mean(per["contrast_ratio"]),
        "lpips_net": None if lpips_model is None else lpips_model.net,
        "lpips_reason": None if lpips_model is not None else (lpips_reason or "no LPIPS model given"),
        "num_views": len(p_views),
        "per_view": per,
    }
