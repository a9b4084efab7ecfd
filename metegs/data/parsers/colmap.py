"""COLMAP sparse models (binary or text) read through pycolmap.

Layouts recognised: ``<scene>/sparse/0/cameras.{bin,txt}`` (several models ``sparse/0``, ``sparse/1``...:
the one with most registered images is used), ``<scene>/sparse/cameras.*`` and ``<scene>/cameras.*``.
Images are read from ``<scene>/images/`` by the image name stored in the model. The model's files are checked
by `metegs.data.parsers.colmap_files.check_model` before pycolmap reads them (a truncated or corrupt file is
named with its record and field, and never makes pycolmap allocate more than the file's size).

Camera models: PINHOLE and SIMPLE_PINHOLE are used directly. SIMPLE_RADIAL, RADIAL, OPENCV and
FULL_OPENCV are undistorted when ``--dataset.undistort`` is on (the default): each image is remapped
once with OpenCV to a pinhole camera of the same size without black borders and cached
(`metegs.data.undistort`: in ``<scene>/.metegs_undistorted/``, or the user's cache when the scene is read-only);
the scene then points at the cached files. Fisheye and other models are refused with a DataError naming the model.
Clean references (as `metegs-synth` writes them) come from ``<scene>/images_clean/`` for views that were
not undistorted.
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np

from metegs.cameras import Cameras, to_homogeneous
from metegs.data.config import DatasetConfig
from metegs.data.exif import exposure_times_s
from metegs.data.parsers.clean import find_clean_paths
from metegs.data.parsers.colmap_files import check_model, model_file
from metegs.data.parsers.masks import mask_paths
from metegs.data.scene import SceneData, split_every_nth
from metegs.data.undistort import Distortion, cache_folder, undistorted_copy
from metegs.errors import DataError

_PINHOLE = ("SIMPLE_PINHOLE", "PINHOLE")
_DISTORTED = ("SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV")
_N_INTRINSICS = {"SIMPLE_PINHOLE": 3, "PINHOLE": 4, "SIMPLE_RADIAL": 3, "RADIAL": 3, "OPENCV": 4, "FULL_OPENCV": 4}
"""Number of leading (f, cx, cy) or (fx, fy, cx, cy) parameters of each supported model."""


def _has_model(folder: Path) -> bool:
    return any((folder / f"cameras.{ext}").is_file() for ext in ("bin", "txt"))


def find_model_folders(path: Path) -> list[Path]:
    """Candidate model folders of a scene, in the order sparse/N (numeric), sparse/, the scene folder."""
    sparse = path / "sparse"
    numbered = []
    if sparse.is_dir():
        numbered = [p for p in sparse.iterdir() if p.is_dir() and _has_model(p)]
        numbered.sort(key=lambda p: (0, int(p.name)) if p.name.isdigit() else (1, p.name))
    others = [p for p in (sparse, path) if _has_model(p)]
    return numbered + others


def up_from_cameras(c2w: np.ndarray) -> np.ndarray:
    """World up estimated from ``[N, 4, 4]`` OpenCV camera-to-worlds: minus the mean camera y axis, normalised."""
    up = -np.asarray(c2w, dtype=np.float64)[:, :3, 1].mean(axis=0)
    norm = np.linalg.norm(up)
    if not np.isfinite(norm) or norm < 1e-8:
        return np.array([0.0, 0.0, 1.0], dtype=np.float32)
    return (up / norm).astype(np.float32)


@dataclass
class _Pinhole:
    """Pinhole intrinsics of one view, COLMAP pixel convention (pixel centres at +0.5)."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int


def _pinhole_part(model: str, params: np.ndarray, width: int, height: int) -> _Pinhole:
    """The pinhole part of a model's parameters (distortion ignored); a placeholder for unsupported models."""
    n = _N_INTRINSICS.get(model)
    if n == 3:
        return _Pinhole(params[0], params[0], params[1], params[2], width, height)
    if n == 4:
        return _Pinhole(params[0], params[1], params[2], params[3], width, height)
    return _Pinhole(1.0, 1.0, width / 2, height / 2, width, height)


