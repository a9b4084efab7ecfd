"""Distorted cameras (OpenCV radial-tangential or fisheye) to pinhole ones: intrinsics and undistorted images.

Each image is remapped once with OpenCV to a pinhole camera of the same size without black borders
(``cv2.getOptimalNewCameraMatrix`` with alpha 0; for fisheye ``cv2.fisheye.estimateNewCameraMatrixForUndistortRectify``
with balance 0) and cached as a 16-bit PNG named by the source file's size and time and the camera, in
``<scene>/.metegs_undistorted/``, or, when the scene folder cannot be written, in the user's cache
(``~/.cache/metegs/undistorted/<scene hash>/``). Intrinsics use the pixel convention of COLMAP and
nerfstudio (pixel centres at +0.5); OpenCV's (centres at integers) only inside this module.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from metegs.config import scene_cache
from metegs.data.images import load_image
from metegs.errors import DataError
from metegs.files import atomic_output

CACHE_DIR = ".metegs_undistorted"
"""Folder (inside the scene) holding undistorted copies of images with distorted camera models."""


@dataclass(frozen=True)
class Distortion:
    """One distorted camera: pinhole part (pixel centres at +0.5) and OpenCV coefficients."""

    fx: float
    fy: float
    cx: float
    cy: float
    coeffs: tuple[float, ...]
    """OpenCV order: k1 k2 p1 p2 [k3 [k4 k5 k6]] (radial-tangential) or k1 k2 k3 k4 (fisheye)."""
    fisheye: bool = False

    @property
    def distorted(self) -> bool:
        return any(c != 0.0 for c in self.coeffs)

    def _opencv_k(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx - 0.5], [0.0, self.fy, self.cy - 0.5], [0.0, 0.0, 1.0]])

    def pinhole(self, width: int, height: int) -> tuple[float, float, float, float]:
        """(fx, fy, cx, cy) of the undistorted view of size ``width`` x ``height`` (pixel centres at +0.5)."""
        k = self._new_k(width, height)
        return float(k[0, 0]), float(k[1, 1]), float(k[0, 2]) + 0.5, float(k[1, 2]) + 0.5

    def _new_k(self, width: int, height: int) -> np.ndarray:
        K, dist = self._opencv_k(), np.asarray(self.coeffs, dtype=np.float64)
        if self.fisheye:
            return cv2.fisheye.estimateNewCameraMatrixForUndistortRectify(
                K, dist[:4], (width, height), np.eye(3), balance=0.0
            )
        return cv2.getOptimalNewCameraMatrix(K, dist, (width, height), 0, (width, height))[0]

    def undistort(self, image: np.ndarray) -> np.ndarray:
        """[H, W, C] image -> the same size seen through the pinhole camera of `pinhole`."""
        h, w = image.shape[:2]
        K, dist, new_k = self._opencv_k(), np.asarray(self.coeffs, dtype=np.float64), self._new_k(w, h)
        if self.fisheye:
            return cv2.fisheye.undistortImage(image, K, dist[:4], Knew=new_k, new_size=(w, h))
        return cv2.undistort(image, K, dist, None, new_k)


def cache_folder(scene: Path) -> Path:
    """``<scene>/.metegs_undistorted`` when it can be written, else a folder of the user's cache for this scene."""
    return scene_cache(scene, CACHE_DIR, "undistorted")


def undistorted_copy(src: Path, cache: Path, name: str, camera: Distortion) -> Path:
    """The undistorted copy of image ``src`` in ``cache`` (made once; reused while the file and camera are unchanged)."""
    stat = src.stat()
    key = hashlib.sha1(f"{camera!r}|{stat.st_mtime_ns}|{stat.st_size}".encode()).hexdigest()[:10]
    dst = cache / f"{name}.{key}.png"
    if dst.is_file():
        return dst
    out = camera.undistort(load_image(src))
    bgr16 = np.round(np.clip(out[:, :, ::-1], 0.0, 1.0) * 65535.0).astype(np.uint16)
    try:
        dst.parent.mkdir(parents=True, exist_ok=True)
        with atomic_output(dst, ".png") as tmp:
            if not cv2.imwrite(str(tmp), bgr16):
                raise DataError(dst, "cannot write the undistorted image")
    except OSError as exc:
        raise DataError(cache, f"cannot write undistorted images: {exc}") from exc
    return dst
