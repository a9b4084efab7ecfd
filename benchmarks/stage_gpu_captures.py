"""Stage configs/bench/real.yaml's captures for a lent GPU machine, which has no pycolmap and reaches nothing outside.

Writes into .gpu/ (ignored by git; carry it with the run): the Ethiopian head (LLFF), the instant-ngp fox (undistorted
here), the Lund street and the kitchen (COLMAP) as nerfstudio ``transforms.json`` scenes with their own train/test
split, the fox and Lund at half their size (the training size is the same: both train at their power-of-two downscale
under 640 px), the kitchen at its own (its grid's fixed downscale 3 sets its training size),
each world turned so that metegs's own up estimate is +Z, the capture's own sparse points where it has them (Lund's SfM
points) and none where it has none, so that each GPU run triangulates from the photos it trains on and chooses its
start (those points or a plane sweep) as a CPU run does (carry the pycolmap wheel: without it a run has no points to
start from or to measure the weather at), the two met records, and ``real-gpu.yaml``:
real.yaml's grid on CUDA without the rows the GPU image cannot run (the 2D restoration needs OpenCV's contrib module),
plus two ablations of blind MeteGS (without the dark-channel prior; densification stopped at 20 % of the run) and
3DGS's and blind MeteGS's rows also with seeds 1 and 2 (``seeds``: rows ``-seed1``, ``-seed2``).
``--scenes`` stages some of them (the grid then names only those).
Then, on the machine, ``bash benchmarks/gpu_real.sh`` runs it.

    python benchmarks/stage_gpu_captures.py        # reads $METEGS_CAPTURES and ../shared
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
import yaml
from PIL import Image

ROOT = Path(__file__).resolve().parents[1]
FOLDERS = ("ethiopianhead-llff", "fox", "lund", "kitchen")  # the staged folders of real.yaml's scenes, in its order
RECORDS = (
    "meteo/beijing-prsa/PRSA_Data_Aotizhongxin_20130301-20170228.csv",
    "meteo/isd-janmayen-1988/DS3505.txt",
)


def turn_up_to_z(up: np.ndarray) -> np.ndarray:
    """[3, 3] rotation taking the unit vector ``up`` to +Z (Rodrigues)."""
    up = up / np.linalg.norm(up)
    z = np.array([0.0, 0.0, 1.0])
    v, c = np.cross(up, z), float(up @ z)
    if np.linalg.norm(v) < 1e-9:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    k = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + k + k @ k / (1.0 + c)


def stage_scene(src: Path, dst: Path, shrink: int) -> None:
    """``src`` (any format metegs reads, undistorted by its parser) as a nerfstudio scene in ``dst``: photos (and
    masks) ``shrink`` times smaller, the world turned so metegs's up estimate is +Z (nerfstudio's convention; a
    COLMAP or LLFF world kept as it is puts height fog along the street), the same train/test split, and sparse
    points where it has them (none: each run triangulates from its own photos)."""
    from metegs.cameras import Cameras
    from metegs.data.config import DatasetConfig
    from metegs.data.parsers.base import parse_scene
    from metegs.synth.writers import pinhole_frames, write_ply_points

    scene = parse_scene(src, None, DatasetConfig(downscale=1))
    turn = torch.eye(4, dtype=torch.float64)
    turn[:3, :3] = torch.from_numpy(turn_up_to_z(np.asarray(scene.up, dtype=np.float64)))
    cam = scene.cameras
    sizes = [(round(int(w) / shrink), round(int(h) / shrink)) for w, h in zip(cam.width, cam.height, strict=True)]
    cams = Cameras.cat([cam[i].resized(w, h) for i, (w, h) in enumerate(sizes)])
    cams = replace(cams, camera_to_worlds=(turn @ cams.camera_to_worlds.double()).float())
    files = [f"images/{i:03d}_{Path(name).stem}.jpg" for i, name in enumerate(scene.names)]  # JPEG: it must travel
    frames = pinhole_frames(cams, files)
    (dst / "images").mkdir(parents=True)
    for i, (w, h) in enumerate(sizes):
        Image.open(scene.image_paths[i]).convert("RGB").resize((w, h), Image.LANCZOS).save(dst / files[i], quality=95)
        if scene.mask_paths is not None:
            mask = f"masks/{Path(files[i]).stem}.png"
            (dst / "masks").mkdir(exist_ok=True)
            Image.open(scene.mask_paths[i]).convert("L").resize((w, h), Image.NEAREST).save(dst / mask)
            frames[i]["mask_path"] = mask
    meta = {
        "camera_model": "PINHOLE",
        "frames": frames,
        "train_filenames": [frames[i]["file_path"] for i in scene.train_indices],
        "test_filenames": [frames[i]["file_path"] for i in scene.test_indices],
    }
    if scene.points is not None and len(scene.points):
        points = np.asarray(scene.points, dtype=np.float64) @ turn[:3, :3].numpy().T
        write_ply_points(dst / "sparse_pc.ply", points, scene.point_colors)
        meta["ply_file_path"] = "sparse_pc.ply"
    (dst / "transforms.json").write_text(json.dumps(meta, indent=1))


def grid_config(real: dict, staged: list[str]) -> dict:
    """real.yaml's grid on the ``staged`` captures' folders, on CUDA, without downloads, and the rows the GPU image
    can run."""
    config = dict(real, name="real-gpu", output="outputs/bench/real-gpu")
    config["train"] = {**real["train"], "device": "cuda", "lpips_download": False}
    config["scenes"] = [
        {**s, "data": f"data/{folder}"} for s, folder in zip(real["scenes"], FOLDERS, strict=True) if folder in staged
    ]
    text = yaml.safe_dump(real["conditions"])
    for record in RECORDS:
        text = text.replace(f"../../../shared/data/{record}", record)
    config["conditions"] = yaml.safe_load(text)
    restores = lambda m: m.get("photos") == "restored" or m.get("overrides", {}).get("pseudo_references")  # noqa: E731
    methods = [m for m in real["methods"] if not restores(m)]
    for m in methods:
        if m["method"].startswith("metegs"):
            m.setdefault("overrides", {})["compare_baseline"] = False
            m["overrides"].setdefault("perceptual", {})["download"] = False
    blind = next(m for m in methods if m["name"] == "metegs-blind")
    ablation = {
        **blind,
        "name": "metegs-blind-nodcp",
        "group": "ablation",
        "label": "MeteGS (blind) without the dark-channel prior",
        "overrides": {**blind["overrides"], "dark_channel": {"mode": "off"}},
    }
    early_stop = {  # the lead of the Lund rain + fog runs: densification stops at a fifth of the steps
        **blind,
        "name": "metegs-blind-stop",
        "group": "ablation",
        "label": "MeteGS (blind), densification stopped at 20 % of the steps",
        "overrides": {**blind["overrides"], "densify": {"refine_stop": 0.2}},
    }
    for m in methods:  # the same rows with other seeds on the same photos: the spread a target's margin must clear
        if m["name"] in ("3dgs", "metegs-blind"):
            m["seeds"] = [1, 2]
    # a suite process runs its rows in this order: cheap, then key
    first = ("3dgs-clean", "3dgs", "metegs-blind", "metegs-blind-stop")
    methods = [*methods, early_stop]
    methods.sort(key=lambda m: first.index(m["name"]) if m["name"] in first else len(first))
    config["methods"] = [*methods, ablation]
    config.pop("checks", None)
    return config


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--captures", type=Path, default=Path(os.environ.get("METEGS_CAPTURES", "/work/captures")))
    parser.add_argument("--shared", type=Path, default=ROOT.parent / "shared")
    parser.add_argument("--out", type=Path, default=ROOT / ".gpu")
    parser.add_argument("--scenes", nargs="+", choices=FOLDERS, default=list(FOLDERS), help="the captures to stage")
    args = parser.parse_args()
    data = args.out / "data"
    shutil.rmtree(data, ignore_errors=True)
    captures = {
        "ethiopianhead-llff": (args.shared / "data/scenes/ethiopianhead-llff", 1),
        "fox": (args.captures / "fox-instant-ngp/data/nerf/fox", 2),
        "lund": (args.captures / "opensfm-lund/scene", 2),
        "kitchen": (args.captures / "vggsfm-kitchen/scene", 1),  # its grid's downscale 3 then trains at 519 px
    }
    for folder in args.scenes:
        src, shrink = captures[folder]
        stage_scene(src, data / folder, shrink)
        for note in ("SOURCE.txt", "SOURCE.md", "LICENSE.txt", "LICENSE.md", "LICENSE"):
            for where in (src, *src.parents[:3]):
                if (where / note).is_file():
                    shutil.copy(where / note, data / folder)
                    break
    for record in RECORDS:
        (args.out / record).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(args.shared / "data" / record, args.out / record)
    for path in args.out.rglob("*"):
        path.chmod(path.stat().st_mode | 0o200)  # ../shared is read-only; the copies must be removable
    real = yaml.safe_load((ROOT / "configs/bench/real.yaml").read_text())
    (args.out / "real-gpu.yaml").write_text(yaml.safe_dump(grid_config(real, args.scenes), sort_keys=False, width=120))
    size = sum(p.stat().st_size for p in args.out.rglob("*") if p.is_file()) / 2**20
    print(f"staged {args.out} ({size:.1f} MiB): carry it with .whl (bash benchmarks/gpu_wheels.sh)")


if __name__ == "__main__":
    main()
