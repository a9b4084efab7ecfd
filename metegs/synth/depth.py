"""Depth maps for synthesis: rendered from a trained run, and a metric-scale guess for scenes without one."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import torch

from metegs.data.scene import SceneData
from metegs.errors import DataError

ASSUMED_MEDIAN_DEPTH_M = 4.0
"""Default guess of the median scene depth, m, for scenes without a metric scale (LLFF, COLMAP): forward-facing
captures are mostly taken a few metres from their subject; a bust seen from ~1 m or a room of ~8 m both stay
within a factor of 3 of it."""

MIN_ALPHA = 0.5
"""Rendered pixels with less accumulated opacity have unknown depth (they look into the distance)."""


def guess_metres_per_unit(depths: Sequence[np.ndarray], median_depth_m: float = ASSUMED_MEDIAN_DEPTH_M) -> float:
    """Metres per scene unit such that the median known depth over all views is ``median_depth_m``."""
    values = [np.asarray(d, dtype=np.float32).reshape(-1) for d in depths]
    flat = np.concatenate(values) if values else np.zeros(0, np.float32)
    flat = flat[np.isfinite(flat) & (flat > 0)]
    if flat.size == 0:
        raise DataError(None, "cannot guess the scene scale: no view has a known depth; give --metres-per-unit")
    return float(median_depth_m / np.median(flat))


def cameras_match(a, b, atol: float = 1e-4) -> bool:
    """Same number of views, same poses and the same field of view (sizes may differ)."""
    if len(a) != len(b):
        return False
    same_pose = torch.allclose(a.camera_to_worlds.cpu(), b.camera_to_worlds.cpu(), atol=atol)
    fov_a, fov_b = a.fx.cpu() / a.width.cpu(), b.fx.cpu() / b.width.cpu()
    return bool(same_pose and torch.allclose(fov_a, fov_b, rtol=1e-3))


def depths_from_run(
    run_dir: Path,
    scene: SceneData,
    checkpoint: Path | None = None,
    progress: Callable[[int], None] | None = None,
    device: str | None = None,
) -> tuple[list[np.ndarray], str]:
    """Depth of every view of ``scene`` rendered from a trained run at the scene's image sizes.

    Returns (depths [H, W] float32 in scene units with NaN where the render's opacity is below
    ``MIN_ALPHA``, a description of the source). The run must have been trained on the same cameras.
    """
    from metegs.engine.run import load_run
    from metegs.render.base import RenderSettings

    run_dir = Path(run_dir)
    trainer = load_run(run_dir, checkpoint, device=device)
    if not cameras_match(trainer.scene.cameras, scene.cameras):
        raise DataError(
            run_dir,
            f"the run was trained on other cameras ({len(trainer.scene.cameras)} views, data "
            f"{trainer.config.data}) than the scene to degrade ({len(scene)} views, {scene.source}); "
            "give the run of this dataset",
        )
    model = trainer.model.activated()
    settings = RenderSettings(background=(0.0, 0.0, 0.0), sh_degree=trainer.model.active_sh_degree)
    depths = []
    with torch.no_grad():
        for i in range(len(scene)):
            out = trainer.rasterizer.render(model, scene.cameras[i].to(trainer.device), settings)
            d = torch.where(out.alpha >= MIN_ALPHA, out.depth, torch.full_like(out.depth, float("nan")))
            depths.append(d.float().cpu().numpy())
            if progress is not None:
                progress(i)
    ckpt = checkpoint or "latest checkpoint"
    return depths, f"rendered from run {run_dir.resolve()} ({trainer.config.method}, {ckpt}, step {trainer.step})"
