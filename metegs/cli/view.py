"""`metegs-view RUN_DIR`: open a run in the browser viewer (clean / weather, met sliders, exports)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import tyro
from rich.console import Console

from metegs.cli import run_cli
from metegs.engine.run import run_folder
from metegs.validate import Range, check_config


@dataclass
class ViewArgs:
    """View a trained run in the browser (viser), rendered by the run's rasteriser."""

    run_dir: tyro.conf.Positional[Path]
    """Run folder (holds config.yml and checkpoints/), or its config.yml."""
    host: str = "127.0.0.1"
    """Address to bind; 0.0.0.0 exposes the viewer to the network (deliberately)."""
    port: Annotated[int, Range(0, 65535)] = 7007
    """Port (the next free one when it is taken)."""
    checkpoint: Path | None = None
    """Checkpoint to show (default: the latest)."""
    ply: Path | None = None
    """Show the Gaussians of this PLY file instead of a checkpoint."""
    device: str | None = None
    """Torch device (default: the run's)."""
    max_side: Annotated[int, Range(16)] = 1024
    """Longest side of a full-resolution frame, px."""
    output_dir: Path | None = None
    """Where exports go (default: RUN_DIR/viewer)."""

    def __post_init__(self) -> None:
        check_config(self)
        self.run_dir = run_folder(self.run_dir)


def main(args: ViewArgs, block: bool = True):
    from metegs.engine.run import load_run
    from metegs.viewer import Viewer, ViewerConfig, announce

    console = Console(stderr=True)
    console.print(f"loading {args.run_dir} ...")
    trainer = load_run(args.run_dir, args.checkpoint, args.ply, args.device)
    config = ViewerConfig(host=args.host, port=args.port, max_side=args.max_side, output_dir=args.output_dir)
    viewer = Viewer(trainer, config, live=False, console=console)
    announce(viewer, console)
    console.print(f"{len(trainer.model):,} Gaussians at step {trainer.step}; Ctrl+C quits")
    if block:
        viewer.serve_forever()
    return viewer


def entrypoint() -> None:
    run_cli(lambda: main(tyro.cli(ViewArgs, prog="metegs-view")))