def _read_model(folder: Path):
    """pycolmap's reconstruction of ``folder``, once `check_model` has found its files well-formed."""
    import pycolmap

    check_model(folder)
    try:
        return pycolmap.Reconstruction(str(folder))
    except Exception as exc:  # pycolmap raises plain RuntimeError/ValueError on malformed models
        raise DataError(folder, f"cannot read the COLMAP model: {exc}") from exc


def _registered(im) -> bool:
    """Whether a pycolmap image has a pose (``has_pose`` in pycolmap 4, ``registered`` in 3.x)."""
    flag = getattr(im, "has_pose", None)
    if flag is None:
        flag = getattr(im, "registered", True)
    return bool(flag() if callable(flag) else flag)


def _cam_from_world(im) -> np.ndarray:
    """[3, 4] float64 world-to-camera of a pycolmap image (a method in pycolmap 4, a property in 3.x)."""
    pose = im.cam_from_world
    pose = pose() if callable(pose) else pose
    return np.asarray(pose.matrix(), dtype=np.float64)


def _distortion(model: str, params: np.ndarray) -> Distortion:
    """The distorted camera of COLMAP ``model`` and ``params`` (COLMAP pixel convention)."""
    if model in ("SIMPLE_RADIAL", "RADIAL"):
        f, cx, cy = params[:3]
        k = [*params[3:], 0.0, 0.0]
        return Distortion(f, f, cx, cy, (k[0], k[1], 0.0, 0.0))
    # OPENCV: fx fy cx cy k1 k2 p1 p2; FULL_OPENCV adds k3 k4 k5 k6 (OpenCV rational model)
    return Distortion(*(float(v) for v in params[:4]), tuple(float(v) for v in params[4:]))


