"""LLFF scenes: ``poses_bounds.npy`` plus ``images/`` or downsampled ``images_N/`` folders.

Each row of ``poses_bounds.npy`` (shape [N, 17]) is a 3x5 matrix (camera-to-world [R | t] whose rotation
columns are [down, right, backwards], then a column [H, W, focal] at the original resolution) followed
by near/far bounds. Rows match the image files in sorted filename order. ``images/`` is used when present,
else the ``images_N/`` folder with the smallest N; the focal length is rescaled to the size of the images
actually found and the principal point is the image centre. Masks come from the matching ``masks/`` or
``masks_N/`` folder (same file stems), clean references (as `metegs-synth` writes them) from the sibling
``images_N_clean/`` folder. There are no 3D points and no metric scale.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import ClassVar

import numpy as np

from metegs.cameras import Cameras
from metegs.data.config import DatasetConfig
from metegs.data.images import image_size, list_images
from metegs.data.parsers.clean import find_clean_paths
from metegs.data.parsers.colmap import up_from_cameras
from metegs.data.parsers.masks import mask_paths
from metegs.data.parsers.nerfstudio import read_npy
from metegs.data.scene import SceneData, split_every_nth
from metegs.errors import DataError


def llff_to_opencv(poses: np.ndarray) -> np.ndarray:
    """[N, 3, 4] LLFF camera-to-world (rotation columns [down, right, backwards]) -> [N, 4, 4] OpenCV c2w."""
    c2w = np.zeros((poses.shape[0], 4, 4), dtype=np.float64)
    c2w[:, :3, 0] = poses[:, :, 1]  # right
    c2w[:, :3, 1] = poses[:, :, 0]  # down
    c2w[:, :3, 2] = -poses[:, :, 2]  # forward
    c2w[:, :3, 3] = poses[:, :, 3]
    c2w[:, 3, 3] = 1.0
    return c2w


def image_folder(path: Path) -> Path:
    """``images/`` if present, else the ``images_N/`` folder with the smallest N."""
    if (path / "images").is_dir():
        return path / "images"
    scaled = [
        (int(m.group(1)), p)
        for p in path.glob("images_*")
        if p.is_dir() and (m := re.fullmatch(r"images_(\d+)", p.name))
    ]
    if not scaled:
        raise DataError(path, "no image folder found (expected images/ or images_N/)")
    return min(scaled)[1]


class LLFFParser:
    """LLFF ``poses_bounds.npy`` scene -> SceneData (see the module docstring)."""

    priority: ClassVar[int] = 30

    @staticmethod
    def can_parse(path: Path) -> bool:
        return (Path(path) / "poses_bounds.npy").is_file()

    def parse(self, path: Path | None, options: DatasetConfig) -> SceneData:
        if path is None:
            raise DataError(None, "the LLFF parser needs a scene folder")
        path = Path(path)
        source = path / "poses_bounds.npy"
        data = self._load(source)
        image_dir = image_folder(path)
        images = list_images(image_dir)
        if len(images) != data.shape[0]:
            raise DataError(
                image_dir, f"{len(images)} images found but {source.name} has {data.shape[0]} poses (they must match)"
            )
        poses = data[:, :15].reshape(-1, 3, 5)
        h_file, w_file, focal = poses[:, 0, 4], poses[:, 1, 4], poses[:, 2, 4]
        width, height = image_size(images[0])
        c2w = llff_to_opencv(poses[:, :, :4])
        cams = Cameras.create(
            c2w.astype(np.float32),
            focal * width / w_file,
            focal * height / h_file,
            width / 2.0,
            height / 2.0,
            width,
            height,
        )
        train, test = split_every_nth(len(images), options.test_every)
        return SceneData(
            cameras=cams,
            names=[p.name for p in images],
            image_paths=images,
            clean_image_paths=find_clean_paths(path, images),
            mask_paths=mask_paths(path, images, image_dir),
            train_indices=train,
            test_indices=test,
            up=up_from_cameras(c2w),
            source=path,
        )

    @staticmethod
    def _load(source: Path) -> np.ndarray:
        """[N, 17] float64 rows of poses_bounds.npy; DataError naming the file if malformed."""
        data = read_npy(source, "poses and bounds")
        if data.ndim != 2 or data.shape[1] != 17 or data.shape[0] == 0:
            raise DataError(source, f"expected an array of shape [N, 17], got {list(data.shape)}")
        data = data.astype(np.float64)
        if not np.isfinite(data).all():
            raise DataError(source, "contains non-finite values")
        hwf = data[:, :15].reshape(-1, 3, 5)[:, :, 4]
        if (hwf <= 0).any():
            raise DataError(source, "H, W and focal (5th column of each 3x5 pose) must be positive")
        return data
