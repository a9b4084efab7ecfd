"""What every per-view 2D restorer is: an image in, an image out, and the weather kinds it removes.

A restorer works on one photo at a time (no poses, no other views): the classical "2D restoration,
then 3DGS" baseline of the benchmark restores every training photo and trains plain 3DGS on the results.

    restorer = restorer_config("dcp").setup()
    clean = restorer.restore(foggy)            # [H, W, 3] float32 in [0, 1] -> same shape, in [0, 1]
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from metegs.errors import DataError


class Restorer(Protocol):
    """A single-image restorer (registry kind ``restorer``)."""

    name: str
    """Registry name."""
    removes: frozenset[str]
    """Weather kinds it removes: ``{"fog"}``, ``{"rain"}`` or both."""

    def restore(self, image: np.ndarray) -> np.ndarray:
        """``image`` [H, W, 3] float32 RGB in [0, 1] -> the restored image, same shape and range."""
        ...


def check_image(image: np.ndarray, who: str) -> np.ndarray:
    """``image`` as a contiguous float32 [H, W, 3] array in [0, 1]; a clear error otherwise."""
    arr = np.asarray(image)
    if arr.ndim != 3 or arr.shape[2] != 3 or arr.shape[0] < 1 or arr.shape[1] < 1:
        raise DataError(None, f"{who}: expected an RGB image [H, W, 3], got shape {list(arr.shape)}")
    arr = np.ascontiguousarray(arr, dtype=np.float32)
    if not np.isfinite(arr).all():
        raise DataError(None, f"{who}: the image holds NaN or Inf values")
    return np.clip(arr, 0.0, 1.0)


@dataclass
class ChainRestorer:
    """Restorers applied one after the other (rain + fog: derain first, the rain lies in front of the fog)."""

    stages: Sequence[Restorer]

    @property
    def name(self) -> str:
        return "+".join(s.name for s in self.stages)

    @property
    def removes(self) -> frozenset[str]:
        return frozenset().union(*(s.removes for s in self.stages))

    def restore(self, image: np.ndarray) -> np.ndarray:
        out = check_image(image, self.name)
        for stage in self.stages:
            out = check_image(stage.restore(out), stage.name)
        return out
