"""The dark channel prior (He, Sun and Tang, CVPR 2009) as a loss on a medium: blind fog removal from the photos.

In haze-free images most patches hold a pixel near black in some colour channel (shadows, saturated colours, dark
objects); fog lifts those pixels towards the airlight. Where a foggy photo is dehazed with the medium's own
transmission, J = (I − A)/t + A, a medium that is too thin leaves J's dark channel high (haze kept), one that is too
thick drives it below zero. The loss holds a low quantile of J's dark channel at zero (a pinball loss), which sets
β's level from the photos where the photometric fit alone cannot tell fog from a hazy scene (every view at about the
same distance); β's colour stays the photometric fit's (`FogAnalytic.dehaze`), and the trainer holds the airlight
at its estimate from the photos, as He et al. estimate A once (a free A sank from 0.85 to 0.70 on the Ethiopian
head in fog while the scene took the haze in). A low quantile
rather than the median: in the clean views of the Ethiopian head, the instant-ngp fox and the Lund street (15 px
patches at 500 px) the median of the dark channel is 0.14-0.23 (white cloth, sky), the 10 % quantile 0.000-0.029.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Literal

import torch
import torch.nn.functional as F

from metegs.validate import NON_NEGATIVE, Range

PATCH_PX_AT_600 = 15
"""He et al.'s patch: 15 px at images of about 600 px; scaled with the image."""

SAMPLED_SIDE_PX = 320
"""Longer side, in pixels, near which the prior samples a view (`sample_stride`)."""


@dataclass
class DarkChannelPriorConfig:
    """Dark-channel prior on the fog medium in blind training (no clean references to measure β and A)."""

    mode: Literal["auto", "on", "off"] = "auto"
    """auto: on where the photos cannot measure β themselves (every view sees the scene from about the same
    distance) or the fog is dense at the scene's depth with no heavy rain through it; on: wherever training is
    blind."""
    weight: Annotated[float, NON_NEGATIVE] = 1.0
    """Weight of the prior in the weather branch's loss (0: off)."""
    quantile: Annotated[float, Range(0.0, 1.0)] = 0.1
    """The quantile of the dehazed photo's dark channel held at zero."""
    patch_px: Annotated[int, NON_NEGATIVE] = 0
    """Side of the dark channel's square patch in pixels (0: 15 px per 600 px of the longer image side)."""
    min_transmission: Annotated[float, Range(1e-3, 1.0)] = 0.05
    """Pixels seen through less than this are left out (their dehazing only amplifies noise)."""


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


def pinball(values: torch.Tensor, quantile: float) -> torch.Tensor:
    """Mean pinball (quantile) loss of ``values`` [N] against 0: minimised where ``quantile`` of them are below 0."""
    return torch.maximum(quantile * values, (quantile - 1.0) * values).mean()


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


def dark_channel_loss(dehazed: torch.Tensor, valid: torch.Tensor, config: DarkChannelPriorConfig) -> torch.Tensor:
    """Pinball loss holding ``config.quantile`` of the dark channel of ``dehazed`` [H, W, 3] at zero over the
    ``valid`` [H, W] bool pixels (a patch touching an invalid pixel is left out; every `sample_stride`-th pixel of
    large views) -> scalar (0 when none is valid)."""
    step = sample_stride(*valid.shape)
    dehazed, valid = dehazed[::step, ::step], valid[::step, ::step]
    h, w = valid.shape
    patch = patch_size(h, w, config.patch_px)
    dark = masked_dark_channel(dehazed, valid, patch)
    whole = window_min(valid.float(), patch) > 0.5
    if not bool(whole.any()):
        return dehazed.sum() * 0.0
    return pinball(dark[whole], config.quantile)
