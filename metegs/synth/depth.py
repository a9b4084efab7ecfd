"""A metric-scale guess for scenes without one, from their depth maps (rendered from a run by
`metegs.engine.run.depths_from_run`)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from metegs.errors import DataError

ASSUMED_MEDIAN_DEPTH_M = 4.0
"""Default guess of the median scene depth, m, for scenes without a metric scale (LLFF, COLMAP): forward-facing
captures are mostly taken a few metres from their subject; a bust seen from ~1 m or a room of ~8 m both stay
within a factor of 3 of it."""


def guess_metres_per_unit(depths: Sequence[np.ndarray], median_depth_m: float = ASSUMED_MEDIAN_DEPTH_M) -> float:
    """Metres per scene unit such that the median known depth over all views is ``median_depth_m``."""
    values = [np.asarray(d, dtype=np.float32).reshape(-1) for d in depths]
    flat = np.concatenate(values) if values else np.zeros(0, np.float32)
    flat = flat[np.isfinite(flat) & (flat > 0)]
    if flat.size == 0:
        raise DataError(None, "cannot guess the scene scale: no view has a known depth; give --metres-per-unit")
    return float(median_depth_m / np.median(flat))
