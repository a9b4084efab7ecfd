"""How much weather is left in a render that should be clean, against its clean reference.

- `streak_energy`: the orientation-selective ridge response of the luminance residual (render − reference) where
  the reference is smooth: thin structures sharing a direction (rain streaks) answer one of the oriented line
  filters much more than the others, while noise, a uniform veil and blur at the reference's edges answer
  little. 0 for a perfect render.
- `contrast_ratio`: the local RMS contrast of the render over that of the reference (7 × 7 windows): haze
  multiplies it by the transmittance (C = I·t + A·(1 − t) has t times the contrast of I), so values below 1 are
  contrast lost to a veil (or to blur); 1 for a perfect render.
"""

from __future__ import annotations

import math
from functools import lru_cache

import torch
import torch.nn.functional as F

from metegs.data.images import LUMA

ANGLES = 12
"""Orientations of the line filters (every 15°)."""
SMOOTH_LEVEL = 0.01
"""Line-filter response of the reference above which a pixel counts as near an edge (weight e^-1 there)."""


@lru_cache(maxsize=4)
def line_filters(sigma_across: float = 1.0, sigma_along: float = 3.0, size: int = 15) -> torch.Tensor:
    """[ANGLES, 1, size, size] zero-mean, unit-L1 second-derivative-across-the-line filters (thin bright or dark
    lines of about 2·``sigma_across`` px along each orientation)."""
    r = torch.arange(size, dtype=torch.float64) - size // 2
    y, x = torch.meshgrid(r, r, indexing="ij")
    kernels = []
    for k in range(ANGLES):
        a = math.pi * k / ANGLES
        u = x * math.cos(a) + y * math.sin(a)  # across the line
        v = -x * math.sin(a) + y * math.cos(a)  # along it
        g = (1 - u**2 / sigma_across**2) * torch.exp(-(u**2) / (2 * sigma_across**2) - v**2 / (2 * sigma_along**2))
        g = g - g.mean()
        kernels.append(g / g.abs().sum())
    return torch.stack(kernels)[:, None].float()


def line_responses(image: torch.Tensor) -> torch.Tensor:
    """[1, 1, H, W] -> [ANGLES, H, W]: the absolute response of each oriented line filter (`line_filters`, the image
    reflected at its borders), in ``image``'s dtype."""
    filters = line_filters().to(image.device, image.dtype)
    pad = [filters.shape[-1] // 2] * 4
    return F.conv2d(F.pad(image, pad, mode="reflect"), filters).abs()[0]


def _luma(image: torch.Tensor) -> torch.Tensor:
    """[H, W, 3] -> [1, 1, H, W] luminance."""
    return (image.float() * torch.tensor(LUMA, device=image.device)).sum(-1)[None, None]


def streak_energy(pred: torch.Tensor, ref: torch.Tensor) -> float:
    """Absolute line-filter response of the luminance residual of ``pred`` [H, W, 3] against ``ref`` [H, W, 3],
    averaged over the pixels, at the strongest orientation minus its mean over orientations: thin structures that
    share a direction (rain falls one way in a view) and that the reference does not have. Noise answers every
    orientation alike, so it scores near 0."""
    y = _luma(ref).double()
    response = line_responses(_luma(pred).double() - y)
    # where the reference has edges, a slightly blurred or shifted render leaves oriented residuals too: count
    # the pixels whose neighbourhood is smooth in the reference
    edges = line_responses(y).amax(dim=0)
    smooth = torch.exp(-((edges / SMOOTH_LEVEL) ** 2))
    per_angle = (response * smooth).sum(dim=(1, 2)) / smooth.sum().clamp_min(1.0)
    return float(per_angle.max() - per_angle.mean())


def _local_contrast(y: torch.Tensor, size: int = 7) -> torch.Tensor:
    mean = F.avg_pool2d(y, size, stride=1)
    var = (F.avg_pool2d(y * y, size, stride=1) - mean * mean).clamp_min(0)
    return var.sqrt()


def contrast_ratio(pred: torch.Tensor, ref: torch.Tensor) -> float:
    """Mean local RMS contrast of ``pred`` [H, W, 3] over that of ``ref`` [H, W, 3] (7 × 7 windows)."""
    c_ref = _local_contrast(_luma(ref).double()).mean()
    return float(_local_contrast(_luma(pred).double()).mean() / c_ref.clamp_min(1e-8))
