"""`metegs-render RUN_DIR`: render a run's views (colour, and optionally depth) to PNG files, or a video along a
camera path (`--camera-path interpolate|spiral|camera_path.json`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import torch
import tyro
from rich.console import Console
from rich.progress import track

from metegs.cli import run_cli
from metegs.engine.run import run_folder
from metegs.validate import Range, check_config


@dataclass
class RenderArgs:
    """Render views of a trained run."""

    run_dir: tyro.conf.Positional[Path]
    """Run folder (holds config.yml and checkpoints/), or its config.yml."""
    split: Literal["test", "train", "all"] = "test"
    """Which views to render."""
    checkpoint: Path | None = None
    """Checkpoint to render (default: the latest)."""
    ply: Path | None = None
    """Render the Gaussians of this PLY file instead of a checkpoint."""
    output: Path | None = None
    """Output folder (default: RUN_DIR/renders/<split>-render)."""
    depth: bool = False
    """Also write normalised depth maps (<name>_depth.png)."""
    device: str | None = None
    """Torch device (default: the run's)."""
    camera_path: str | None = None
    """Render the clean scene as a video along a path instead of the dataset's views: interpolate (through the
    training views in order), spiral (around the mean view, looking where the views look) or a nerfstudio
    camera_path.json; written to the output folder as camera-path.mp4."""
    frames: Annotated[int, Range(2, 10000)] = 120
    """Frames of an interpolate or spiral path."""
    fps: Annotated[float, Range(1, 240)] = 30.0
    """Frames per second of an interpolate or spiral video (a camera-path file's own wins)."""

    def __post_init__(self) -> None:
        self.run_dir = run_folder(self.run_dir)
        check_config(self)


def render_camera_path(trainer, args: RenderArgs) -> Path:
    """The clean scene along ``args.camera_path`` as a video -> the file written (see `metegs.video`)."""
    from metegs.engine.init import look_at_point
    from metegs.render import RenderSettings
    from metegs.render.camera_path import interpolate, read_camera_path, spiral
    from metegs.video import to_uint8, write_video

    ds = trainer.dataset
    views = ds.cameras[sorted(ds.train_indices, key=lambda i: ds.names[i])]
    fps = args.fps
    if args.camera_path == "interpolate":
        cameras = interpolate(views, args.frames)
    elif args.camera_path == "spiral":
        cameras = spiral(views, args.frames, look_at_point(views))
    else:
        cameras, fps = read_camera_path(Path(args.camera_path))
    cameras = cameras.to(trainer.device)
    settings = RenderSettings(background=trainer.background(training=False), sh_degree=trainer.model.active_sh_degree)
    gaussians = trainer.model.activated()
    frames = []
    for i in track(range(len(cameras)), description="camera path", console=Console(stderr=True)):
        with torch.no_grad():
            frames.append(to_uint8(trainer.rasterizer.render(gaussians, cameras[i], settings).rgb))
    out_dir = args.output or Path(args.run_dir) / "renders"
    path = write_video(out_dir / "camera-path.mp4", frames, fps)
    Console(stderr=True).print(f"wrote {len(frames)} frames ({fps:g} fps) to {path}")
    return path


def main(args: RenderArgs) -> Path:
    from metegs.data.images import save_image
    from metegs.engine.run import load_run

    trainer = load_run(args.run_dir, args.checkpoint, args.ply, args.device)
    ds = trainer.dataset
    if args.camera_path is not None:
        return render_camera_path(trainer, args)
    idx = {"test": ds.test_indices, "train": ds.train_indices, "all": list(range(len(ds)))}[args.split]
    out_dir = args.output or Path(args.run_dir) / "renders" / f"{args.split}-render"
    for i in track(idx, description="render", console=Console(stderr=True)):
        with torch.no_grad():
            out = trainer.render(i)
        name = Path(ds.names[i]).stem
        save_image(out_dir / f"{name}.png", out.rgb.clamp(0, 1))
        if args.depth:
            d = out.depth * (out.alpha > 0.5)
            d = (d / d.max().clamp_min(1e-6))[..., None].expand(-1, -1, 3)
            save_image(out_dir / f"{name}_depth.png", d)
    Console(stderr=True).print(f"wrote {len(idx)} views to {out_dir}")
    return out_dir


def entrypoint() -> None:
    run_cli(lambda: main(tyro.cli(RenderArgs, prog="metegs-render")))
