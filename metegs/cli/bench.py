"""`metegs-bench`: benchmarks. `metegs-bench raster` times every rasteriser backend in one process."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
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


def entrypoint() -> None:
    """Console script `metegs-bench`."""

    def main() -> None:
        args = tyro.extras.subcommand_cli_from_dict({"raster": RasterArgs}, prog="metegs-bench")
        if isinstance(args, RasterArgs):
            raster(args)

    run_cli(main)
