"""Per-view exposure: a gain and an offset per colour channel for each training photo.

Photos of one capture differ in exposure and white balance; without a place for that, the view-dependent colour
of the Gaussians learns each training photo's tone and shows it wrongly in every other view. Each training view
gets per-channel gains and offsets (exposure times white balance, and a black level) that its renders pass through
before the loss, as the reference 3DGS's exposure compensation does with a full 3x4 affine (which measured worse
here: it also fits what is not tone). Gains average to one and offsets to zero over the training views, so the
scene holds the views' average appearance, which exports, camera paths and the viewer render.

A view outside training (a test view) is photographed too, with the exposure its camera chose there. Where the
training photos' tone follows where the camera stands (automatic exposure down a street, a phone circling an
object), the nearest training photo's tone predicts it; where it jumps from shot to shot, the average does. Which
of the two predicts each training photo better from the others (leave one out) decides how test views are toned.
"""

from __future__ import annotations

import torch
from torch import nn

from metegs.cameras import Cameras

TONE_LEVELS = (0.25, 0.5, 0.75)
"""Colour values at which two tones (gain and offset per channel) are compared."""


def nearest_training_rows(cameras: Cameras, train_indices: list[int]) -> list[int]:
    """Row (in ``train_indices``) of each view's nearest other training view: camera centres apart in units of the
    training cameras' median spacing, plus 1 - cos of the angle between their optical axes. [N] rows as a list;
    -1 where no other training view exists."""
    train = torch.as_tensor(list(train_indices), dtype=torch.long)
    cameras = cameras.to("cpu")
    centers = cameras.centers.double()
    axes = cameras.camera_to_worlds[:, :3, 2].double()
    apart = torch.cdist(centers, centers[train])  # [N, V]
    spacing_between = apart[train].clone()
    spacing_between.fill_diagonal_(float("inf"))
    spacing = spacing_between.min(dim=1).values
    spacing = spacing[torch.isfinite(spacing) & (spacing > 0)]
    unit = float(spacing.median()) if len(spacing) else 1.0  # cameras in one place: the heading decides
    distance = apart / unit + (1.0 - axes @ axes[train].T)
    distance[train, torch.arange(len(train))] = float("inf")  # a training view's neighbour is another view
    rows = distance.argmin(dim=1)
    rows[~torch.isfinite(distance.min(dim=1).values)] = -1
    return rows.tolist()


class ViewExposure(nn.Module):
    """Per-channel gains and offsets per training view, averaging to the identity."""

    def __init__(
        self,
        train_indices: list[int],
        num_views: int,
        device: torch.device | str = "cpu",
        nearest: list[int] | None = None,
    ):
        super().__init__()
        train = torch.as_tensor(list(train_indices), dtype=torch.long)
        slot = torch.full((num_views,), -1, dtype=torch.long)
        slot[train] = torch.arange(len(train))
        self.train_views: list[int] = train.tolist()
        """The dataset view of each row of ``offsets``."""
        self.slot: list[int] = slot.tolist()
        """Row of each dataset view in ``offsets`` (-1: not a training view); a list, so a step on a GPU reads it
        without waiting for the device."""
        self.offsets = nn.Parameter(torch.zeros(len(train), 2, 3, device=device))
        """[V, 2, 3] each training view's gain departure from one and its offset, per channel (before the means
        over the views are removed)."""
        self.nearest = nearest
        """Row of each dataset view's nearest other training view (`nearest_training_rows`), or None: views outside
        training always take the average tone."""

    def gains_and_offsets(self) -> tuple[torch.Tensor, torch.Tensor]:
        """([V, 3], [V, 3]) the training views' gains (mean one) and offsets (mean zero): colour' = gain * colour
        + offset."""
        centred = self.offsets - self.offsets.mean(dim=0, keepdim=True)
        return 1.0 + centred[:, 0], centred[:, 1]

    @torch.no_grad()
    def tone_errors(self) -> tuple[float, float]:
        """RMS colour errors (at `TONE_LEVELS`) of predicting each training photo's tone from its nearest other
        training photo's and from the other photos' average, left out one at a time; (inf, 0) where there is no
        neighbour to ask."""
        views = len(self.offsets)
        if self.nearest is None or views < 2:
            return float("inf"), 0.0
        gains, offsets = self.gains_and_offsets()
        levels = torch.tensor(TONE_LEVELS, dtype=gains.dtype, device=gains.device)
        tones = gains[:, None, :] * levels[None, :, None] + offsets[:, None, :]  # [V, L, 3]
        neighbour = torch.as_tensor([self.nearest[view] for view in self.train_views], device=tones.device)
        others = (tones.sum(dim=0, keepdim=True) - tones) / (views - 1)
        near = float((tones[neighbour] - tones).square().mean().sqrt())
        average = float((others - tones).square().mean().sqrt())
        return near, average

    def tones_from_nearest(self) -> bool:
        """Whether views outside training take their nearest training photo's tone (it predicts the training photos
        better than their average does) rather than the average (as rendered)."""
        near, average = self.tone_errors()
        return near < average

    def forward(self, rgb: torch.Tensor, view: int) -> torch.Tensor:
        """``rgb`` [H, W, 3] as dataset view ``view``'s photo shows it: a training view in its own tone, any other
        in its nearest training photo's where `tones_from_nearest`, else unchanged (the average tone)."""
        row = self.slot[view]
        if row < 0:
            if not self.tones_from_nearest():
                return rgb
            row = self.nearest[view]
        gains, offsets = self.gains_and_offsets()
        return rgb * gains[row] + offsets[row]
