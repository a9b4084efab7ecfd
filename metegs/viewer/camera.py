"""Cameras between the browser and metegs: viser's pose (OpenCV axes, like metegs) -> `Cameras`, render sizes,
training-camera frustums and a smooth camera path through the training views."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import torch
import viser.transforms as vtf

from metegs.cameras import Cameras
from metegs.video import to_uint8


@dataclass(frozen=True)
class ViewPose:
    """A browser camera: pose in world coordinates (OpenCV axes: x right, y down, z forward) and its lens."""

    wxyz: tuple[float, float, float, float]
    """Rotation camera -> world as a unit quaternion (w, x, y, z)."""
    position: tuple[float, float, float]
    """Camera centre in world coordinates."""
    fov_y: float
    """Vertical field of view, radians."""
    aspect: float
    """Width / height of the browser canvas."""

    def camera_to_world(self) -> np.ndarray:
        """[4, 4] float64 camera-to-world matrix."""
        c2w = np.eye(4)
        c2w[:3, :3] = vtf.SO3(np.asarray(self.wxyz, dtype=np.float64)).as_matrix()
        c2w[:3, 3] = self.position
        return c2w

    def cameras(self, height: int, device: torch.device | str = "cpu") -> Cameras:
        """One pinhole camera of this pose, ``height`` px tall (width from the aspect), square pixels."""
        height = max(1, int(height))
        width = max(1, int(round(height * self.aspect)))
        fy = 0.5 * height / math.tan(0.5 * self.fov_y)
        c2w = torch.as_tensor(self.camera_to_world(), dtype=torch.float32)[None]
        return Cameras.create(c2w, fy, fy, width / 2.0, height / 2.0, width, height).to(device)


def pose_of(cameras: Cameras, index: int, aspect: float | None = None) -> ViewPose:
    """The ViewPose of view ``index`` (its own aspect unless ``aspect`` is given)."""
    c2w = cameras.camera_to_worlds[index].double().cpu().numpy()
    w, h, fy = float(cameras.width[index]), float(cameras.height[index]), float(cameras.fy[index])
    wxyz = vtf.SO3.from_matrix(c2w[:3, :3]).wxyz
    return ViewPose(
        wxyz=tuple(float(v) for v in wxyz),
        position=tuple(float(v) for v in c2w[:3, 3]),
        fov_y=2.0 * math.atan(0.5 * h / fy),
        aspect=aspect if aspect is not None else w / h,
    )


def render_height(canvas_w: int, canvas_h: int, max_side: int, pixels: float | None = None) -> int:
    """Height of a render for a ``canvas_w`` x ``canvas_h`` canvas: the canvas, scaled down so its longer side is at
    most ``max_side`` and, when ``pixels`` is given, so that it has at most that many pixels (never below 16 px)."""
    canvas_w, canvas_h = max(1, int(canvas_w)), max(1, int(canvas_h))
    scale = min(1.0, max_side / max(canvas_w, canvas_h))
    if pixels is not None:
        scale = min(scale, math.sqrt(max(pixels, 1.0) / (canvas_w * canvas_h)))
    return max(16, int(round(canvas_h * scale)))


def look_at_point(pose: ViewPose, centre: np.ndarray) -> np.ndarray:
    """The point on the viewing axis of ``pose`` nearest to ``centre`` (at least a small distance ahead)."""
    c2w = pose.camera_to_world()
    forward, eye = c2w[:3, 2], c2w[:3, 3]
    distance = max(float((np.asarray(centre) - eye) @ forward), 1e-3 * (1.0 + float(np.linalg.norm(eye))))
    return eye + distance * forward


def start_pose(pose: ViewPose, centre: np.ndarray, back: float = 0.35) -> ViewPose:
    """``pose`` moved back along its viewing axis by ``back`` of its distance to ``centre`` (so that its own
    frustum is seen in front of the camera instead of around it)."""
    c2w = pose.camera_to_world()
    eye = c2w[:3, 3]
    distance = float(np.linalg.norm(look_at_point(pose, centre) - eye))
    return replace(pose, position=tuple(float(v) for v in eye - back * distance * c2w[:3, 2]))


def orbit_order(cameras: Cameras, up: np.ndarray) -> list[int]:
    """Views sorted by azimuth about ``up`` around the cameras' centroid (a path that goes round the scene)."""
    centres = cameras.camera_to_worlds[:, :3, 3].double().cpu().numpy()
    up = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    rel = centres - centres.mean(0)
    rel = rel - np.outer(rel @ up, up)
    a = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(up, a)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    return np.argsort(np.arctan2(rel @ e2, rel @ e1), kind="stable").tolist()


def interpolate_poses(poses: list[ViewPose], t: float, closed: bool = True) -> ViewPose:
    """The pose at ``t`` in [0, 1] along ``poses``: positions linear, rotations by slerp, lens linear."""
    if len(poses) == 1:
        return poses[0]
    segments = len(poses) if closed else len(poses) - 1
    x = min(max(t, 0.0), 1.0) * segments
    i = min(int(x), segments - 1)
    f = x - i
    a, b = poses[i], poses[(i + 1) % len(poses)]
    ra, rb = vtf.SO3(np.asarray(a.wxyz)), vtf.SO3(np.asarray(b.wxyz))
    r = ra @ vtf.SO3.exp(f * (ra.inverse() @ rb).log())
    lerp = lambda u, v: (1 - f) * np.asarray(u, dtype=np.float64) + f * np.asarray(v, dtype=np.float64)  # noqa: E731
    return ViewPose(
        wxyz=tuple(float(v) for v in r.wxyz),
        position=tuple(float(v) for v in lerp(a.position, b.position)),
        fov_y=float(lerp(a.fov_y, b.fov_y)),
        aspect=float(lerp(a.aspect, b.aspect)),
    )


def thumbnail(image: torch.Tensor, max_side: int) -> np.ndarray:
    """[H, W, 3] float image in [0, 1] -> uint8 thumbnail whose longer side is at most ``max_side``."""
    import cv2

    arr = to_uint8(image)
    h, w = arr.shape[:2]
    scale = min(1.0, max_side / max(h, w))
    if scale < 1.0:
        arr = cv2.resize(arr, (max(1, round(w * scale)), max(1, round(h * scale))), interpolation=cv2.INTER_AREA)
    return arr
