"""Options shared by the data parsers and the dataset (the `--dataset.*` flags)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated

from metegs.validate import NON_NEGATIVE, POSITIVE, Range


@dataclass
class SyntheticSceneConfig:
    """The procedural default scene: ray-cast analytic textured primitives in metres."""

    width: Annotated[int, Range(8)] = 160
    """Image width in pixels."""
    height: Annotated[int, Range(8)] = 120
    """Image height in pixels."""
    num_views: Annotated[int, Range(2)] = 48
    """Number of views on the camera orbit (every 8th is a test view)."""
    seed: int = 0
    """Seed of the scene layout, textures and camera jitter."""
    num_points: Annotated[int, Range(1)] = 4000
    """Number of coloured surface points sampled for initialisation (like SfM points)."""
    metres_per_unit: Annotated[float, POSITIVE] = 10.0
    """Metres per scene unit: the default scene is a town square about 150 m across, seen from 80 m."""


@dataclass
class DatasetConfig:
    """How views are read, scaled and split."""

    downscale: float | None = None
    """Image downscale factor; None picks the smallest power of two bringing the longer side to at most `auto-max-side`."""
    auto_max_side: Annotated[int | None, Range(8)] = None
    """Longest image side (px) targeted when `downscale` is None; None: 1600 on CUDA (nerfstudio's convention),
    640 on CPU (sharp, and a 3000-step 3dgs run of a 50-view capture takes about 3 minutes on 2 cores)."""
    test_every: Annotated[int, NON_NEGATIVE] = 8
    """Every n-th view is held out for testing when the format has no explicit split (0: no test views)."""
    undistort: bool = True
    """Undistort COLMAP views with distorted camera models (else they are refused with an error)."""
    use_masks: bool = False
    """When the scene ships masks (white = keep), train and evaluate against photos whose masked-out pixels
    take the background colour (object-only reconstruction)."""
    synthetic: SyntheticSceneConfig = field(default_factory=SyntheticSceneConfig)
    """Options of the synthetic scene used when no `--data` is given."""


AUTO_MAX_SIDE = {"cuda": 1600, "cpu": 640}
"""Longest image side by device type when `DatasetConfig.auto_max_side` is None."""


def auto_max_side(options: DatasetConfig, device: str = "cpu") -> int:
    """The longest image side that `options` targets on ``device`` (a torch device string or type)."""
    if options.auto_max_side is not None:
        return options.auto_max_side
    return AUTO_MAX_SIDE.get(str(device).split(":")[0], AUTO_MAX_SIDE["cpu"])
