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

from metegs.eval.veil import masked_dark_channel, patch_size, sample_stride, window_min
from metegs.validate import NON_NEGATIVE, Range


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


def pinball(values: torch.Tensor, quantile: float) -> torch.Tensor:
    """Mean pinball (quantile) loss of ``values`` [N] against 0: minimised where ``quantile`` of them are below 0."""
    return torch.maximum(quantile * values, (quantile - 1.0) * values).mean()


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
