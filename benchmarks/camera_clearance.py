"""What the camera clearance does to finished runs: their test views with and without it, in the same process.

    python benchmarks/camera_clearance.py RUN [RUN ...] [--fraction 0.5] [--json out.json]

For each run folder (any method: 3dgs, restoration + 3dgs, MeteGS) loads its latest checkpoint, scores the test views
against their clean references, then hides the Gaussians that `metegs.densify.camera_clearance` prunes (within
``--fraction`` of the median distance between neighbouring training cameras, at most a tenth of the scene's typical
depth, and seen by none of the cameras there) and scores them again: the PSNR / SSIM of both, the change and how many
Gaussians went. A MeteGS run trained with the clearance on (the default) has none left to prune.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch


def with_and_without(run: Path, fraction: float) -> dict:
    """Test-view metrics of ``run`` before and after the clearance, and the count pruned."""
    from metegs.densify.camera_clearance import CameraClearance, unseen_near_cameras
    from metegs.engine.run import evaluate_run, load_run
    from metegs.weather.medium import typical_depth_m

    trainer = load_run(run)
    cameras = trainer.dataset.cameras[trainer.dataset.train_indices]
    clearance = CameraClearance(cameras, fraction, typical_depth_m(cameras, trainer.scene.points, 1.0))
    before = evaluate_run(trainer)
    gone = unseen_near_cameras(trainer.model.params["means"].detach(), cameras, clearance.radius)
    with torch.no_grad():
        trainer.model.params["opacities"][gone] = -60.0  # hidden: the rasteriser skips them
    after = evaluate_run(trainer)
    return {
        "run": str(run),
        "method": trainer.config.method,
        "radius": clearance.radius,
        "pruned": int(gone.sum()),
        "gaussians": len(trainer.model),
        "before": {"psnr": before["psnr"], "ssim": before["ssim"]},
        "after": {"psnr": after["psnr"], "ssim": after["ssim"]},
        "psnr_change": after["psnr"] - before["psnr"],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", type=Path, help="run folders (each with config.yml and checkpoints/)")
    parser.add_argument("--fraction", type=float, default=0.5, help="of the median camera spacing (--camera-clearance)")
    parser.add_argument("--json", type=Path, default=None, help="also write the rows here")
    args = parser.parse_args()
    rows = []
    for run in args.runs:
        row = with_and_without(run, args.fraction)
        rows.append(row)
        b, a = row["before"], row["after"]
        print(
            f"{run}: {b['psnr']:.2f} / {b['ssim']:.3f} -> {a['psnr']:.2f} / {a['ssim']:.3f} "
            f"({row['psnr_change']:+.2f} dB, {row['pruned']} of {row['gaussians']} Gaussians pruned)",
            flush=True,
        )
    if args.json is not None:
        args.json.write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
