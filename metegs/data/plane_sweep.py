"""Sparse points from a plane sweep of posed photos, for views whose features SIFT cannot match (rain, haze).

Rain streaks and lens drops are features of one photo: they take SIFT's keypoints, and a dense fog takes the
contrast of the rest, so triangulation from such photos finds a few dozen points (the Ethiopian head under heavy
rain: 36, against 3000 from its clean photos) and training starts from random ones. A plane sweep needs no
keypoints. For every training view it tries depths along each pixel's ray, scores each depth by the normalised
cross-correlation (ZNCC) of a window around the pixel with the neighbour views' pixels it projects to, and keeps
the best depth where the best half of the neighbours agree (a streak or drop in one neighbour does not count
against it: the classic view selection of multi-view stereo, Goesele et al. 2007). Depths that the neighbours'
own depth maps confirm become points, coloured by the median of the views that see them. It works at a small size (``max_side``, 160 px): the scene's coarse structure is what
the Gaussians need to start from, and there the streaks are thin and faint.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from metegs.cameras import Cameras, look_at_point
from metegs.data.triangulate import MIN_POINTS, TriangulatedPoints, cache_key, load_points, save_points

UNSEEN = -2.0
"""ZNCC given to a window that projects outside a neighbour or behind it (below every real score)."""


def _small(image: torch.Tensor, max_side: int) -> torch.Tensor:
    """[H, W, 3] image -> [3, h, w] with its longer side at most ``max_side`` (area average)."""
    h, w = image.shape[:2]
    s = min(1.0, max_side / max(h, w))
    x = image.permute(2, 0, 1)[None].float()
    if s < 1.0:
        x = F.interpolate(x, size=(max(1, round(h * s)), max(1, round(w * s))), mode="area")
    return x[0]


def _neighbours(cameras: Cameras, count: int, max_angle_deg: float) -> list[list[int]]:
    """For each view, the ``count`` nearest other views (camera centres) whose optical axes lie within
    ``max_angle_deg`` of its own."""
    c = cameras.centers.double()
    axis = F.normalize(cameras.camera_to_worlds[:, :3, 2].double(), dim=1)
    dist = torch.cdist(c, c)
    dist[axis @ axis.T < math.cos(math.radians(max_angle_deg))] = math.inf
    dist.fill_diagonal_(math.inf)
    order = dist.argsort(dim=1)[:, :count]
    return [[int(j) for j in row if math.isfinite(float(dist[i, j]))] for i, row in enumerate(order)]


def _box(x: torch.Tensor, window: int) -> torch.Tensor:
    """Mean of each ``window`` x ``window`` square of ``x`` [B, C, h, w] (cut at the borders), by running sums."""
    r = window // 2
    for dim in (-1, -2):
        n = x.shape[dim]
        c = F.pad(x.movedim(dim, -1), (1, 0)).cumsum(-1)  # c[..., i] = sum of x[..., :i]
        hi = torch.arange(n) + r + 1
        lo = torch.arange(n) - r
        hi, lo = hi.clamp(max=n), lo.clamp(min=0)
        x = ((c[..., hi] - c[..., lo]) / (hi - lo).to(x.dtype)).movedim(-1, dim)
    return x


def _zncc(ref: torch.Tensor, other: torch.Tensor, valid: torch.Tensor, window: int) -> torch.Tensor:
    """Windowed ZNCC of ``ref`` [1, 1, h, w] against each of ``other`` [D, 1, h, w]; windows that reach an unseen
    pixel (``valid`` [D, 1, h, w] False) score `UNSEEN`. -> [D, h, w]."""
    other = torch.where(valid, other, 0.0)
    mr, m2r = _box(torch.cat([ref, ref * ref], 1), window).unbind(1)
    mo, mro, m2o, seen = _box(torch.cat([other, ref * other, other * other, valid.float()], 1), window).unbind(1)
    cov = mro - mr * mo
    var = (m2r - mr * mr).clamp_min(0) * (m2o - mo * mo).clamp_min(0)
    return torch.where(seen > 0.999, cov / (var + 1e-10).sqrt(), UNSEEN)


def _project(points: torch.Tensor, cameras: Cameras, view: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixel positions [..., 2] (pixel centres at +0.5) and depths [...] of world ``points`` [..., 3] in ``view``."""
    w2c = cameras.world_to_cameras()[view]
    p = points @ w2c[:3, :3].T + w2c[:3, 3]
    z = p[..., 2]
    zs = z.clamp_min(1e-6)
    uv = torch.stack(
        [cameras.fx[view] * p[..., 0] / zs + cameras.cx[view], cameras.fy[view] * p[..., 1] / zs + cameras.cy[view]], -1
    )
    return uv, z


