"""Photometric loss of 3DGS: (1 - λ)·L1 + λ·(1 - SSIM)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated

import torch

from metegs.config import InstantiateConfig
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

    def __call__(self, pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        from metegs.eval.metrics import ssim

        lam = self.config.ssim_lambda
        l1 = (pred - target).abs().mean()
        if lam == 0:
            return l1
        return (1.0 - lam) * l1 + lam * (1.0 - ssim(pred, target, crop_border=False))
