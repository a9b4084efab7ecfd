"""Per-view exposure: a gain and an offset per colour channel for each training photo.

Photos of one capture differ in exposure and white balance; without a place for that, the view-dependent colour
of the Gaussians learns each training photo's tone and shows it wrongly in every other view. Each training view
gets per-channel gains and offsets (exposure times white balance, and a black level) that its renders pass through
before the loss, as the reference 3DGS's exposure compensation does with a full 3x4 affine (which measured worse
here: it also fits what is not tone). Gains average to one and offsets to zero over the training views, so the
scene holds the views' average appearance, which unseen views, exports and the viewer render.
"""

from __future__ import annotations

import torch
from torch import nn


class ViewExposure(nn.Module):
    """Per-channel gains and offsets per training view, averaging to the identity."""

    def __init__(self, train_indices: list[int], num_views: int, device: torch.device | str = "cpu"):
        super().__init__()
        train = torch.as_tensor(list(train_indices), dtype=torch.long)
        slot = torch.full((num_views,), -1, dtype=torch.long)
        slot[train] = torch.arange(len(train))
        self.slot: list[int] = slot.tolist()
        """Row of each dataset view in ``offsets`` (-1: not a training view); a list, so a step on a GPU reads it
        without waiting for the device."""
        self.offsets = nn.Parameter(torch.zeros(len(train), 2, 3, device=device))
        """[V, 2, 3] each training view's gain departure from one and its offset, per channel (before the means
        over the views are removed)."""

    def gains_and_offsets(self) -> tuple[torch.Tensor, torch.Tensor]:
        """([V, 3], [V, 3]) the training views' gains (mean one) and offsets (mean zero): colour' = gain * colour
        + offset."""
        centred = self.offsets - self.offsets.mean(dim=0, keepdim=True)
        return 1.0 + centred[:, 0], centred[:, 1]

    def forward(self, rgb: torch.Tensor, view: int) -> torch.Tensor:
        """``rgb`` [H, W, 3] as dataset view ``view``'s photo shows it (a view outside training: unchanged)."""
        row = self.slot[view]
        if row < 0:
            return rgb
        gains, offsets = self.gains_and_offsets()
        return rgb * gains[row] + offsets[row]
