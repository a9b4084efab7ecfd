"""What the viewer writes: the current view as PNG, the clean scene as PLY and weather-sweep videos
(`metegs.video`: H.264 MP4 that browsers play, with GIF and PNG-frame fallbacks)."""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import numpy as np

from metegs.gaussians.ply import save_ply
from metegs.video import save_png, write_video
from metegs.viewer.render import Snapshot

__all__ = ["save_png", "save_scene_ply", "write_video"]


def save_scene_ply(
    path: Path, snapshot: Snapshot, comments: Iterable[str] = (), world_to_file: np.ndarray | None = None
) -> Path:
    """The clean scene Gaussians of ``snapshot`` as an INRIA-layout PLY (no weather Gaussians), turned by
    ``world_to_file`` [3, 3] when given (see `save_ply`)."""
    save_ply(snapshot.state, path, comments=comments, world_to_file=world_to_file)
    return Path(path)
