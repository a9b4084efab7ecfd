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
    auto_max_side: Annotated[int, Range(8)] = 160
    """Longest image side (px) targeted when `downscale` is None (keeps CPU training interactive)."""
    test_every: Annotated[int, NON_NEGATIVE] = 8
    """Every n-th view is held out for testing when the format has no explicit split (0: no test views)."""
    undistort: bool = True
    """Undistort COLMAP views with distorted camera models (else they are refused with an error)."""
    use_masks: bool = False
    """When the scene ships masks (white = keep), train and evaluate against photos whose masked-out pixels
    take the background colour (object-only reconstruction)."""
    synthetic: SyntheticSceneConfig = field(default_factory=SyntheticSceneConfig)
    """Options of the synthetic scene used when no `--data` is given."""
