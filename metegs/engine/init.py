"""Initial scene Gaussians: from the scene's points, or random where the training views overlap."""

from __future__ import annotations

import numpy as np
import torch

from metegs.cameras import Cameras


def look_at_point(cameras: Cameras) -> torch.Tensor:
    """Least-squares point closest to all optical axes. -> [3]."""
    c = cameras.centers.double()
    d = cameras.camera_to_worlds[:, :3, 2].double()
    d = d / d.norm(dim=1, keepdim=True)
    eye = torch.eye(3, dtype=torch.float64, device=c.device)
    P = eye[None] - d[:, :, None] * d[:, None, :]
    A = P.sum(0)
    b = (P @ c[:, :, None]).sum(0)
    if torch.linalg.matrix_rank(A) < 3:  # parallel axes (forward-facing): a point in front of the mean camera
        return (c.mean(0) + d.mean(0) * c.std(0).norm().clamp_min(1.0)).float()
    return torch.linalg.solve(A, b).flatten().float()


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
