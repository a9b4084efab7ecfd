"""Colours of a scene's points from the photos that see them: a degraded copy must not keep the clean photos' colours.

SfM points carry the colour of the photos they were matched in. A copy of a scene with weather added keeps its
points (their positions are the capture's), but the colours are re-read from the degraded photos, so that a method
trained "blind" on the copy starts from what its photos show, as it would on a real rainy or foggy capture.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from metegs.cameras import Cameras

UNSEEN_COLOUR = 0.5
"""Colour of a point no photo sees (mid grey: nothing of the clean photos)."""


def colours_seen(
    points: np.ndarray,
    cameras: Cameras,
    images: Sequence[np.ndarray],
    depths: Sequence[np.ndarray] | None = None,
    tolerance: float = 0.05,
    transmittance: Callable[[int], np.ndarray] | None = None,
    airlight: np.ndarray | None = None,
    shrink: float = 0.1,
) -> np.ndarray:
    """Colour of each point from the views that see it: in the image, in front of the camera and, with ``depths``,
    not behind the surface a view sees there (z at most (1 + ``tolerance``) times the pixel's depth).

    Without a medium, the mean of what those views show. With ``transmittance`` (view index i -> [P] fraction t of
    each point's light that reaches camera i through a medium) and its ``airlight`` A [3], each view shows
    t·c + (1 − t)·A, and c is the least-squares fit over the views, shrunk towards their mean by ``shrink`` (per view)
    where the medium hides the point (Σ t² small): c = (Σ t·(o − (1 − t)·A) + shrink·n·ō) / (Σ t² + shrink·n),
    so a near view counts for more than a far one and nothing is divided by a vanishing t.

    points [P, 3] world; cameras: one per image; images [H, W, 3] in [0, 1] (any size: the camera's intrinsics are
    scaled); depths [H, W] z-depth (scene units, non-finite where unknown: no test there) -> [P, 3] float32 in
    [0, 1], mid grey (`UNSEEN_COLOUR`) where no view sees the point."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    medium = transmittance is not None
    a = np.zeros(3) if airlight is None else np.asarray(airlight, dtype=np.float64).reshape(3)
    total, fitted, weight = np.zeros((len(pts), 3)), np.zeros((len(pts), 3)), np.zeros((len(pts), 1))
    count = np.zeros(len(pts))
    w2c = cameras.world_to_cameras().double().cpu().numpy()
    for i, image in enumerate(images):
        image = np.asarray(image, dtype=np.float32)
        h, w = image.shape[:2]
        sx, sy = w / float(cameras.width[i]), h / float(cameras.height[i])
        cam = pts @ w2c[i, :3, :3].T + w2c[i, :3, 3]
        z = cam[:, 2]
        front = z > 1e-9
        safe = np.where(front, z, 1.0)
        u = (float(cameras.fx[i]) * cam[:, 0] / safe + float(cameras.cx[i])) * sx
        v = (float(cameras.fy[i]) * cam[:, 1] / safe + float(cameras.cy[i])) * sy
        seen = front & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        col = np.clip(u, 0, w - 1).astype(np.int64)
        row = np.clip(v, 0, h - 1).astype(np.int64)
        if depths is not None:
            surface = np.asarray(depths[i], dtype=np.float64)
            at = surface[np.clip((row / sy).astype(np.int64), 0, surface.shape[0] - 1),
                         np.clip((col / sx).astype(np.int64), 0, surface.shape[1] - 1)]  # fmt: skip
            known = np.isfinite(at) & (at > 0)
            seen &= ~known | (z <= at * (1.0 + tolerance))
        shown = image[row[seen], col[seen], :3].astype(np.float64)
        total[seen] += shown
        count[seen] += 1
        if medium:
            t = np.clip(np.asarray(transmittance(i), dtype=np.float64).reshape(-1)[seen, None], 0.0, 1.0)
            fitted[seen] += t * (shown - (1.0 - t) * a)
            weight[seen] += t * t
    out = np.full((len(pts), 3), UNSEEN_COLOUR, np.float32)
    hit = count > 0
    mean = total[hit] / count[hit, None]
    if medium:
        prior = shrink * count[hit, None]
        mean = np.clip((fitted[hit] + prior * mean) / np.maximum(weight[hit] + prior, 1e-12), 0.0, 1.0)
    out[hit] = mean.astype(np.float32)
    return out


def recolour_colmap_model(model_dir: Path, image_path: Callable[[str], Path | None]) -> int:
    """Set the colour of every 3D point of the COLMAP model in ``model_dir`` to the mean of its track's pixels in
    the photos that ``image_path`` maps the model's image names to (None or no such file: that photo is left out),
    and write the model back in its own format (binary or text) -> the number of points that got a colour from
    them (the rest turn mid grey)."""
    import pycolmap

    from metegs.data.images import load_image

    model = pycolmap.Reconstruction(str(model_dir))
    total: dict[int, np.ndarray] = {}
    count: dict[int, int] = {}
    for image in model.images.values():
        path = image_path(image.name)
        if path is None or not Path(path).is_file():
            continue
        pixels = load_image(path).astype(np.float64) * 255.0
        camera = model.cameras[image.camera_id]
        sx, sy = pixels.shape[1] / camera.width, pixels.shape[0] / camera.height
        for p in image.points2D:
            if not p.has_point3D():
                continue
            col = min(max(int(p.xy[0] * sx), 0), pixels.shape[1] - 1)
            row = min(max(int(p.xy[1] * sy), 0), pixels.shape[0] - 1)
            total[p.point3D_id] = total.get(p.point3D_id, 0.0) + pixels[row, col]
            count[p.point3D_id] = count.get(p.point3D_id, 0) + 1
    grey = np.full(3, round(UNSEEN_COLOUR * 255), np.uint8)
    for point_id, point in model.points3D.items():
        n = count.get(point_id, 0)
        point.color = grey if n == 0 else np.clip(total[point_id] / n + 0.5, 0, 255).astype(np.uint8)
    if (Path(model_dir) / "points3D.bin").exists():
        model.write_binary(str(model_dir))
    else:
        model.write_text(str(model_dir))
    return len(count)
