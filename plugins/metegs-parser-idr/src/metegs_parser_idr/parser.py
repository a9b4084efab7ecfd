"""IDR / NeuS scenes: ``cameras_sphere.npz`` (NeuS) or ``cameras.npz`` (IDR) next to ``image/`` (and ``mask/``).

The format of IDR (Yariv et al., NeurIPS 2020) and NeuS (Wang et al., NeurIPS 2021), in which DTU and
BlendedMVS scenes are commonly shared. For view i the ``.npz`` holds ``world_mat_i``, a 4×4 whose top
three rows are the projection P = K·[R | t] from world points to pixels (OpenCV axes: x right, y down,
z forward; defined up to a scale, sign included), and optionally ``scale_mat_i``, the similarity that maps
the unit sphere around the object to world coordinates. Views are the image files of ``image/`` in sorted
order, view i taking ``world_mat_i``.

The scene is returned in the normalised frame of ``scale_mat`` (the object inside the unit sphere), as
IDR and NeuS train: P·S is decomposed into intrinsics and pose (an RQ decomposition). Its scale in metres
is unknown (``metric_scale`` None: give ``--conditions.metres-per-unit`` for weather). Initial points are
drawn uniformly in the unit sphere (the format's region of interest; 4000, seeded), or left to metegs'
random initialisation without ``scale_mat``. Principal points are moved by +0.5 px: IDR and NeuS put pixel
centres at integer coordinates, metegs at +0.5. A skew under 1 % of the focal length is dropped; a larger
one, a non-finite matrix or a missing ``world_mat_i`` raise a DataError naming the file and the view.
Masks (``mask/``, white = keep) are used with ``--dataset.use-masks`` when there is one per image; clean
references follow metegs' convention (``image_clean/``).
"""

from __future__ import annotations

from pathlib import Path
from typing import ClassVar

import numpy as np
from metegs.cameras import Cameras
from metegs.data.config import DatasetConfig
from metegs.data.parsers.clean import find_clean_paths
from metegs.data.scene import SceneData, split_every_nth
from metegs.errors import DataError

CAMERA_FILES = ("cameras_sphere.npz", "cameras.npz")
"""Camera files looked for, in this order (NeuS, IDR)."""
IMAGE_FOLDERS = ("image", "images")
"""Image folders looked for, in this order."""
MASK_FOLDERS = ("mask", "masks")
"""Mask folders looked for, in this order."""
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
PIXEL_CENTRE_OFFSET = 0.5
"""metegs' principal point minus IDR's: IDR/NeuS pixel centres are at integers, metegs' at +0.5."""
MAX_RELATIVE_SKEW = 0.01
"""Largest |skew| / fx that is dropped silently."""
NUM_INIT_POINTS = 4000
"""Points drawn in the unit sphere for initialisation when the file has ``scale_mat``s."""


def decompose_projection(P: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """P [3, 4] (any scale and sign) -> (K [3, 3] with K[2, 2] = 1 and a positive diagonal, R [3, 3] world-to-camera
    rotation, t [3]) such that P ∝ K·[R | t]."""
    P = np.asarray(P, dtype=np.float64)
    if np.linalg.det(P[:, :3]) < 0:  # the sign that makes R a rotation (det +1) with a positive-diagonal K
        P = -P
    M = P[:, :3]
    J = np.eye(3)[::-1]
    Q, U = np.linalg.qr((J @ M).T)  # (J M)ᵀ = Q U  ->  M = (J Uᵀ J)(J Qᵀ): upper triangular × orthogonal
    K = J @ U.T @ J
    R = J @ Q.T
    signs = np.sign(np.diag(K))
    signs[signs == 0] = 1.0
    D = np.diag(signs)
    K, R = K @ D, D @ R
    t = np.linalg.solve(K, P[:, 3])
    return K / K[2, 2], R, t


def projection_matrix(K: np.ndarray, c2w: np.ndarray) -> np.ndarray:
    """The 4×4 ``world_mat`` of a pinhole camera: K [3, 3] (IDR pixel convention) and camera-to-world [4, 4]."""
    w2c = np.linalg.inv(np.asarray(c2w, dtype=np.float64))
    out = np.eye(4)
    out[:3, :4] = np.asarray(K, dtype=np.float64) @ w2c[:3, :4]
    return out


def write_cameras_npz(path: Path, cameras: Cameras, scale_mat: np.ndarray | None = None) -> None:
    """Write metegs cameras as an IDR/NeuS camera file (``world_mat_i`` and, if given, ``scale_mat_i`` [4, 4] for
    every view). ``cameras`` are in world coordinates; readers see them in the frame of ``scale_mat``."""
    arrays = {}
    for i in range(len(cameras)):
        K = np.array(
            [
                [float(cameras.fx[i]), 0.0, float(cameras.cx[i]) - PIXEL_CENTRE_OFFSET],
                [0.0, float(cameras.fy[i]), float(cameras.cy[i]) - PIXEL_CENTRE_OFFSET],
                [0.0, 0.0, 1.0],
            ]
        )
        arrays[f"world_mat_{i}"] = projection_matrix(K, cameras.camera_to_worlds[i].double().numpy())
        if scale_mat is not None:
            arrays[f"scale_mat_{i}"] = np.asarray(scale_mat, dtype=np.float64)
    np.savez(path, **arrays)


def _first(folder: Path, names: tuple[str, ...], want_dir: bool) -> Path | None:
    for name in names:
        p = folder / name
        if p.is_dir() if want_dir else p.is_file():
            return p
    return None


def _image_files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)


