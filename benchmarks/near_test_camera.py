"""What stands right in front of a test camera in finished runs, and what it costs that view.

    python benchmarks/near_test_camera.py RUN [RUN ...] [--view 0] [--fraction 0.25] [--json out.json]

A test view taken away from the training cameras (the first photo of a capture walked around a table) sees the
scene from where no training view looked, and Gaussians that the training views take for a far surface can stand
right in front of it. For each run folder (any method) and one test view (its index among the test views) this
prints how far that camera stands from the nearest training camera, in spacings of neighbouring training cameras;
the Gaussians in its view nearer than ``--fraction`` of the view's median depth, how many of them cover over 30 px
at an opacity over 0.2, and in how many training views' frames they lie, at what share of the surface depth those
views render at their pixel (about 1: a surface to them); then every test view's PSNR with those Gaussians and
without them (hidden in the same process). A diagnostic that uses the test camera, never a training rule.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch


def near_camera(trainer, view: int, fraction: float) -> dict:
    """The Gaussians nearer than ``fraction`` of test view ``view``'s median depth in a loaded run (`load_run`), and
    what they cost the test views; they stay hidden in ``trainer`` afterwards."""
    from metegs.densify.camera_clearance import camera_spacing
    from metegs.engine.run import evaluate_run, surface_depth

    ds = trainer.dataset
    train, camera = list(ds.train_indices), ds.cameras[[list(ds.test_indices)[view]]]
    gaussians = trainer.model.activated()
    means = gaussians.means.detach()
    u, v, z = camera.project(means)[0].unbind(-1)
    in_view = camera.sees(means)[0]
    median_depth = float(z[in_view].median())
    near = in_view & (z < fraction * median_depth)
    footprint = gaussians.scales.detach().max(dim=1).values / z.clamp_min(1e-6) * float(camera.fx[0])
    large = near & (footprint > 30) & (gaussians.opacities.detach().reshape(-1) > 0.2)
    train_cameras = ds.cameras[train]
    frames = train_cameras.sees(means[large])  # [T, L]
    shares = []
    for t in range(len(train)):
        cols = torch.nonzero(frames[t]).reshape(-1)
        if len(cols) == 0:
            continue
        depth = surface_depth(trainer.rasterizer, gaussians, train_cameras[[t]].to(means.device))
        pu, pv, pz = train_cameras[[t]].project(means[large][cols])[0].unbind(-1)
        shares.append(pz / depth[pv.long(), pu.long()])
    share = torch.cat(shares) if shares else torch.empty(0)
    before = evaluate_run(trainer)["per_view"]["psnr"]
    with torch.no_grad():
        trainer.model.params["opacities"][near] = -60.0  # hidden: the rasteriser skips them
    after = evaluate_run(trainer)["per_view"]["psnr"]
    centers = train_cameras.centers
    return {
        "method": trainer.config.method,
        "view": view,
        "camera_spacings_from_training": float((centers - camera.centers).norm(dim=1).min()) / camera_spacing(centers),
        "median_depth": median_depth,
        "near": int(near.sum()),
        "near_large": int(large.sum()),
        "training_frames_per_large": float(frames.sum(0).float().mean()) if int(large.sum()) else 0.0,
        "depth_share_in_training_views": float(share.nanmedian()) if len(share) else None,
        "psnr": before,
        "psnr_without_near": after,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", type=Path, nargs="+", help="run folders (with config.yml and checkpoints)")
    parser.add_argument("--view", type=int, default=0, help="the test view, by its index among the test views")
    parser.add_argument("--fraction", type=float, default=0.25, help="nearer than this share of its median depth")
    parser.add_argument("--json", type=Path, default=None, help="also write the rows here")
    args = parser.parse_args()
    from metegs.engine.run import load_run

    rows = [{"run": str(run), **near_camera(load_run(run), args.view, args.fraction)} for run in args.runs]
    for r in rows:
        share = r["depth_share_in_training_views"]
        print(
            f"{r['run']} ({r['method']}): test view {r['view']} stands {r['camera_spacings_from_training']:.2f} "
            f"camera spacings from the nearest training camera; {r['near']} Gaussians nearer than "
            f"{args.fraction:g} of its median depth ({r['median_depth']:.2f}), {r['near_large']} over 30 px at opacity "
            f"over 0.2, in {r['training_frames_per_large']:.1f} training frames each"
            + (f" at {share:.2f} of the surface depth there" if share is not None else "")
            + "; PSNR "
            + " / ".join(f"{p:.2f}" for p in r["psnr"])
            + ", without them "
            + " / ".join(f"{p:.2f}" for p in r["psnr_without_near"])
        )
    if args.json is not None:
        args.json.write_text(json.dumps(rows, indent=2) + "\n")


if __name__ == "__main__":
    main()