class ColmapParser:
    """COLMAP ``sparse/`` model + ``images/`` folder -> SceneData (see the module docstring)."""

    priority: ClassVar[int] = 10

    @staticmethod
    def can_parse(path: Path) -> bool:
        path = Path(path)
        return path.is_dir() and bool(find_model_folders(path))

    def parse(self, path: Path | None, options: DatasetConfig) -> SceneData:
        if path is None:
            raise DataError(None, "the COLMAP parser needs a scene folder")
        path = Path(path)
        folder, rec = self._best_model(path)
        image_dir = path / "images"
        if not image_dir.is_dir():
            raise DataError(image_dir, "image folder does not exist (COLMAP images are read from <scene>/images/)")
        images = sorted((im for im in rec.images.values() if _registered(im)), key=lambda im: im.name)
        if not images:
            raise DataError(folder, "the COLMAP model has no registered images")
        images = self._existing(images, image_dir)
        c2w, intr, paths, lenses = [], [], [], []
        for im in images:
            pin, file, lens = self._view(im, image_dir, path, folder, options)
            w2c = to_homogeneous_np(_cam_from_world(im))
            c2w.append(np.linalg.inv(w2c))
            intr.append(pin)
            paths.append(file)
            lenses.append(lens)
        masks = mask_paths(path, [image_dir / im.name for im in images], image_dir)
        if masks is not None:  # undistorted with their view
            masks = [
                m if lens is None else undistorted_copy(m, cache_folder(path), os.path.join("masks", im.name), lens)
                for m, lens, im in zip(masks, lenses, images)
            ]
        cams = Cameras.create(
            np.stack(c2w).astype(np.float32),
            [p.fx for p in intr],
            [p.fy for p in intr],
            [p.cx for p in intr],
            [p.cy for p in intr],
            [p.width for p in intr],
            [p.height for p in intr],
            exposure_time_s=exposure_times_s([image_dir / im.name for im in images]),  # EXIF of the originals
        )
        points, colors = self._points(rec, folder)
        train, test = split_every_nth(len(images), options.test_every)
        return SceneData(
            cameras=cams,
            names=[im.name for im in images],
            image_paths=paths,
            clean_image_paths=find_clean_paths(path, paths)
            if all(p.is_relative_to(image_dir) for p in paths)
            else None,
            train_indices=train,
            test_indices=test,
            mask_paths=masks,
            points=points,
            point_colors=colors,
            up=up_from_cameras(np.stack(c2w)),
            metric_scale=None,
            source=path,
        )

    @staticmethod
    def _best_model(path: Path):
        """(folder, reconstruction) of the model with most registered images."""
        folders = find_model_folders(path)
        if not folders:
            raise DataError(path, "no COLMAP model found (expected sparse/0/cameras.bin or cameras.txt)")
        best = None
        for folder in folders:
            rec = _read_model(folder)
            count = sum(1 for im in rec.images.values() if _registered(im))
            if best is None or count > best[2]:
                best = (folder, rec, count)
        return best[0], best[1]

    @staticmethod
    def _existing(images: list, image_dir: Path) -> list:
        """Registered images whose file exists; one warning lists the missing ones."""
        missing = [im.name for im in images if not (image_dir / im.name).is_file()]
        if len(missing) == len(images):
            raise DataError(image_dir, f"no images found in {image_dir} (none of the {len(images)} model images exist)")
        if missing:
            shown = ", ".join(missing[:10]) + (f" and {len(missing) - 10} more" if len(missing) > 10 else "")
            warnings.warn(
                f"{image_dir}: skipping {len(missing)} registered image(s) without a file: {shown}", stacklevel=3
            )
        skip = set(missing)
        return [im for im in images if im.name not in skip]

    @staticmethod
    def _view(
        im, image_dir: Path, scene: Path, model_folder: Path, options: DatasetConfig
    ) -> tuple[_Pinhole, Path, Distortion | None]:
        """Pinhole intrinsics, image file (undistorted into the cache if needed) and lens distortion (None: none) of
        one view."""
        cam = im.camera
        model = cam.model.name
        params = np.asarray(cam.params, dtype=np.float64)
        w, h = int(cam.width), int(cam.height)
        src = image_dir / im.name
        pin = _pinhole_part(model, params, w, h)
        if model in _PINHOLE:
            return pin, src, None
        cameras_file = model_file(model_folder, "cameras")
        if model not in _DISTORTED:
            raise DataError(
                cameras_file,
                f"camera {cam.camera_id} uses the unsupported camera model {model}; supported: "
                f"{', '.join(_PINHOLE + _DISTORTED)} (undistort with COLMAP image_undistorter first)",
            )
        if np.all(params[_N_INTRINSICS[model] :] == 0.0):
            return pin, src, None
        if not options.undistort:
            raise DataError(
                cameras_file,
                f"camera {cam.camera_id}: camera model {model} is distorted; rerun with --dataset.undistort "
                "or undistort with COLMAP image_undistorter",
            )
        camera = _distortion(model, params)
        copy = undistorted_copy(src, cache_folder(scene), im.name, camera)
        return _Pinhole(*camera.pinhole(w, h), w, h), copy, camera

    @staticmethod
    def _points(rec, folder: Path) -> tuple[np.ndarray | None, np.ndarray | None]:
        """[P, 3] float32 xyz and [P, 3] float32 colours in [0, 1] of the model's 3D points (None if none)."""
        pts = list(rec.points3D.values())
        if not pts:
            return None, None
        xyz = np.array([p.xyz for p in pts], dtype=np.float32).reshape(-1, 3)
        bad = int((~np.isfinite(xyz).all(axis=1)).sum())
        if bad:
            raise DataError(
                model_file(folder, "points3D"), f"{bad} of {len(pts)} points have a non-finite position (X, Y, Z)"
            )
        rgb = np.array([p.color for p in pts], dtype=np.float32).reshape(-1, 3) / 255.0
        return xyz, rgb


def to_homogeneous_np(m: np.ndarray) -> np.ndarray:
    """[..., 3, 4] numpy -> [..., 4, 4] (through `metegs.cameras.to_homogeneous`)."""
    import torch

    return to_homogeneous(torch.from_numpy(np.ascontiguousarray(m, dtype=np.float64))).numpy()