def _up_from_cameras(c2w: np.ndarray) -> np.ndarray:
    """World up: minus the mean camera y axis (OpenCV: y points down in the image), normalised."""
    up = -c2w[:, :3, 1].mean(axis=0)
    norm = np.linalg.norm(up)
    return (up / norm).astype(np.float32) if np.isfinite(norm) and norm > 1e-8 else np.array([0, 0, 1], np.float32)


class IdrParser:
    """IDR / NeuS scene folder -> SceneData (see the module docstring)."""

    priority: ClassVar[int] = 40

    @staticmethod
    def can_parse(path: Path) -> bool:
        path = Path(path)
        return (
            path.is_dir()
            and _first(path, CAMERA_FILES, want_dir=False) is not None
            and _first(path, IMAGE_FOLDERS, want_dir=True) is not None
        )

    def parse(self, path: Path | None, options: DatasetConfig) -> SceneData:
        if path is None:
            raise DataError(None, "the idr parser needs a scene folder")
        path = Path(path)
        camera_file = _first(path, CAMERA_FILES, want_dir=False)
        image_dir = _first(path, IMAGE_FOLDERS, want_dir=True)
        if camera_file is None or image_dir is None:
            raise DataError(
                path, f"expected {' or '.join(CAMERA_FILES)} and an image folder ({', '.join(IMAGE_FOLDERS)}/)"
            )
        images = _image_files(image_dir)
        if not images:
            raise DataError(image_dir, f"no images ({', '.join(IMAGE_SUFFIXES)}) in the folder")
        try:
            with np.load(camera_file, allow_pickle=False) as npz:
                mats = {k: np.asarray(npz[k], dtype=np.float64) for k in npz.files}
        except (OSError, ValueError) as exc:
            raise DataError(camera_file, f"cannot read the camera file: {exc}") from exc
        c2ws, intrinsics, scaled = [], [], []
        for i in range(len(images)):
            K, c2w, has_scale = self._view(mats, i, camera_file, images[i].name)
            c2ws.append(c2w)
            intrinsics.append(K)
            scaled.append(has_scale)
        height, width = self._size(images[0])
        c2w = np.stack(c2ws)
        Ks = np.stack(intrinsics)
        cameras = Cameras.create(
            c2w.astype(np.float32),
            Ks[:, 0, 0],
            Ks[:, 1, 1],
            Ks[:, 0, 2] + PIXEL_CENTRE_OFFSET,
            Ks[:, 1, 2] + PIXEL_CENTRE_OFFSET,
            width,
            height,
        )
        mask_dir = _first(path, MASK_FOLDERS, want_dir=True)
        masks = _image_files(mask_dir) if mask_dir is not None else []
        train, test = split_every_nth(len(images), options.test_every)
        points = colours = None
        if all(scaled):
            rng = np.random.default_rng(0)
            direction = rng.normal(size=(NUM_INIT_POINTS, 3))
            direction /= np.linalg.norm(direction, axis=1, keepdims=True)
            points = (direction * rng.random((NUM_INIT_POINTS, 1)) ** (1 / 3)).astype(np.float32)
            colours = np.full((NUM_INIT_POINTS, 3), 0.5, dtype=np.float32)
        return SceneData(
            cameras=cameras,
            names=[p.name for p in images],
            image_paths=images,
            clean_image_paths=find_clean_paths(path, images),
            mask_paths=masks if len(masks) == len(images) else None,
            train_indices=train,
            test_indices=test,
            points=points,
            point_colors=colours,
            up=_up_from_cameras(c2w),
            metric_scale=None,
            source=path,
        )

    @staticmethod
    def _view(mats: dict[str, np.ndarray], i: int, source: Path, name: str) -> tuple[np.ndarray, np.ndarray, bool]:
        """(K [3, 3] in IDR pixels, camera-to-world [4, 4] in the normalised frame, has a scale_mat) of view i."""
        where = f"view {i} ({name})"
        world = mats.get(f"world_mat_{i}")
        if world is None:
            raise DataError(source, f"{where}: no 'world_mat_{i}' (one per image file, in sorted order)")
        scale = mats.get(f"scale_mat_{i}")
        if world.shape not in ((4, 4), (3, 4)) or (scale is not None and scale.shape != (4, 4)):
            raise DataError(source, f"{where}: world_mat must be 3x4 or 4x4 and scale_mat 4x4")
        P = world[:3, :4] @ (scale if scale is not None else np.eye(4))
        if not np.isfinite(P).all() or abs(np.linalg.det(P[:, :3])) < 1e-12:
            raise DataError(source, f"{where}: the projection matrix is not finite or is degenerate")
        K, R, t = decompose_projection(P)
        if abs(K[0, 1]) > MAX_RELATIVE_SKEW * K[0, 0]:
            raise DataError(source, f"{where}: skewed pixels (skew {K[0, 1]:.3g} px) are unsupported")
        c2w = np.eye(4)
        c2w[:3, :3] = R.T
        c2w[:3, 3] = -R.T @ t
        return K, c2w, scale is not None

    @staticmethod
    def _size(image: Path) -> tuple[int, int]:
        import cv2

        img = cv2.imread(str(image), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise DataError(image, "cannot read the image")
        return int(img.shape[0]), int(img.shape[1])
