"""`metegs-bench`: benchmarks. `metegs-bench raster` times every rasteriser backend in one process."""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path

import torch
import tyro
from rich.console import Console
from rich.table import Table

from metegs.cli import run_cli
from metegs.config import atomic_write_text
from metegs.errors import ConfigError


@dataclass
class RasterArgs:
    """Forward and forward+backward time and peak memory of every rasteriser backend, as ratios over `torch`."""

    sizes: list[int] = field(default_factory=lambda: [5000, 20000, 100000])
    """Numbers of Gaussians."""
    images: list[str] = field(default_factory=lambda: ["150x100", "300x200", "600x400"])
    """Image sizes as WIDTHxHEIGHT."""
    backends: list[str] | None = None
    """Backends to time (default: every registered backend usable on the device; `torch` first)."""
    repeats: int = 3
    """Timed steps per configuration (after one warm-up step); the median is reported."""
    threads: int | None = None
    """torch intra-op threads (default: torch's)."""
    device: str = "cpu"
    """Torch device."""
    json: bool = False
    """Print the records as a JSON list instead of a table."""
    output: Path | None = None
    """Also write the JSON records to this file."""


@dataclass
class StepArgs:
    """Full training steps (render, loss, backward, Adam) on the synthetic scene: ms per step, it/s, peak RSS."""

    sizes: list[int] = field(default_factory=lambda: [4000, 20000, 60000])
    """Numbers of Gaussians (the scene's points resampled)."""
    width: int | None = None
    """Image width of the synthetic scene (default: its default, 160)."""
    height: int | None = None
    """Image height of the synthetic scene (default: its default, 120)."""
    backends: list[str] | None = None
    """Backends to time (default: every registered backend usable on the device)."""
    repeats: int = 10
    """Timed steps per configuration (after one warm-up step); the median is reported."""
    threads: int | None = None
    """torch intra-op threads (default: torch's)."""
    device: str = "cpu"
    """Torch device."""
    json: bool = False
    """Print the records as a JSON list instead of a table."""
    output: Path | None = None
    """Also write the JSON records to this file."""


def usable_backends(device: torch.device) -> list[str]:
    from metegs.registry import registry

    names = []
    for name in registry("rasterizer").names():
        available = getattr(registry("rasterizer").get(name), "available", None)
        if available is None or available(device):
            names.append(name)
    return sorted(names, key=lambda n: n != "torch")


def raster(args: RasterArgs) -> list[dict]:
    from metegs.bench.raster import records_as_dicts, run_raster_benchmark

    if args.threads:
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    try:
        images = [tuple(int(v) for v in s.lower().split("x")) for s in args.images]
    except ValueError:
        raise ConfigError(f"--images: expected WIDTHxHEIGHT, got {args.images}") from None
    backends = args.backends or usable_backends(device)
    console = Console(stderr=True)
    console.print(
        f"torch {torch.__version__}, {torch.get_num_threads()} threads, device {device}; backends {', '.join(backends)}"
    )
    with console.status("benchmarking ...") as status:
        records = run_raster_benchmark(
            args.sizes,
            images,
            backends,
            args.repeats,
            device,
            progress=lambda r: status.update(f"done {r.backend} {r.num_gaussians} @ {r.width}x{r.height}"),
        )
    rows = records_as_dicts(records)
    if args.output:
        atomic_write_text(args.output, json.dumps(rows, indent=2))
    if args.json:
        print(json.dumps(rows, indent=2))
        return rows
    ref = {(r["num_gaussians"], r["width"], r["height"]): r for r in rows if r["backend"] == "torch"}
    table = Table(title="rasteriser: forward / forward+backward (median ms), speed-up over torch, peak memory")
    for col in ("backend", "N", "image", "pairs", "fwd ms", "fwd+bwd ms", "x torch (f+b)", "x floor (f+b)", "peak MB"):
        table.add_column(col, justify="right")
    for r in rows:
        key = (r["num_gaussians"], r["width"], r["height"])
        speedup = ref[key]["forward_backward_ms"] / r["forward_backward_ms"] if key in ref else float("nan")
        table.add_row(
            r["backend"],
            str(r["num_gaussians"]),
            f"{r['width']}x{r['height']}",
            str(r["num_intersections"]),
            f"{r['forward_ms']:.1f}",
            f"{r['forward_backward_ms']:.1f}",
            f"{speedup:.1f}",
            f"{r['forward_backward_ms'] / r['floor_ms']:.1f}",
            f"{r['peak_mem_mb']:.0f}",
        )
    Console().print(table)
    return rows


def step(args: StepArgs) -> list[dict]:
    from metegs.bench.step import run_step_benchmark, step_records_as_dicts
    from metegs.engine.config import TrainConfig

    if args.threads:
        torch.set_num_threads(args.threads)
    config = TrainConfig(method="3dgs", device=args.device, threads=args.threads or 0)
    synth = config.dataset.synthetic
    if args.width or args.height:
        synth = replace(synth, width=args.width or synth.width, height=args.height or synth.height)
        config = replace(config, dataset=replace(config.dataset, synthetic=synth, downscale=1))
    backends = args.backends or [b for b in usable_backends(torch.device(args.device))]
    console = Console(stderr=True)
    with console.status("benchmarking training steps ...") as status:
        records = run_step_benchmark(
            config,
            args.sizes,
            backends,
            args.repeats,
            progress=lambda r: status.update(f"done {r.backend} {r.num_gaussians}"),
        )
    rows = step_records_as_dicts(records)
    if args.output:
        atomic_write_text(args.output, json.dumps(rows, indent=2))
    if args.json:
        print(json.dumps(rows, indent=2))
        return rows
    table = Table(title="training step (render + loss + backward + Adam), median")
    for col in ("backend", "N", "image", "ms/step", "it/s", "RSS before MB", "step peak +MB"):
        table.add_column(col, justify="right")
    for r in rows:
        table.add_row(
            r["backend"],
            str(r["num_gaussians"]),
            f"{r['width']}x{r['height']}",
            f"{r['step_ms']:.1f}",
            f"{r['iterations_per_s']:.1f}",
            f"{r['rss_before_mb']:.0f}",
            f"{r['step_peak_mb']:.0f}",
        )
    Console().print(table)
    return rows


def entrypoint() -> None:
    """Console script `metegs-bench`."""

    def main() -> None:
        args = tyro.extras.subcommand_cli_from_dict({"raster": RasterArgs, "step": StepArgs}, prog="metegs-bench")
        if isinstance(args, RasterArgs):
            raster(args)
        else:
            step(args)

    run_cli(main)
