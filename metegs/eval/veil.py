"""How much veil an image shows: the dark channel (He, Sun and Tang, CVPR 2009) and what it reads in a photo.

In haze-free images most patches hold a pixel near black in some colour channel (shadows, saturated colours, dark
objects); a medium lifts those pixels towards its airlight, so the dark channel measures the share of contrast the
medium takes. The airlight estimate (`metegs.weather.airlight`), the dark-channel prior on the fog medium
(`metegs.losses.dark_channel`) and the trainer's veil rule read it from here.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

PATCH_PX_AT_600 = 15
"""He et al.'s patch: 15 px at images of about 600 px; scaled with the image."""

SAMPLED_SIDE_PX = 320
"""Longer side, in pixels, near which the prior samples a view (`sample_stride`)."""


def patch_size(height: int, width: int, patch_px: int = 0) -> int:
    """An odd patch side: ``patch_px`` if given, else 15 px per 600 px of the longer side (at least 3)."""
    size = patch_px or round(PATCH_PX_AT_600 * max(height, width) / 600)
    return max(3, size | 1)


def window_min(values: torch.Tensor, patch: int) -> torch.Tensor:
    """The smallest of ``values`` [H, W] over a ``patch``×``patch`` window (odd) around each pixel -> [H, W]; by rows
    then columns (2·patch comparisons a pixel instead of patch²)."""
    x = -values[None, None]
    x = F.max_pool2d(x, (patch, 1), stride=1, padding=(patch // 2, 0))
    return -F.max_pool2d(x, (1, patch), stride=1, padding=(0, patch // 2))[0, 0]


def dark_channel(image: torch.Tensor, patch: int) -> torch.Tensor:
    """The smallest value over the channels and a ``patch``×``patch`` window (odd). image [H, W, C] -> [H, W]."""
    return window_min(image.amin(-1), patch)


def masked_dark_channel(image: torch.Tensor, valid: torch.Tensor, patch: int) -> torch.Tensor:
    """`dark_channel` of ``image`` [H, W, C] in which only the ``valid`` [H, W] bool pixels can be a patch's minimum
    (the others are lifted above every value first) -> [H, W]."""
    return dark_channel(torch.where(valid[..., None], image, image.detach().amax() + 1.0), patch)


def sample_stride(height: int, width: int) -> int:
    """Every how many pixels the prior looks: it sets one level, which a quarter of a 500 px view measures as well
    (1 up to 480 px on the longer side, 2 up to 800 px, ...)."""
    return max(1, round(max(height, width) / SAMPLED_SIDE_PX))


VEIL_QUANTILE = 0.05
"""The share of a photo's patches whose dark channel `photo_veil` reads: its darkest, below which a photo's own
noise lies (clear views of the Ethiopian head and the instant-ngp fox: 0.001-0.014)."""

BLACK = 1.0 / 255.0
"""Pixels at or under this in every channel are no surface (an undistorted photo's borders, a masked sky): no
medium leaves a pixel that dark, so `photo_veil` reads around them."""


def photo_veil(image: torch.Tensor, airlight: torch.Tensor, quantile: float = VEIL_QUANTILE) -> float:
    """The veil a photo shows: ``quantile`` of the dark channel of ``image`` [H, W, 3] / ``airlight`` [3] (every
    `sample_stride`-th pixel, He et al.'s patch; black pixels left out). Through a medium of transmission t a surface
    near black reads I = A·(1 − t), so its dark channel over A is the share of contrast the medium takes there
    (`weather.medium.veil_fraction`); clear photos hold such patches at about 0, fog lifts all of them. 0 for a
    photo that is black throughout."""
    step = sample_stride(*image.shape[:2])
    x = image[::step, ::step].detach().float()
    seen = x.amax(dim=-1) > BLACK
    if not bool(seen.any()):
        return 0.0
    x = x / airlight.detach().to(x.device).float().clamp_min(1e-3)
    dark = masked_dark_channel(x, seen, patch_size(*x.shape[:2]))
    return float(torch.quantile(dark[seen], quantile))
