"""`metegs-render RUN_DIR`: render a run's views (colour, and optionally depth) to PNG files, or a video along a
camera path (`--camera-path interpolate|spiral|camera_path.json`), clean and optionally through the weather
(`--weather run|record`)."""

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
from metegs.errors import ConfigError, DataError
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
    weather: Literal["off", "run", "record"] = "off"
    """With --camera-path, also render the path through the weather (camera-path-weather.mp4): run = the weather the
    run trained under on every frame; record = the hours of the run's met record passing from its capture time."""
    hours: Annotated[float, Range(0, 100_000)] = 24.0
    """Hours of the met record that a --weather record video spans (its last frame is this long after the first)."""

    def __post_init__(self) -> None:
        self.run_dir = run_folder(self.run_dir)
        check_config(self)
        if self.weather != "off" and self.camera_path is None:
            raise ConfigError(f"--weather {self.weather} renders along a camera path: give --camera-path too")


def render_camera_path(trainer, args: RenderArgs, cameras, fps: float) -> Path:
    """The clean scene along ``cameras`` (`path_cameras`) as a video -> the file written (see `metegs.video`)."""
    from metegs.render import RenderSettings
    from metegs.video import to_uint8

    settings = RenderSettings(background=trainer.background(training=False), sh_degree=trainer.model.active_sh_degree)
    gaussians = trainer.model.activated()
    frames = []
    for i in track(range(len(cameras)), description="camera path", console=Console(stderr=True)):
        with torch.no_grad():
            frames.append(to_uint8(trainer.rasterizer.render(gaussians, cameras[i], settings).rgb))
    return _write(frames, fps, args, "camera-path.mp4")


def path_cameras(trainer, args: RenderArgs):
    """The cameras of ``args.camera_path`` on the run's device and the video's frames per second."""
    from metegs.cameras import look_at_point
    from metegs.render.camera_path import interpolate, read_camera_path, spiral

    ds = trainer.dataset
    views = ds.cameras[sorted(ds.train_indices, key=lambda i: ds.names[i])]
    fps = args.fps
    if args.camera_path == "interpolate":
        cameras = interpolate(views, args.frames)
    elif args.camera_path == "spiral":
        cameras = spiral(views, args.frames, look_at_point(views))
    else:
        cameras, fps = read_camera_path(Path(args.camera_path))
    return cameras.to(trainer.device), fps


def render_weather_path(trainer, args: RenderArgs, cameras, fps: float) -> Path:
    """The scene through the weather along ``cameras`` (`path_cameras`), each frame captioned with its weather (and
    time, for ``--weather record``) -> the video written. Every frame draws its own rain, as a video's frames do."""
    from metegs.video import caption, to_uint8
    from metegs.viewer.render import Snapshot, render_frame
    from metegs.viewer.weather import run_weather

    run = run_weather(trainer)
    if run.note:
        Console(stderr=True).print(f"[yellow]warning:[/] {run.note}")
    if args.weather == "record" and run.timeline is None:
        raise DataError(trainer.config.conditions.record, "no met record could be read for --weather record")
    snapshot = Snapshot.of(trainer.model, trainer.step)
    background = trainer.background(training=False)
    seed, n = run.weather.seed, len(cameras)
    frames = []
    for i in track(range(n), description="weather along the path", console=Console(stderr=True)):
        if args.weather == "record":
            hour = run.timeline.capture_index + args.hours * i / max(n - 1, 1)
            time, values = run.timeline.at(hour, run.values.exposure_s)
            text = f"{time:%Y-%m-%d %H:%M}Z  {values.describe(exposure=False)}"
        else:
            values, text = run.values, run.values.describe(exposure=False)
        run.weather.set_values(values)
        run.weather.seed = seed + i
        rgb = render_frame(trainer.rasterizer, snapshot, cameras[i], background, run.weather)
        frames.append(caption(to_uint8(rgb), text))
    return _write(frames, fps, args, "camera-path-weather.mp4")


def _write(frames: list, fps: float, args: RenderArgs, name: str) -> Path:
    from metegs.video import write_video

    out_dir = args.output or Path(args.run_dir) / "renders"
    path = write_video(out_dir / name, frames, fps)
    Console(stderr=True).print(f"wrote {len(frames)} frames ({fps:g} fps) to {path}")
    return path


def main(args: RenderArgs) -> Path:
    from metegs.data.images import save_image
    from metegs.engine.run import load_run

    trainer = load_run(args.run_dir, args.checkpoint, args.ply, args.device)
    ds = trainer.dataset
    if args.camera_path is not None:
        cameras, fps = path_cameras(trainer, args)
        path = render_camera_path(trainer, args, cameras, fps)
        if args.weather != "off":
            render_weather_path(trainer, args, cameras, fps)
        return path
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
