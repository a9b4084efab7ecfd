"""Trimmed photometric loss: pixels that the model cannot explain in one view are left out of that view's fit.

In the spirit of RobustNeRF (Sabour et al., CVPR 2023): what is not multi-view consistent (a rain streak, a drop)
leaves a residual that stays large where the rest of the view is fitted. Per view, a pixel is an outlier when its
residual (photo − render, mean over channels) exceeds ``k_sigma`` robust standard deviations of that view's
residuals (1.4826 × the median absolute deviation, so the threshold follows how well the view is fitted: early in
training, when everything is off, little is left out), and by at least ``min_excess`` (a view fitted closely has
a tiny σ, and its fine texture is not weather). Rain and drops add light to a photo, so by default only
residuals where the photo is brighter than the model count (``brighter_only``); outliers are grown by
``dilate_px`` to take the soft edges of a streak. The weights carry no gradient: they select which pixels the
photometric loss sees.

The mask leaves out what stands out; dense rain also brightens almost every other pixel a little (blurred streak
tails, a veil), so the median of a pixel's photos, which L1 fits, sits above the clean scene. Rain only ever adds
light to a photo (Garg and Nayar, CVPR 2004), so with the mask the L1 fits a low ``quantile`` of a pixel's photos
(`metegs.losses.photometric.pinball_l1`). The SSIM term can weigh less then (``ssim_lambda``): it rewards a render
whose local contrast and structure follow the photo's, streaks included, and a fit that may not be brighter than the
photos follows them by darkening the gaps between the streaks, which leaves dark strokes in the clean scene.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

import torch
import torch.nn.functional as F

from metegs.validate import FRACTION, NON_NEGATIVE, Range

MAD_TO_SIGMA = 1.4826
"""Standard deviation per median absolute deviation of a normal distribution."""


@dataclass
class RobustMaskConfig:
    """Trimmed photometric loss of the weather branch (outlier mask from a robust residual scale)."""

    enabled: bool = True
    """Leave out of each view's photometric loss the pixels the model cannot explain (outlier mask)."""
    k_sigma: Annotated[float, Range(1.0)] = 3.0
    """A residual above this many robust standard deviations of its view's residuals is an outlier."""
    brighter_only: bool = True
    """Only pixels where the photo is brighter than the model can be outliers (rain and drops add light)."""
    min_excess: Annotated[float, FRACTION] = 0.04
    """Nor is a pixel less than this much brighter than the model (a well-fitted view's small residuals: fine
    texture, not weather)."""
    dilate_px: Annotated[int, NON_NEGATIVE] = 1
    """Outliers are grown by this many pixels (the soft edges of a streak)."""
    start: Annotated[float, FRACTION] = 0.1
    """Fraction of the run before the mask is used (the scene must first fit something)."""
    quantile: Annotated[float, Range(0.0, 0.5, lo_open=True)] = 0.1
    """With the mask, the L1 fits this quantile of a pixel's photos instead of their median (0.5: plain L1): rain
    brightens nearly every pixel a little, so the clean scene lies under most of its photos."""
    ssim_lambda: Annotated[float | None, FRACTION] = None
    """Weight of the D-SSIM term while the L1 fits the low quantile (None: the loss's own): SSIM asks for the
    photos' local contrast, streaks included, which a fit held under the photos makes by darkening between them."""


@torch.no_grad()
def inlier_weights(residual: torch.Tensor, config: RobustMaskConfig) -> torch.Tensor:
    """[H, W] float weights in {0, 1} of one view from its residual ``residual`` [H, W, 3] (photo − render)."""
    err = residual.mean(dim=-1)
    excess = err - err.median()
    sigma = MAD_TO_SIGMA * excess.abs().median()
    outlier = excess if config.brighter_only else excess.abs()
    mask = (outlier > torch.clamp(config.k_sigma * sigma, min=config.min_excess)).float()[None, None]
    if config.dilate_px > 0:
        k = 2 * config.dilate_px + 1
        mask = F.max_pool2d(mask, k, stride=1, padding=config.dilate_px)
    return 1.0 - mask[0, 0]
