"""Stage configs/bench/real.yaml's captures for a lent GPU machine, which has no pycolmap and reaches nothing outside.

Writes into .gpu/ (ignored by git; carry it with the run): the Ethiopian head as it is, the instant-ngp fox and the
Lund street as nerfstudio ``transforms.json`` scenes at half their size (the training size is the same: both train at
their power-of-two downscale under 640 px), Lund converted from its COLMAP model with its world turned so that metegs's
own up estimate is +Z (nerfstudio's convention; a COLMAP world kept as it is puts height fog along the street), the
two met records, and ``real-gpu.yaml``: real.yaml's grid on CUDA without the rows the GPU image cannot run (the 2D
restoration needs OpenCV's contrib module), plus the ablation without the dark-channel prior. Then, on the machine,
``bash benchmarks/gpu_real.sh`` runs it.

    python benchmarks/stage_gpu_captures.py        # reads $METEGS_CAPTURES and ../shared
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
from pathlib import Path

import numpy as np
import yaml
from PIL import Image

ROOT = Path(__file__).resolve().parents[1]
RECORDS = (
    "meteo/beijing-prsa/PRSA_Data_Aotizhongxin_20130301-20170228.csv",
    "meteo/isd-janmayen-1988/DS3505.txt",
)


def halve(src: Path, dst: Path, meta: dict, frames: list[dict]) -> dict:
    """Write each frame's photo at half size into ``dst/images``; ``meta`` with the intrinsics scaled to it."""
    w, h = int(meta["w"]), int(meta["h"])
    nw, nh = round(w / 2), round(h / 2)
    (dst / "images").mkdir(parents=True, exist_ok=True)
    kept = []
    for frame in frames:
        path = src / frame["file_path"]
        if not path.is_file():  # instant-ngp's fox lists photos it does not ship
            continue
        Image.open(path).convert("RGB").resize((nw, nh), Image.LANCZOS).save(dst / "images" / path.name, quality=95)
        kept.append({**frame, "file_path": f"images/{path.name}"})
    sx, sy = nw / w, nh / h
    out = {k: v for k, v in meta.items() if k not in ("camera_angle_x", "camera_angle_y", "frames")}
    out.update(w=nw, h=nh, fl_x=meta["fl_x"] * sx, fl_y=meta["fl_y"] * sy, cx=meta["cx"] * sx, cy=meta["cy"] * sy)
    return {**out, "frames": kept}


def turn_up_to_z(up: np.ndarray) -> np.ndarray:
    """[3, 3] rotation taking the unit vector ``up`` to +Z (Rodrigues)."""
    up = up / np.linalg.norm(up)
    z = np.array([0.0, 0.0, 1.0])
    v, c = np.cross(up, z), float(up @ z)
    if np.linalg.norm(v) < 1e-9:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    k = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + k + k @ k / (1.0 + c)


