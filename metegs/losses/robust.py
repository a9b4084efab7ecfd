"""Trimmed photometric loss: pixels that the model cannot explain in one view are left out of that view's fit.

In the spirit of RobustNeRF (Sabour et al., CVPR 2023): what is not multi-view consistent (a rain streak, a drop)
leaves a residual that stays large where the rest of the view is fitted. Per view, a pixel is an outlier when its
residual (photo − render, mean over channels) exceeds ``k_sigma`` robust standard deviations of that view's
residuals (1.4826 × the median absolute deviation, so the threshold follows how well the view is fitted: early in
training, when everything is off, little is left out), and by at least ``min_excess`` (a view fitted closely has
a tiny σ, and its fine texture is not weather). Rain and drops add light to a photo, so by default only
residuals where the photo is brighter than the model count (``brighter_only``), and only in the photo's thin bright
strokes that run the way most of them run (``thin_only``, `thin_strokes`: a streak is thin and falls with its rain,
a highlight that moves from view to view is neither); outliers are grown by ``dilate_px`` to take the soft edges of
a streak. The weights carry no gradient: they select which pixels the photometric loss sees.

The mask leaves out what stands out; dense rain also brightens almost every other pixel a little (blurred streak
tails, a veil), so the median of a pixel's photos, which L1 fits, sits above the clean scene. Rain only ever adds
light to a photo (Garg and Nayar, CVPR 2004), so with the mask the L1 fits a low ``quantile`` of a pixel's photos
(`metegs.losses.photometric.pinball_l1`); a milder one where the dark-channel prior holds the medium, whose veil
then takes the even part of that light, and one nearer the median where the photos of a scene point spread far
further above their median than below (sparse streaks, which leave the median clear; `metegs.eval.view_spread`).
The SSIM term rewards a render whose local contrast and structure follow the photo's, streaks included, and a fit
that may not be brighter than the photos follows them by darkening the gaps between the streaks, which leaves dark
strokes in the clean scene; during that fit SSIM can compare render and photo without their thin bright strokes
(``stroke_px``, `without_bright_strokes`) or weigh less (``ssim_lambda``).

The record says how hard it rains; the photos say whether there are streaks to trim. The mask goes on only where the
training photos' thin bright strokes of one orientation hold enough energy (`stroke_energy`, ``min_stroke_energy``):
where they do not (faint streaks and a veil that the weather models explain, or clear photos under a rainy record),
leaving each view's brightest pixels out and fitting under the rest only dimmed the scene.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

import torch
import torch.nn.functional as F

from metegs.eval.residual_weather import line_responses
from metegs.losses.fused_opening import fused_opening_available, fused_strokes_out
from metegs.losses.photometric import open_bright
from metegs.validate import FRACTION, NON_NEGATIVE, Range

MAD_TO_SIGMA = 1.4826
"""Standard deviation per median absolute deviation of a normal distribution."""

LOW_QUANTILE = 0.1
"""Quantile of a pixel's photos that the trimmed L1 fits in rain heavier than light, unless told otherwise (Lund,
independent heavy rain, blind: 14.16 dB against 11.93 with the median)."""

VEILED_QUANTILE = 0.25
"""The same where the dark-channel prior holds the medium: the medium's veil then takes the even part of the rain's
light, and a fit held as low as `LOW_QUANTILE` darkens the scene a second time (blind, independent family: the
Ethiopian head's heavy rain 20.67 dB against 19.04 at 0.1 and 20.30 at 0.5, the fox's rain + fog 17.29 against 16.46
and 15.88)."""

THIN_STREAK_PX = 3.0
"""Width of a rain streak at a longer image side of `STROKE_REFERENCE_SIDE_PX`: the robust mask's `thin_only` test
opens the photo by a square of twice this less one, scaled with the image (`stroke_width_px`); D-SSIM's
`RobustMaskConfig.stroke_px` takes strokes of this width by default."""

STROKE_REFERENCE_SIDE_PX = 480
"""Longer image side at which `RobustMaskConfig.stroke_px` is given (a streak's width in px grows with the image)."""

STROKE_TURN_STEPS = 2
"""How many of the line filters' 15° steps a stroke may turn from its photo's main orientation and still count as
rain (`along_the_strokes`): the independent family draws each streak layer's angle about its view's with a spread of
10° in heavy rain; a scene's bright edges, going every way, fall outside in 7 of 12 orientations."""

VISIBLE_STROKE_ENERGY = 0.002
"""`stroke_energy` (median over the training photos) from which the photos show rain streaks: 0.0038-0.0079 under
the independent family's streak layers (Ethiopian head, fox), 0.0003-0.0011 on their clear photos, under metegs's
own heavy rain (faint streaks and a veil, which its weather models explain) and on the built-in scene."""


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
    thin_only: bool = True
    """Only pixels of the photo's thin bright strokes can be outliers (`thin_strokes`; where streaks are at least two
    pixels wide) that run the way most of its strokes run: a streak is thin and falls with its rain, a highlight that
    moves from view to view is neither, and trimming it dims the scene."""
    start: Annotated[float, FRACTION] = 0.1
    """Fraction of the run before the mask is used (the scene must first fit something)."""
    min_stroke_energy: Annotated[float, NON_NEGATIVE] = VISIBLE_STROKE_ENERGY
    """The mask goes on only where the training photos hold at least this much energy of thin bright strokes that
    share one orientation (`stroke_energy`, median): streaks the photos show (0: the record's rain alone decides)."""
    quantile: Annotated[float | None, Range(0.0, 0.5, lo_open=True)] = None
    """With the mask, the L1 fits this quantile of a pixel's photos instead of their median (0.5: plain L1): rain
    brightens nearly every pixel a little, so the clean scene lies under most of its photos. None: from `LOW_QUANTILE`
    (`VEILED_QUANTILE` where the dark-channel prior holds the medium) towards the median as far as the photos of a
    scene point spread further above their median than below it (`metegs.eval.view_spread`, read at ``start``)."""
    ssim_lambda: Annotated[float | None, FRACTION] = None
    """Weight of the D-SSIM term while the L1 fits the low quantile (None: the loss's own): SSIM asks for the
    photos' local contrast, streaks included, which a fit held under the photos makes by darkening between them."""
    stroke_px: Annotated[float, NON_NEGATIVE] = THIN_STREAK_PX
    """While the L1 fits the low quantile, D-SSIM compares render and photo without the bright strokes narrower
    than this (`without_bright_strokes`), in px at a longer image side of 480 px and scaled with it (0: off; under
    2 px after scaling, nothing is taken): the photo's streaks are not asked of the render, which it would fake by
    darkening between them."""


@torch.no_grad()
def inlier_weights(
    residual: torch.Tensor, config: RobustMaskConfig, strokes: torch.Tensor | None = None
) -> torch.Tensor:
    """[H, W] float weights in {0, 1} of one view from its residual ``residual`` [H, W, 3] (photo − render); where
    ``strokes`` [H, W] bool is given (`thin_strokes` of the photo), only its pixels can be outliers."""
    err = residual.mean(dim=-1)
    excess = err - err.median()
    sigma = MAD_TO_SIGMA * excess.abs().median()
    outlier = excess if config.brighter_only else excess.abs()
    mask = outlier > torch.clamp(config.k_sigma * sigma, min=config.min_excess)
    if strokes is not None:
        mask &= strokes
    mask = mask.float()[None, None]
    if config.dilate_px > 0:
        k = 2 * config.dilate_px + 1
        mask = F.max_pool2d(mask, k, stride=1, padding=config.dilate_px)
    return 1.0 - mask[0, 0]


@torch.no_grad()
def thin_strokes(photo: torch.Tensor, width: int, min_excess: float) -> torch.Tensor:
    """[H, W] bool: the pixels of ``photo`` [H, W, 3] whose bright stroke, narrower than ``width`` px in some
    direction, stands out of the photo's `open_bright` by more than ``min_excess`` (mean over channels), and runs
    the way the photo's strokes run most (`along_the_strokes`): a streak falls with its rain, the bright edges of a
    scene (a metal head's highlights) go every way."""
    top_hat = (photo - open_bright(photo, width)).mean(dim=-1)
    return (top_hat > min_excess) & along_the_strokes(top_hat)


@torch.no_grad()
def along_the_strokes(top_hat: torch.Tensor) -> torch.Tensor:
    """[H, W] bool: the pixels of a photo's top-hat ``top_hat`` [H, W] whose strongest oriented line filter
    (`line_responses`) is within `STROKE_TURN_STEPS` of the one that answers the whole photo most. A photo twice
    `STROKE_REFERENCE_SIDE_PX` or more is read in blocks of a whole number of pixels, which keeps its longer side at
    that reference or over (where `stroke_energy` reads it too), and each pixel takes its block's answer."""
    h, w = top_hat.shape
    block = max(1, max(h, w) // STROKE_REFERENCE_SIDE_PX)
    response = line_responses(F.avg_pool2d(top_hat.float()[None, None], block, ceil_mode=True))
    steps = response.shape[0]
    turn = (response.argmax(dim=0) - response.mean(dim=(1, 2)).argmax()).abs()
    along = torch.minimum(turn, steps - turn) <= STROKE_TURN_STEPS
    return along.repeat_interleave(block, 0).repeat_interleave(block, 1)[:h, :w]


def without_bright_strokes(
    render: torch.Tensor, photo: torch.Tensor, width: int, min_excess: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """(render, photo), each [H, W, 3], opened (`open_bright`) where either holds a bright stroke narrower than
    ``width`` px that stands out of its opening by more than ``min_excess`` (mean over channels), as they are
    elsewhere. A streak in the photo is then not asked of the render, nor a modelled streak in the render of the
    photo, and a stroke both hold (a bright edge) is compared opened on both sides. The render's opening carries
    its gradient (to the pixels the erosion and dilation pick): without it the fox's blind run lost 2 dB."""
    if width <= 1:
        return render, photo
    if not photo.requires_grad and fused_opening_available(render):
        return fused_strokes_out(render, photo, width | 1, min_excess)
    return pooled_strokes_out(render, photo, width, min_excess)


def pooled_strokes_out(
    render: torch.Tensor, photo: torch.Tensor, width: int, min_excess: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """`without_bright_strokes` in torch ops (the reference of the compiled `fused_strokes_out`)."""
    render_opened, photo_opened = open_bright(render, width), open_bright(photo, width)
    with torch.no_grad():
        stroke = (photo - photo_opened).mean(dim=-1) > min_excess
        stroke |= (render - render_opened).mean(dim=-1) > min_excess
    stroke = stroke[..., None]
    return torch.where(stroke, render_opened, render), torch.where(stroke, photo_opened, photo)


@torch.no_grad()
def stroke_energy(image: torch.Tensor) -> float:
    """Energy of the thin bright strokes of ``image`` [H, W, 3] that share one orientation, seen at a longer side
    of at most `STROKE_REFERENCE_SIDE_PX`: the mean response of the oriented line filters (`line_responses`) to its
    top-hat (the image less its `open_bright` by a 3-px square, mean over channels) at the strongest orientation,
    less their mean over orientations (as `streak_energy` measures a residual). The streaks of one rain fall one way
    in a photo; a scene's bright details go every way, and noise answers every filter alike."""
    x = image.float()
    scale = STROKE_REFERENCE_SIDE_PX / max(image.shape[:2])
    if scale < 1:  # not up: interpolation would lend pixel noise the grid's orientations
        x = F.interpolate(x.permute(2, 0, 1)[None], scale_factor=scale, mode="area", recompute_scale_factor=False)
        x = x[0].permute(1, 2, 0)
    response = line_responses((x - open_bright(x, 3)).mean(dim=-1)[None, None]).mean(dim=(1, 2))
    return float(response.max() - response.mean())


def stroke_width_px(stroke_px: float, longer_side_px: int) -> int:
    """The odd square width that takes strokes of ``stroke_px`` (at `STROKE_REFERENCE_SIDE_PX`) from an image whose
    longer side is ``longer_side_px``; 1 (nothing to take) where they are under two pixels wide."""
    width = round(stroke_px * longer_side_px / STROKE_REFERENCE_SIDE_PX)
    return width | 1 if width >= 2 else 1
