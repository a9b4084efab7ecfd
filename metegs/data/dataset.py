"""`Dataset`: every view of a `SceneData` loaded eagerly, downscaled, as torch tensors on one device."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import torch

from metegs.cameras import Cameras
from metegs.data.config import DatasetConfig, auto_max_side
from metegs.data.images import load_image, load_mask, resize_image
from metegs.data.scene import SceneData
from metegs.errors import ConfigError, DataError


def longest_side(cameras: Cameras) -> int:
    """The longest image side (px) over all views."""
    return int(torch.maximum(cameras.width, cameras.height).max())


def auto_downscale(cameras: Cameras, max_side: int) -> int:
    """Smallest power of two ``d`` with max(W, H) / d <= ``max_side`` over all views (at least 1)."""
    longest = longest_side(cameras)
    d = 1
    while longest / d > max(1, max_side):
        d *= 2
    return d


class Dataset:
    """All views of a scene in memory, resized by ``downscale``, as tensors on ``device``.

    Attributes:
        scene: the parsed `SceneData` (cameras at the stored image resolution).
        cameras: `Cameras` of all views rescaled to the loaded image sizes, on ``device``.
        images: per view float32 RGB tensor [H, W, 3] in [0, 1].
        clean_images: per view clean reference [H, W, 3], or None when the scene has none.
        depths: per view float32 depth [H, W] (nearest-neighbour resized), or None.
        masks: per view float32 mask [H, W] in [0, 1] (1 = keep) when ``options.use_masks`` and the
            scene ships masks, else None. Compositing masked-out pixels is left to the trainer.
        train_indices / test_indices: view indices of the split.
        downscale: the factor applied to the stored images (int for powers of two, else float).
        names: one name per view.
    """

    def __init__(self, scene: SceneData, options: DatasetConfig, device: torch.device | str = "cpu"):
        self.scene = scene
        self.device = torch.device(device)
        self.names = list(scene.names)
        self.train_indices = list(scene.train_indices)
        self.test_indices = list(scene.test_indices)
        self.downscale = self._downscale(scene.cameras, options, self.device.type)
        cams = scene.cameras
        self.sizes = [
            (max(1, round(int(w) / self.downscale)), max(1, round(int(h) / self.downscale)))
            for w, h in zip(cams.width.tolist(), cams.height.tolist(), strict=True)
        ]
        """(width, height) per view after downscaling."""
        self.cameras = Cameras.cat([cams[i].resized(w, h) for i, (w, h) in enumerate(self.sizes)]).to(self.device)
        self.images = self._load_rgb(scene.images, scene.image_paths, "images")
        self.clean_images = self._load_rgb(scene.clean_images, scene.clean_image_paths, "clean images", optional=True)
        self.depths = None if scene.depths is None else [self._depth(i, d) for i, d in enumerate(scene.depths)]
        self.masks = None
        if options.use_masks and scene.mask_paths is not None:
            self.masks = [self._mask(i, p) for i, p in enumerate(scene.mask_paths)]

    def __len__(self) -> int:
        return len(self.cameras)

    @staticmethod
    def _downscale(cameras: Cameras, options: DatasetConfig, device: str) -> int | float:
        if options.downscale is None:
            return auto_downscale(cameras, auto_max_side(options, device))
        if not options.downscale > 0:
            raise ConfigError(f"--dataset.downscale must be positive, got {options.downscale}")
        d = float(options.downscale)
        return int(d) if d.is_integer() else d

    def _expected(self, i: int) -> tuple[int, int]:
        """(width, height) of view ``i`` as stored (the scene camera's size)."""
        return int(self.scene.cameras.width[i]), int(self.scene.cameras.height[i])

    def _check(self, i: int, array: np.ndarray, what: str | Path) -> None:
        w, h = self._expected(i)
        if array.shape[1] != w or array.shape[0] != h:
            raise DataError(
                what,
                f"image is {array.shape[1]}x{array.shape[0]} but its camera (view {i}, {self.names[i]}) is {w}x{h}",
            )

    def _to_tensor(self, array: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(array, dtype=np.float32)).to(self.device)

    def _rgb(self, i: int, array: np.ndarray, what: str | Path) -> torch.Tensor:
        """One stored image (float32 [H, W, 3]) -> resized tensor [h, w, 3] after the size check."""
        array = np.asarray(array, dtype=np.float32)
        if array.ndim != 3 or array.shape[2] != 3:
            raise DataError(what, f"expected an RGB image [H, W, 3], got shape {list(array.shape)}")
        self._check(i, array, what)
        return self._to_tensor(resize_image(array, *self.sizes[i]))

    def _load_rgb(self, arrays, paths, label: str, optional: bool = False) -> list[torch.Tensor] | None:
        """Per-view tensors from in-memory ``arrays`` or files ``paths`` (None if optional and absent)."""
        source = arrays if arrays is not None else paths
        if source is None:
            if optional:
                return None
            raise DataError(self.scene.source, f"the scene has no {label} (neither in memory nor as files)")
        if len(source) != len(self):
            raise DataError(self.scene.source, f"{len(source)} {label} for {len(self)} cameras")
        if arrays is not None:
            return [self._rgb(i, a, f"{label} view {i} ({self.names[i]})") for i, a in enumerate(arrays)]
        return [self._rgb(i, load_image(p), p) for i, p in enumerate(paths)]

    def _depth(self, i: int, depth: np.ndarray) -> torch.Tensor:
        """Depth [H, W] -> nearest-neighbour resized tensor [h, w]."""
        depth = np.asarray(depth, dtype=np.float32)
        self._check(i, depth, f"depth view {i} ({self.names[i]})")
        w, h = self.sizes[i]
        if depth.shape != (h, w):
            depth = cv2.resize(depth, (w, h), interpolation=cv2.INTER_NEAREST)
        return self._to_tensor(depth)

    def _mask(self, i: int, path: Path) -> torch.Tensor:
        """Mask file -> area-resized tensor [h, w] in [0, 1]."""
        mask = load_mask(path)
        self._check(i, mask, path)
        return self._to_tensor(resize_image(mask, *self.sizes[i]))
