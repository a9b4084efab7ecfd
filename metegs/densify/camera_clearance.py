"""Free space around the training cameras: no part of the scene sits where a photo was taken from, unseen by it.

A camera, and whoever holds it, fills the space around the point each photo was taken from, and a surface there in
front of the lens would fill that photo. Gaussians that end up beside or behind a camera, where its own view does not
see them, are floaters: they carry light of the views behind it that no surface explains (the rain's streaks and veil
in blind training), and a novel view on the same path looks straight through them. So the Gaussians within a fraction
of the distance between neighbouring cameras of a training camera that none of those near cameras sees are pruned,
whatever their opacity (within a tenth of the scene's typical depth at most); one in front of a near camera stays,
for that photo holds it.

Around a scene seen from outside (an object, a face) nothing comes near the cameras and this prunes nothing; where the
cameras walk through the scene (a street) it clears their path.
"""

from __future__ import annotations

import torch

from metegs.cameras import Cameras
from metegs.densify.depth_prune import camera_depths
from metegs.densify.surgery import select_rows
from metegs.gaussians.model import GaussianModel

DEPTH_SHARE = 0.1
"""The radius stays under this share of the scene's typical depth: where few cameras stand far apart (a ring of a
dozen), half their spacing reaches the ground under them."""

_PAIRS_PER_CHUNK = 1 << 22


def camera_spacing(centers: torch.Tensor) -> float:
    """Median over the cameras of the distance to the nearest other camera. centers [V, 3] -> scene units (0 with
    fewer than two cameras)."""
    if len(centers) < 2:
        return 0.0
    nearest = torch.cdist(centers, centers).topk(2, largest=False).values[:, 1]
    return float(nearest.median())


def unseen_near_cameras(means: torch.Tensor, cameras: Cameras, radius: float) -> torch.Tensor:
    """[N] bool: which of ``means`` [N, 3] lie within ``radius`` of a camera centre, and in none of those near
    cameras' views (`camera_depths`)."""
    out = torch.zeros(len(means), dtype=torch.bool, device=means.device)
    if radius <= 0 or len(cameras) == 0:
        return out
    cams = cameras.to(means.device)
    centers = cams.camera_to_worlds[:, :3, 3].to(means)
    chunk = max(1, _PAIRS_PER_CHUNK // len(cams))
    for start in range(0, len(means), chunk):
        part = means[start : start + chunk]
        near = torch.cdist(centers, part) < radius  # [C, n]
        candidates = near.any(dim=0)
        if not candidates.any():
            continue
        _, seen = camera_depths(part[candidates], cams)
        hit = candidates.clone()
        hit[candidates] = ~(near[:, candidates] & seen).any(dim=0)
        out[start : start + chunk] = hit
    return out


class CameraClearance:
    """Prunes the Gaussians that `unseen_near_cameras` finds within ``fraction`` of the cameras' `camera_spacing`,
    at most `DEPTH_SHARE` of ``typical_depth`` (scene units)."""

    def __init__(self, cameras: Cameras, fraction: float, typical_depth: float):
        self.cameras = cameras
        spacing = camera_spacing(cameras.camera_to_worlds[:, :3, 3].float())
        self.radius = min(fraction * spacing, DEPTH_SHARE * typical_depth)

    @torch.no_grad()
    def prune(self, model: GaussianModel, optimizers) -> int:
        """Remove those of the model's Gaussians (and their Adam moments) -> how many."""
        gone = unseen_near_cameras(model.params["means"].detach(), self.cameras, self.radius)
        count = int(gone.sum())
        if count:
            select_rows(model.params, optimizers, ~gone)
        return count