def _sample(image: torch.Tensor, uv: torch.Tensor, mode: str = "bilinear") -> tuple[torch.Tensor, torch.Tensor]:
    """``image`` [C, h, w] at pixel positions ``uv`` [D, P, 2] -> ([C, D, P] values, [D, P] inside the image)."""
    h, w = image.shape[1:]
    grid = torch.stack([uv[..., 0] / w * 2 - 1, uv[..., 1] / h * 2 - 1], -1)
    inside = (grid.abs() <= 1).all(-1)
    values = F.grid_sample(image[None], grid[None], mode=mode, padding_mode="border", align_corners=False)[0]
    return values, inside


def _rays(cameras: Cameras, view: int, h: int, w: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(camera centre [3], world directions [h*w, 3] with unit depth) of the pixel centres of ``view``."""
    v, u = torch.meshgrid(torch.arange(h) + 0.5, torch.arange(w) + 0.5, indexing="ij")
    d = torch.stack(
        [(u - cameras.cx[view]) / cameras.fx[view], (v - cameras.cy[view]) / cameras.fy[view], torch.ones_like(u)], -1
    )
    c2w = cameras.camera_to_worlds[view]
    return c2w[:3, 3], d.reshape(-1, 3) @ c2w[:3, :3].T


def depth_range(cameras: Cameras) -> tuple[float, float]:
    """(near, far) depths the sweep tries: a fifth to five times the median distance of the cameras to the point
    their optical axes meet (`look_at_point`)."""
    d = float((cameras.centers - look_at_point(cameras)).norm(dim=1).median())
    return 0.2 * d, 5.0 * d


def plane_sweep_depths(
    images: list[torch.Tensor],
    cameras: Cameras,
    max_side: int = 160,
    planes: int = 64,
    neighbours: int = 4,
    window: int = 7,
    min_zncc: float = 0.5,
    max_angle_deg: float = 45.0,
) -> tuple[list[torch.Tensor], Cameras, list[list[int]]]:
    """Per view, a depth map at a longer side of ``max_side`` (0 where no depth scores ``min_zncc`` with the best
    half of its ``neighbours``). ``images``: one [H, W, 3] per camera. -> (depth maps [h, w], the cameras at that
    size, each view's neighbours)."""
    small = [_small(im.cpu(), max_side) for im in images]
    cams = Cameras.cat([cameras[i].to("cpu").resized(x.shape[2], x.shape[1]) for i, x in enumerate(small)])
    grey = [x.mean(0, keepdim=True) for x in small]
    near, far = depth_range(cams)
    inv = torch.linspace(1.0 / near, 1.0 / far, planes)
    nbrs = _neighbours(cams, neighbours, max_angle_deg)
    depths = []
    for r, (img, nb) in enumerate(zip(grey, nbrs)):
        h, w = img.shape[1:]
        if len(nb) < 2:
            depths.append(torch.zeros(h, w))
            continue
        origin, dirs = _rays(cams, r, h, w)
        points = origin + (1.0 / inv)[:, None, None] * dirs[None]  # [D, h*w, 3]
        scores = []
        for n in nb:
            uv, z = _project(points, cams, n)
            values, inside = _sample(grey[n], uv)
            valid = (inside & (z > 1e-6)).reshape(planes, 1, h, w)
            scores.append(_zncc(img[None], values.reshape(planes, 1, h, w), valid, window))
        best_half = torch.stack(scores).topk(max(1, len(nb) // 2), dim=0).values.mean(0)  # [D, h, w]
        score, k = best_half.max(0)
        # sub-plane refinement: the parabola through the best plane and its two neighbours, in inverse depth
        km, kp = (k - 1).clamp(0, planes - 1), (k + 1).clamp(0, planes - 1)
        c0, cm, cp = score, best_half.gather(0, km[None])[0], best_half.gather(0, kp[None])[0]
        curv = cm - 2 * c0 + cp
        shift = torch.where((curv < -1e-6) & (k > 0) & (k < planes - 1), 0.5 * (cm - cp) / curv, 0.0).clamp(-0.5, 0.5)
        step = inv[1] - inv[0]
        depth = 1.0 / (inv[k] + shift * step)
        depths.append(torch.where((score >= min_zncc) & (k > 0) & (k < planes - 1), depth, 0.0))
    return depths, cams, nbrs


def plane_sweep_points(
    images: list[torch.Tensor],
    cameras: Cameras,
    max_points: int = 50_000,
    max_side: int = 160,
    max_relative_error: float = 0.02,
    agreeing: float = 0.75,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """Points of `plane_sweep_depths` that the depth maps of at least a share ``agreeing`` of a view's neighbours
    (and two) confirm (to ``max_relative_error`` of the depth), each coloured by the median over its view and those
    that confirm it, at most ``max_points`` of them (a seeded random subset). ``images``: one [H, W, 3] in [0, 1]
    per camera. -> ([P, 3] float32 points, [P, 3] float32 colours)."""
    colour = [_small(im.cpu(), max_side) for im in images]  # [3, h, w]; the sweep below finds them small already
    depths, cams, nbrs = plane_sweep_depths([c.permute(1, 2, 0) for c in colour], cameras, max_side=max_side)
    all_points, all_colours = [], []
    for r, (depth, nb) in enumerate(zip(depths, nbrs)):
        h, w = depth.shape
        keep = depth.reshape(-1) > 0
        if not keep.any():
            continue
        origin, dirs = _rays(cams, r, h, w)
        points = origin + depth.reshape(-1)[keep, None] * dirs[keep]  # [P, 3]
        seen = []
        agree = torch.zeros(len(points), dtype=torch.int64)
        for n in nb:
            uv, z = _project(points[None], cams, n)
            theirs, inside = _sample(depths[n][None], uv, mode="nearest")
            ok = inside[0] & (theirs[0, 0] > 0) & ((theirs[0, 0] - z[0]).abs() <= max_relative_error * z[0])
            agree += ok.long()
            seen.append(torch.where(ok, _sample(colour[n], uv)[0][:, 0], float("nan")))
        seen.append(colour[r].reshape(3, -1)[:, keep])
        good = agree >= max(2, math.ceil(agreeing * len(nb)))
        all_points.append(points[good])
        all_colours.append(torch.stack(seen).nanmedian(0).values[:, good].T)
    if not all_points:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32)
    points, colours = torch.cat(all_points), torch.cat(all_colours).clamp(0, 1)
    if len(points) > max_points:
        pick = np.sort(np.random.default_rng(seed).choice(len(points), max_points, replace=False))
        points, colours = points[pick], colours[pick]
    return points.numpy().astype(np.float32), colours.numpy().astype(np.float32)


COVERAGE_CELLS = 32
"""Cells along a view's longer side in `view_coverage` (the sweep's own scale: 160 px in cells of 5 px)."""


def view_coverage(points: np.ndarray, cameras: Cameras, cells: int = COVERAGE_CELLS) -> float:
    """Mean over the views of ``cameras`` of the share of cells (``cells`` along the longer side) that hold at least
    one of ``points`` [P, 3] in front of the camera: how much of each view a start from those points leaves empty.
    -> float in [0, 1]."""
    pts = torch.as_tensor(points, dtype=torch.float32).cpu()
    cameras = cameras.to("cpu")  # the training device's cameras (CUDA) beside points read from a file
    shares = []
    for view in range(len(cameras)):
        w, h = int(cameras.width[view]), int(cameras.height[view])
        uv, z = _project(pts, cameras, view)
        size = max(w, h) / cells
        cw, ch = math.ceil(w / size), math.ceil(h / size)
        inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        u, v = (uv[inside] / size).floor().long().unbind(-1)
        shares.append(len(torch.unique(v * cw + u)) / (cw * ch))
    return float(np.mean(shares)) if shares else 0.0


SWEEP_VERSION = "plane-sweep-1"
"""Part of the cache key: a change to the sweep that changes its points changes this."""


def sweep_known_poses(
    images: list[torch.Tensor],
    image_paths: list[Path],
    cameras: Cameras,
    cache_dir: Path | None,
    max_points: int = 50_000,
    seed: int = 0,
) -> TriangulatedPoints:
    """`plane_sweep_points` of ``images`` (one [H, W, 3] per camera, read from ``image_paths``), cached in
    ``cache_dir`` like `triangulate_known_poses` (None: no cache). Raises ``RuntimeError`` when fewer than
    `MIN_POINTS` points are found."""
    cache = None
    found = None
    if cache_dir is not None:
        key = cache_key(image_paths, cameras, SWEEP_VERSION, f"{max_points}|{seed}")
        cache = Path(cache_dir) / f"sweep-{key}.npz"
        if cache.is_file():
            found = load_points(cache)
    if found is None:
        points, colours = plane_sweep_points(images, cameras, max_points=max_points, seed=seed)
        found = TriangulatedPoints(points, colours, len(images), float("nan"))
        if cache is not None:
            found.cache = save_points(cache, found)
    if len(found.points) < MIN_POINTS:
        raise RuntimeError(f"the plane sweep found {len(found.points)} points in {found.num_views} views")
    return found
