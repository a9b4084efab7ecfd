"""Camera paths to render a scene as a video: through the captured views, a spiral, or a nerfstudio file.

``interpolate`` passes through every given camera in order (positions on a Catmull-Rom curve, rotations by
spherical interpolation); ``spiral`` circles in front of the mean camera while looking at the point the views
look at; ``read_camera_path`` reads nerfstudio's ``camera_path.json`` (``camera_to_world`` as 16 numbers,
row-major, OpenGL axes; ``fov`` vertical in degrees; ``render_width`` / ``render_height``).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch
from scipy.spatial.transform import Rotation, Slerp

from metegs.cameras import Cameras, opengl_to_opencv
from metegs.errors import DataError

KINDS = ("interpolate", "spiral")
"""Built-in paths; anything else is read as a camera-path file."""


def _like(cameras: Cameras, c2w: np.ndarray) -> Cameras:
    """Cameras with the poses ``c2w`` [N, 4, 4] and the intrinsics and size of ``cameras``' first view."""
    return Cameras.create(
        c2w.astype(np.float32),
        float(cameras.fx[0]), float(cameras.fy[0]), float(cameras.cx[0]), float(cameras.cy[0]),
        int(cameras.width[0]), int(cameras.height[0]),
    )  # fmt: skip


def interpolate(cameras: Cameras, frames: int) -> Cameras:
    """``frames`` views through every camera of ``cameras`` in order, the first and last included."""
    c2w = cameras.camera_to_worlds.double().cpu().numpy()
    n = len(c2w)
    if n < 2:
        return _like(cameras, np.repeat(c2w, max(frames, 1), axis=0))
    t = np.linspace(0.0, n - 1.0, max(frames, 2))
    rotations = Slerp(np.arange(n), Rotation.from_matrix(c2w[:, :3, :3]))(t).as_matrix()
    p = c2w[:, :3, 3]
    padded = np.concatenate([2 * p[:1] - p[1:2], p, 2 * p[-1:] - p[-2:-1]])
    i = np.minimum(np.floor(t).astype(int), n - 2)
    s = (t - i)[:, None]
    p0, p1, p2, p3 = padded[i], padded[i + 1], padded[i + 2], padded[i + 3]
    centres = 0.5 * (
        2 * p1 + (p2 - p0) * s + (2 * p0 - 5 * p1 + 4 * p2 - p3) * s**2 + (3 * p1 - p0 - 3 * p2 + p3) * s**3
    )  # Catmull-Rom: through every keyframe
    out = np.tile(np.eye(4), (len(t), 1, 1))
    out[:, :3, :3], out[:, :3, 3] = rotations, centres
    return _like(cameras, out)


def spiral(cameras: Cameras, frames: int, focus: torch.Tensor, rotations: float = 2.0) -> Cameras:
    """``frames`` views on a spiral around the mean camera, all looking at ``focus`` [3]."""
    c2w = cameras.camera_to_worlds.double().cpu().numpy()
    centre = c2w[:, :3, 3].mean(0)
    right = c2w[:, :3, 0].mean(0)
    right /= max(np.linalg.norm(right), 1e-12)
    down = c2w[:, :3, 1].mean(0)
    down -= (down @ right) * right
    down /= max(np.linalg.norm(down), 1e-12)
    target = focus.double().cpu().numpy()
    radius = 0.25 * max(float(np.linalg.norm(c2w[:, :3, 3] - centre, axis=1).mean()), 1e-3)
    out = np.tile(np.eye(4), (max(frames, 1), 1, 1))
    for k, a in enumerate(np.linspace(0.0, 2 * math.pi * rotations, max(frames, 1), endpoint=False)):
        eye = centre + radius * (math.cos(a) * right + math.sin(a) * down)
        forward = target - eye
        forward /= max(np.linalg.norm(forward), 1e-12)
        x = np.cross(down, forward)  # keep the views' own "down" as the image's down
        x /= max(np.linalg.norm(x), 1e-12)
        out[k, :3, :3] = np.stack([x, np.cross(forward, x), forward], axis=1)
        out[k, :3, 3] = eye
    return _like(cameras, out)


def read_camera_path(path: Path) -> tuple[Cameras, float]:
    """nerfstudio ``camera_path.json`` -> (cameras, frames per second); DataError naming the field when malformed."""
    path = Path(path)
    try:
        meta = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise DataError(path, f"cannot read the camera path: {exc}") from exc
    keys = meta.get("camera_path") if isinstance(meta, dict) else None
    if not isinstance(keys, list) or not keys:
        raise DataError(path, "expected a JSON object with a non-empty 'camera_path' list")
    try:
        width, height = int(meta["render_width"]), int(meta["render_height"])
    except (KeyError, TypeError, ValueError) as exc:
        raise DataError(path, "'render_width' and 'render_height' must be whole numbers") from exc
    if width < 1 or height < 1:
        raise DataError(path, f"render size {width}x{height} must be positive")
    c2w, focal = [], []
    for i, key in enumerate(keys):
        try:
            m = np.asarray(key["camera_to_world"], dtype=np.float64).reshape(4, 4)
            fov = float(key.get("fov", meta.get("default_fov", 50.0)))
        except (KeyError, TypeError, ValueError) as exc:
            raise DataError(path, f"camera_path[{i}]: 'camera_to_world' must be 16 numbers") from exc
        if not np.isfinite(m).all() or not 0.0 < fov < 180.0:
            raise DataError(path, f"camera_path[{i}]: a finite pose and a fov in (0, 180) degrees are needed")
        c2w.append(m)
        focal.append(0.5 * height / math.tan(math.radians(fov) / 2))
    fps = float(meta.get("fps", 0) or 0) or (len(keys) / float(meta["seconds"]) if meta.get("seconds") else 24.0)
    poses = opengl_to_opencv(torch.as_tensor(np.stack(c2w), dtype=torch.float32))
    cams = Cameras.create(poses, focal, focal, width / 2, height / 2, width, height)
    return cams, fps
