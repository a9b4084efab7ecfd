"""Train plain 3DGS on the very photos a weather-aware run used, and compare their clean-view metrics."""

from __future__ import annotations

import json
from dataclasses import replace

from rich.console import Console
from rich.table import Table

from metegs.engine.config import TrainConfig
from metegs.files import atomic_write_text

METRIC_KEYS = ("psnr", "ssim", "lpips", "streak_energy", "contrast_ratio", "num_gaussians", "train_seconds")


def baseline_config(config: TrainConfig) -> TrainConfig:
    """Plain `3dgs` with the run's data, schedule, seed and hardware choices (no weather, no degrading) and its
    per-view exposure choice, so both take the photos' tones the same way."""
    from metegs.registry import registry

    base = registry("method").get("3dgs")()
    shared = (
        "data",
        "parser",
        "output_dir",
        "max_steps",
        "seed",
        "backend",
        "device",
        "threads",
        "background",
        "view_exposure",
        "eval_every",
        "checkpoint_every",
        "save_renders",
        "lpips_net",
        "lpips_download",
        "progress",
        "dataset",
    )
    return replace(base, **{k: getattr(config, k) for k in shared}, degrade="off", conditions=config.conditions)


def train_baseline(trainer, console: Console | None = None) -> dict:
    """Train `3dgs` on ``trainer``'s scene (degraded photos included) into RUN_DIR/baseline-3dgs; its metrics."""
    from metegs.engine.trainer import Trainer

    config = baseline_config(trainer.config)
    baseline = Trainer(config, run_dir=trainer.run_dir / "baseline-3dgs", console=console, scene=trainer.scene)
    return baseline.train()


def train_blind(trainer, console: Console | None = None) -> dict:
    """Train ``trainer``'s method again without its clean references (blind: the photos and the met record only),
    on the same scene, into RUN_DIR/blind; its metrics. This is the run to compare with 3DGS like for like."""
    config = replace(trainer.config, clean_supervision=False, compare_baseline=False, load_checkpoint=None)
    blind = type(trainer)(config, run_dir=trainer.run_dir / "blind", console=console, scene=trainer.scene)
    return blind.train()


INPUTS = {
    "photos": "photos",
    "blind": "photos + met record",
    "clean": "photos + met record + clean refs (oracle)",
}
"""What each kind of comparison row was trained on (the ``inputs`` column and field)."""


def comparison_table(rows: dict[str, dict]) -> Table:
    """A rich table of clean-view metrics, one row per method, saying what each was trained on."""
    table = Table(title="clean held-out views")
    for col in ("method", "trained on", "PSNR dB", "SSIM", "LPIPS", "Gaussians", "train s"):
        table.add_column(col, justify="left" if col in ("method", "trained on") else "right")
    for name, m in rows.items():
        lp = m.get("lpips")
        table.add_row(
            name,
            INPUTS[m.get("inputs", "photos")],
            f"{m['psnr']:.2f}",
            f"{m['ssim']:.4f}",
            "null" if lp is None else f"{lp:.4f}",
            str(m["num_gaussians"]),
            f"{m['train_seconds']:.1f}",
        )
    return table


def write_comparison(path, rows: dict[str, dict]) -> None:
    """comparison.json: the metrics of each method, what it was trained on (``inputs``, ``clean_references``) and
    the PSNR / SSIM differences to the first row."""
    names = list(rows)
    first = rows[names[0]]
    record = {
        "methods": {
            n: {
                **{k: rows[n].get(k) for k in METRIC_KEYS},
                "inputs": INPUTS[rows[n].get("inputs", "photos")],
                "clean_references": rows[n].get("inputs") == "clean",
            }
            for n in names
        },
        "delta_vs_first": {
            n: {"psnr": rows[n]["psnr"] - first["psnr"], "ssim": rows[n]["ssim"] - first["ssim"]} for n in names[1:]
        },
    }
    atomic_write_text(path, json.dumps(record, indent=2))
