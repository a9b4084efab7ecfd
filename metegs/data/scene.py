"""`SceneData`: what every data parser returns. Nothing downstream knows which format a scene came from."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from metegs.cameras import Cameras


@dataclass
class SceneData:
    """Cameras, where the images are (or the images themselves), the split and optional 3D points."""

    cameras: Cameras
    """All views, OpenCV convention, intrinsics matching the images as stored (before any downscale)."""
    names: list[str]
    """One name per view (usually the image file name)."""
    image_paths: list[Path] | None = None
    """Image file per view; None when ``images`` holds them in memory."""
    images: list[np.ndarray] | None = None
    """In-memory images per view, float32 HxWx3 in [0, 1] (synthetic scenes)."""
    clean_images: list[np.ndarray] | None = None
    """In-memory clean references per view (float32 HxWx3), when the scene provides them."""
    clean_image_paths: list[Path] | None = None
    """Clean reference image file per view, when the scene provides them."""
    depths: list[np.ndarray] | None = None
    """Exact per-view depth maps (float32 HxW, scene units along the optical axis; × ``metric_scale`` for metres), when known."""
    mask_paths: list[Path] | None = None
    """Per-view mask files (white = keep), when the scene provides them."""
    train_indices: list[int] = field(default_factory=list)
    """Views used for training."""
    test_indices: list[int] = field(default_factory=list)
    """Held-out views used for evaluation."""
    points: np.ndarray | None = None
    """[P, 3] float32 sparse points (SfM or surface samples) for initialisation, or None."""
    point_colors: np.ndarray | None = None
    """[P, 3] float32 colours in [0, 1] of ``points``, or None."""
    up: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0], dtype=np.float32))
    """[3] unit world up vector."""
    metric_scale: float | None = None
    """Metres per world unit when known (1.0 for metric scenes), else None."""
    source: Path | None = None
    """The folder or file the scene was read from (None for procedural scenes)."""
    parser: str = ""
    """Registry name of the parser that produced this scene."""
    image_space: str = "srgb"
    """Colour space of the images: 'srgb' or 'linear'."""
    rendered: bool = False
    """Views rendered with one exposure (synthetic, Blender, metegs-synth of those), not photographed."""

    def __len__(self) -> int:
        return len(self.cameras)


def split_every_nth(n_views: int, every: int = 8) -> tuple[list[int], list[int]]:
    """Train/test split when a format has no explicit lists: every ``every``-th view (0, 8, 16, ...) is a test view."""
    if every <= 0 or n_views < 2:
        return list(range(n_views)), []
    test = list(range(0, n_views, every))
    train = [i for i in range(n_views) if i not in set(test)]
    return train, test
