"""`metegs-render RUN_DIR`: render a run's views (colour, and optionally depth) to PNG files."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import torch
import tyro
from rich.console import Console
from rich.progress import track

from metegs.cli import run_cli
from metegs.engine.run import run_folder


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

    def __post_init__(self) -> None:
        self.run_dir = run_folder(self.run_dir)


def main(args: RenderArgs) -> Path:
    from metegs.data.images import save_image
    from metegs.engine.run import load_run

    trainer = load_run(args.run_dir, args.checkpoint, args.ply, args.device)
    ds = trainer.dataset
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
