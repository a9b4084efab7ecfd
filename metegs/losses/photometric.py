"""Photometric loss of 3DGS: (1 - λ)·L1 + λ·(1 - SSIM), the SSIM map compiled on CPU (`fused_ssim`).

The L1 term can fit a quantile of a pixel's photos rather than their median (`pinball_l1`): where the photos are
only ever brightened (rain), the scene lies under most of them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated

import torch
import torch.nn.functional as F

from metegs.config import InstantiateConfig
from metegs.losses.fused_ssim import training_ssim_map
from metegs.validate import FRACTION


@dataclass
class PhotometricLossConfig(InstantiateConfig):
    """(1 - λ)·L1 + λ·(1 - SSIM) between a render and its photo."""

    _target: type = field(default_factory=lambda: PhotometricLoss, repr=False)
    ssim_lambda: Annotated[float, FRACTION] = 0.2
    """Weight λ of the D-SSIM term."""


class PhotometricLoss:
    """Callable loss; images are [H, W, 3] channels-last in [0, 1]."""

    def __init__(self, config: PhotometricLossConfig | None = None):
        self.config = config or PhotometricLossConfig()

    def __call__(
        self,
        pred: torch.Tensor,
        target: torch.Tensor,
        weights: torch.Tensor | None = None,
        quantile: float = 0.5,
        ssim_lambda: float | None = None,
        ssim_images: tuple[torch.Tensor, torch.Tensor] | None = None,
    ) -> torch.Tensor:
        """Scalar loss of ``pred`` against ``target`` (both [H, W, 3]); ``weights`` [H, W] (e.g. an inlier mask)
        restricts both terms to the pixels it weighs, as a weighted mean; ``quantile`` below 0.5 makes the L1 term
        `pinball_l1` (0.5: plain L1); ``ssim_lambda`` replaces the configured weight of the D-SSIM term and
        ``ssim_images`` (two [H, W, 3]) the pair it compares (default ``pred`` and ``target``)."""
        lam = self.config.ssim_lambda if ssim_lambda is None else ssim_lambda
        w = None if weights is None else weights[..., None]
        denom = None if w is None else w.sum().clamp_min(1.0)
        diff = pinball_l1(pred, target, quantile)
        l1 = diff.mean() if w is None else (diff * w).sum() / (denom * pred.shape[-1])
        if lam == 0:
            return l1
        sim = training_ssim_map(*((pred, target) if ssim_images is None else ssim_images))
        s = sim.mean() if w is None else (sim * w).sum() / (denom * pred.shape[-1])
        return (1.0 - lam) * l1 + lam * (1.0 - s)


def pinball_l1(pred: torch.Tensor, target: torch.Tensor, quantile: float = 0.5) -> torch.Tensor:
    """Per-element asymmetric L1 of ``pred`` against ``target`` (same shape): 2q·(target − pred) where the target is
    brighter, 2(1 − q)·(pred − target) where it is darker. Summed over samples of one target it is least at their
    ``quantile`` (q), so a Gaussian seen in many photos takes their q-quantile; q = 0.5 is |pred − target|."""
    if quantile == 0.5:
        return (pred - target).abs()
    residual = target - pred
    return 2.0 * torch.maximum(quantile * residual, (quantile - 1.0) * residual)


def box_detail(image: torch.Tensor, width: int) -> torch.Tensor:
    """[H, W, C] -> [H, W, C]: ``image`` minus its mean over the ``width`` × ``width`` box around each pixel (at the
    borders, the mean of the pixels inside the image): the detail a box filter takes away, without the tone. An
    even ``width`` is taken as the odd one above it; 0 returns ``image`` as it is."""
    if width <= 0:
        return image
    k = width | 1
    x = image.permute(2, 0, 1)[None]
    pool = torch.nn.functional.avg_pool2d
    # one row pass and one column pass: the clipped box's mean is the mean of the clipped row means (2k, not k²)
    rows = pool(x, (1, k), stride=1, padding=(0, k // 2), count_include_pad=False)
    mean = pool(rows, (k, 1), stride=1, padding=(k // 2, 0), count_include_pad=False)
    return (x - mean)[0].permute(1, 2, 0)


def open_bright(image: torch.Tensor, width: int) -> torch.Tensor:
    """[H, W, C] -> [H, W, C]: grey-scale opening of ``image`` (each channel) by a ``width`` × ``width`` square, the
    erosion's minimum then the dilation's maximum (windows clipped at the borders): bright structures narrower than
    the square in some direction (a rain streak) take the level of what is around them, wider ones and everything
    dark stay. An even ``width`` is taken as the odd one above it; 0 returns ``image`` as it is. The gradient goes
    to the pixel each output was picked from."""
    if width <= 0:
        return image
    k = width | 1
    x = image.permute(2, 0, 1)[None]
    eroded = -F.max_pool2d(-x, k, stride=1, padding=k // 2)
    return F.max_pool2d(eroded, k, stride=1, padding=k // 2)[0].permute(1, 2, 0)
