"""Write the training views of a metegs run as a nerfstudio project for another toolkit (OpenSplat, gsplat, ...).

A peer row of a suite (`peer: {ply: FILE, like: METHOD}`) scores another toolkit's Gaussians on the test views of
a metegs run; to be like for like, the peer must train on what that run trained on. This writes exactly that: the
run's training views only (its test views left out), as the run loaded them (its size, as PNG), their cameras
(PINHOLE, in the run's world frame, so the peer's PLY needs no turn when it keeps its input's frame, e.g.
OpenSplat's ``--keep-crs``) and the run's initial points.

    python benchmarks/peer_input.py RUN_DIR OUT_DIR
    opensplat OUT_DIR -n 7000 --keep-crs -o peer-7000.ply      # for example
    metegs-eval RUN_DIR --ply peer-7000.ply                     # or a suite's peer row
"""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path

import numpy as np


def write_peer_input(run_dir: Path, out: Path) -> int:
    """The training views of ``run_dir`` as a nerfstudio project in ``out``; returns the number of views."""
    from metegs.data.config import auto_max_side
    from metegs.data.dataset import Dataset
    from metegs.data.images import save_image
    from metegs.data.parsers.base import parse_scene
    from metegs.engine.run import load_run_config, run_folder
    from metegs.synth.writers import pinhole_frames, write_ply_points

    run_dir = run_folder(run_dir)
    config = load_run_config(run_dir)
    metrics = json.loads((run_dir / "metrics.json").read_text()) if (run_dir / "metrics.json").is_file() else {}
    device = metrics.get("device", config.device)  # the size a run chose by itself depends on its device
    options = replace(config.dataset, auto_max_side=auto_max_side(config.dataset, device))
    scene = parse_scene(config.data, config.parser, options)
    data = Dataset(scene, options, device="cpu")
    size = [int(data.cameras.width[0]), int(data.cameras.height[0])]
    if metrics.get("image_size") not in (None, size):
        raise SystemExit(f"{run_dir}: the run trained at {metrics['image_size']}, its config gives {size}")
    if not data.test_indices:
        raise SystemExit(f"{run_dir}: the run has no test views; a peer trained on all views cannot be scored")
    train = data.train_indices
    files = [f"images/{i:03d}_{Path(data.names[i]).stem}.png" for i in train]
    (out / "images").mkdir(parents=True, exist_ok=True)
    for i, file in zip(train, files, strict=True):
        save_image(out / file, data.images[i].numpy())
    meta = {"camera_model": "PINHOLE", "frames": pinhole_frames(data.cameras[train].to("cpu"), files)}
    if scene.points is not None and len(scene.points):
        write_ply_points(out / "points.ply", np.asarray(scene.points), scene.point_colors)
        meta["ply_file_path"] = "points.ply"
    (out / "transforms.json").write_text(json.dumps(meta, indent=1) + "\n")
    return len(files)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", type=Path, help="a metegs run folder (or its config.yml)")
    parser.add_argument("out", type=Path, help="folder for the nerfstudio project (created)")
    args = parser.parse_args()
    n = write_peer_input(args.run_dir, args.out)
    print(f"wrote {n} training views to {args.out / 'transforms.json'}")


if __name__ == "__main__":
    main()
