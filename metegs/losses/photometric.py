"""Photometric loss of 3DGS: (1 - λ)·L1 + λ·(1 - SSIM), the SSIM map compiled on CPU (`fused_ssim`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated

import torch

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

    def __call__(self, pred: torch.Tensor, target: torch.Tensor, weights: torch.Tensor | None = None) -> torch.Tensor:
        """Scalar loss of ``pred`` against ``target`` (both [H, W, 3]); ``weights`` [H, W] (e.g. an inlier mask)
        restricts both terms to the pixels it weighs, as a weighted mean."""
        lam = self.config.ssim_lambda
        w = None if weights is None else weights[..., None]
        denom = None if w is None else w.sum().clamp_min(1.0)
        diff = (pred - target).abs()
        l1 = diff.mean() if w is None else (diff * w).sum() / (denom * pred.shape[-1])
        if lam == 0:
            return l1
        sim = training_ssim_map(pred, target)
        s = sim.mean() if w is None else (sim * w).sum() / (denom * pred.shape[-1])
        return (1.0 - lam) * l1 + lam * (1.0 - s)