def stage_lund(src: Path, dst: Path) -> None:
    from metegs.data.config import DatasetConfig
    from metegs.data.parsers.base import parse_scene

    scene = parse_scene(src, None, DatasetConfig(downscale=1))
    turn = turn_up_to_z(np.asarray(scene.up, dtype=np.float64))
    frames = []
    for name, c2w in zip(scene.names, scene.cameras.camera_to_worlds.double().numpy()):
        gl = np.eye(4)
        gl[:3, :3] = turn @ c2w[:3, :3] @ np.diag([1.0, -1.0, -1.0])  # OpenCV -> OpenGL camera axes
        gl[:3, 3] = turn @ c2w[:3, 3]
        frames.append({"file_path": f"images/{Path(name).name}", "transform_matrix": gl.tolist()})
    cam = scene.cameras
    meta = {
        "camera_model": "PINHOLE",
        **{k: float(getattr(cam, k)[0]) for k in ("fx", "fy", "cx", "cy")},
        "w": int(cam.width[0]),
        "h": int(cam.height[0]),
    }
    meta = {"fl_x": meta.pop("fx"), "fl_y": meta.pop("fy"), **meta}
    staged = halve(src, dst, {**meta, "ply_file_path": "sparse_pc.ply"}, frames)
    (dst / "transforms.json").write_text(json.dumps(staged, indent=1))
    points = np.asarray(scene.points, dtype=np.float64) @ turn.T
    colours = np.clip(np.asarray(scene.point_colors) * (255.0 if np.max(scene.point_colors) <= 1.0 else 1.0), 0, 255)
    vertex = np.zeros(
        len(points), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("r", "u1"), ("g", "u1"), ("b", "u1")]
    )
    vertex["x"], vertex["y"], vertex["z"] = points.T
    vertex["r"], vertex["g"], vertex["b"] = colours.astype(np.uint8).T
    header = (
        f"ply\nformat binary_little_endian 1.0\nelement vertex {len(points)}\nproperty float x\nproperty float y\n"
        "property float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n"
    )
    (dst / "sparse_pc.ply").write_bytes(header.encode() + vertex.tobytes())


def grid_config(real: dict) -> dict:
    """real.yaml's grid with the staged paths, on CUDA, without downloads, and the rows the GPU image can run."""
    config = dict(real, name="real-gpu", output="outputs/bench/real-gpu")
    config["train"] = {**real["train"], "device": "cuda", "lpips_download": False}
    config["scenes"] = [
        {**s, "data": f"data/{folder}"}
        for s, folder in zip(real["scenes"], ("ethiopianhead-llff", "fox", "lund"), strict=True)
    ]
    text = yaml.safe_dump(real["conditions"])
    for record in RECORDS:
        text = text.replace(f"../../../shared/data/{record}", record)
    config["conditions"] = yaml.safe_load(text)
    methods = [m for m in real["methods"] if m.get("photos") != "restored"]
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
    config["methods"] = [*methods, ablation]
    config.pop("checks", None)
    return config


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--captures", type=Path, default=Path(os.environ.get("METEGS_CAPTURES", "/work/captures")))
    parser.add_argument("--shared", type=Path, default=ROOT.parent / "shared")
    parser.add_argument("--out", type=Path, default=ROOT / ".gpu")
    args = parser.parse_args()
    data = args.out / "data"
    shutil.rmtree(data, ignore_errors=True)
    shutil.copytree(args.shared / "data/scenes/ethiopianhead-llff", data / "ethiopianhead-llff")
    fox = args.captures / "fox-instant-ngp/data/nerf/fox"
    meta = json.loads((fox / "transforms.json").read_text())
    (data / "fox").mkdir(parents=True)
    (data / "fox/transforms.json").write_text(json.dumps(halve(fox, data / "fox", meta, meta["frames"]), indent=1))
    stage_lund(args.captures / "opensfm-lund/scene", data / "lund")
    for folder, capture in (("fox", "fox-instant-ngp"), ("lund", "opensfm-lund")):
        for note in ("SOURCE.txt", "LICENSE.txt", "LICENSE"):
            if (args.captures / capture / note).is_file():
                shutil.copy(args.captures / capture / note, data / folder)
    for record in RECORDS:
        (args.out / record).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(args.shared / "data" / record, args.out / record)
    for path in args.out.rglob("*"):
        path.chmod(path.stat().st_mode | 0o200)  # ../shared is read-only; the copies must be removable
    real = yaml.safe_load((ROOT / "configs/bench/real.yaml").read_text())
    (args.out / "real-gpu.yaml").write_text(yaml.safe_dump(grid_config(real), sort_keys=False, width=120))
    size = sum(p.stat().st_size for p in args.out.rglob("*") if p.is_file()) / 2**20
    print(f"staged {args.out} ({size:.1f} MiB): carry it with .whl (gsplat, tyro and their wheels)")


if __name__ == "__main__":
    main()
