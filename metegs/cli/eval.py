"""`metegs-eval RUN_DIR`: evaluate a run's Gaussians on its test views and write eval.json."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import tyro
from rich.console import Console

from metegs.cli import run_cli
from metegs.engine.run import run_folder
from metegs.files import write_result


@dataclass
class EvalArgs:
    """Evaluate a trained run."""

    run_dir: tyro.conf.Positional[Path]
    """Run folder (holds config.yml and checkpoints/), or its config.yml."""
    checkpoint: Path | None = None
    """Checkpoint to evaluate (default: the latest in the run)."""
    ply: Path | None = None
    """Evaluate the Gaussians of this PLY file instead of a checkpoint (e.g. the run's scene.ply)."""
    split: Literal["test", "train"] = "test"
    """Which views to evaluate."""
    lpips_net: Literal["alex", "vgg"] = "alex"
    """LPIPS backbone."""
    output: Path | None = None
    """Where to write the metrics JSON (default: RUN_DIR/eval.json)."""
    device: str | None = None
    """Torch device (default: the run's)."""

    def __post_init__(self) -> None:
        self.run_dir = run_folder(self.run_dir)


def main(args: EvalArgs) -> dict:
    from metegs.engine.run import evaluate_run, load_run

    trainer = load_run(args.run_dir, args.checkpoint, args.ply, args.device)
    m = evaluate_run(trainer, args.split, args.lpips_net)
    m["source"] = str(args.ply or args.checkpoint or "latest checkpoint")
    write_result(args.output or Path(args.run_dir) / "eval.json", json.dumps(m, indent=2))
    lp = m["lpips"]
    Console(stderr=True).print(
        f"{args.split}: PSNR {m['psnr']:.2f} dB, SSIM {m['ssim']:.4f}, LPIPS "
        + (f"{lp:.4f}" if lp is not None else f"null ({m['lpips_reason']})")
    )
    return m


def entrypoint() -> None:
    run_cli(lambda: main(tyro.cli(EvalArgs, prog="metegs-eval")))
