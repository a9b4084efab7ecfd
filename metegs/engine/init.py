"""Initial scene Gaussians: from the scene's points, or random where the training views overlap."""

from __future__ import annotations

import numpy as np
import torch

from metegs.cameras import Cameras, look_at_point


def random_points_in_view_overlap(cameras: Cameras, n: int, seed: int = 0, min_views: int = 3) -> np.ndarray:
    """``n`` random points in a box around the views' look-at point, each seen by at least ``min_views`` cameras
    (drawn on the CPU: the same points on every device)."""
    cameras = cameras.to("cpu")
    g = torch.Generator().manual_seed(seed)
    center = look_at_point(cameras)
    radius = float((cameras.centers - center).norm(dim=1).median()) * 0.6
    need = min(min_views, len(cameras))
    kept = []
    total = 0
    for _ in range(50):
        cand = center + (torch.rand(4 * n, 3, generator=g) * 2 - 1) * radius
        ok = cand[cameras.sees(cand).sum(0) >= need]
        kept.append(ok)
        total += ok.shape[0]
        if total >= n:
            break
    pts = torch.cat(kept)[:n] if total else center + (torch.rand(n, 3, generator=g) * 2 - 1) * radius
    return pts.numpy()


def scene_extent(cameras: Cameras) -> float:
    """3DGS scene extent: 1.1 x the largest distance of a camera centre from their mean."""
    c = cameras.centers
    return float(1.1 * (c - c.mean(0)).norm(dim=1).max().clamp_min(1e-3))
