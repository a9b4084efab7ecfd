"""`metegs-bench`: benchmarks.

metegs-bench configs/bench/default.yaml      # a method suite (same as `metegs-bench suite FILE`)
metegs-bench suite --quick                   # the reduced CI suite (configs/bench/quick.yaml)
metegs-bench raster                          # every rasteriser backend, forward / backward
metegs-bench step                            # whole training steps
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Annotated, Literal

import torch
import tyro
from rich.console import Console
from rich.table import Table

from metegs.bench.steal import StealMeter
from metegs.cli import run_cli
from metegs.errors import ConfigError, MetegsError
from metegs.files import atomic_write_text
from metegs.render.select import usable_backends
from metegs.validate import NON_NEGATIVE, Range, check_config

STEAL_WARNING = 0.02
"""Share of CPU time stolen by the hypervisor above which `raster` and `step` print a note."""


@dataclass
class _BenchArgs:
    """Options every benchmark shares."""

    backends: list[str] | None = None
    """Backends to time (default: every registered backend usable on the device; `torch` first)."""
    threads: Annotated[int | None, Range(1)] = None
    """torch intra-op threads (default: torch's)."""
    torch_threads: Annotated[int, NON_NEGATIVE] = 0
    """With the `cpu` backend: threads of torch's own ops (loss, Adam, autograd) while its kernels keep `--threads`
    (0: the same; as `metegs-train --torch-threads`)."""
    device: str = "cpu"
    """Torch device."""
    json: bool = False
    """Print the records as a JSON list instead of a table."""
    output: Path | None = None
    """Also write the JSON records to this file."""

    def __post_init__(self) -> None:
        check_config(self)

    def setup(self) -> list[str]:
        """Apply the thread count and start measuring steal time; -> the backends to time."""
        self._steal = StealMeter()
        if self.threads:
            torch.set_num_threads(self.threads)
        return self.backends or sorted(usable_backends(self.device), key=lambda n: n != "torch")

    def report(self, records: list, table: Table, row: Callable[[dict], list[str]]) -> list[dict]:
        """Write/print the records (JSON, or ``table`` filled by ``row``) -> them as dicts."""
        rows = [asdict(r) for r in records]
        if self.output:
            atomic_write_text(self.output, json.dumps(rows, indent=2))
        if self.json:
            print(json.dumps(rows, indent=2))
        else:
            for r in rows:
                table.add_row(*row(r))
            Console().print(table)
        self.warn_steal()
        return rows

    def warn_steal(self) -> None:
        """On a virtual machine, say how much CPU time the hypervisor took while the benchmark ran."""
        meter = getattr(self, "_steal", None)
        stolen = meter.fraction() if meter is not None else None
        if stolen is not None and stolen >= STEAL_WARNING:
            Console(stderr=True).print(
                f"[yellow]note[/]: the hypervisor gave {100 * stolen:.0f} % of this machine's CPU time to other "
                "machines while this ran (steal time in /proc/stat): the timings are slower and noisier than on an "
                "idle host",
                highlight=False,
            )


@dataclass
class RasterArgs(_BenchArgs):
    """Forward and forward+backward time and peak memory of every rasteriser backend, as ratios over `torch`."""

    sizes: Annotated[list[int], Range(1)] = field(default_factory=lambda: [5000, 20000, 100000])
    """Numbers of Gaussians."""
    images: list[str] = field(default_factory=lambda: ["150x100", "300x200", "600x400"])
    """Image sizes as WIDTHxHEIGHT."""
    repeats: Annotated[int, Range(1)] = 3
    """Timed steps per configuration (after one warm-up step); the median is reported."""


@dataclass
class StepArgs(_BenchArgs):
    """Full training steps (render, loss, backward, Adam) on the synthetic scene: ms per step, it/s, peak RSS."""

    sizes: Annotated[list[int], Range(1)] = field(default_factory=lambda: [4000, 20000, 60000])
    """Numbers of Gaussians (the scene's points resampled)."""
    width: Annotated[int | None, Range(8)] = None
    """Image width of the synthetic scene (default: its default, 160)."""
    height: Annotated[int | None, Range(8)] = None
    """Image height of the synthetic scene (default: its default, 120)."""
    repeats: Annotated[int, Range(1)] = 10
    """Timed steps per configuration (after one warm-up step); the median is reported."""
    methods: list[Literal["3dgs", "metegs-full", "metegs-full-blind"]] = field(
        default_factory=lambda: ["3dgs", "metegs-full", "metegs-full-blind"]
    )
    """Methods whose training steps are timed (`x 3dgs`: each row's time over the 3dgs row's; `x raster`: over the
    rasteriser's render and backward on the same model; `metegs-full-blind`: without clean references)."""


@dataclass
class SuiteArgs:
    """Run a benchmark suite (scenes x conditions x methods) from a YAML file: resumable, gathered into
    results.json, results.md (tables) and plots/ (PSNR against time)."""

    suite: tyro.conf.Positional[Path | None] = None
    """Suite file (configs/bench/*.yaml); none with --quick: configs/bench/quick.yaml."""
    quick: bool = False
    """Run the reduced CI suite (tiny synthetic scene, few steps, one condition) and check its ordering."""
    output: Path | None = None
    """Suite folder (default: the file's `output`, else outputs/bench/<name>)."""
    only_scenes: list[str] | None = None
    """Run only these scenes."""
    only_conditions: list[str] | None = None
    """Run only these conditions."""
    only_methods: list[str] | None = None
    """Run only these methods."""
    fail_fast: bool = False
    """Stop at the first failed run (default: record the failure and go on)."""
    executor: Literal["local", "ray"] = "local"
    """Where the runs go: one after the other here (local), or as tasks of a Ray cluster (ray: pip install -e
    ".[ray]"; each run asks for the suite's or its method's `resources`). Either finishes what the other began."""
    address: str | None = None
    """With --executor ray: the cluster (auto, or ray://HOST:10001); none: start Ray on this machine."""
    dry_run: bool = False
    """Print the plan (runs and their folders) and exit."""
    prepare: bool = False
    """Make only what the weather runs need (the clean-photo runs that give the depth, the degraded and restored
    photos) and train none of them: e.g. here, before the runs go to a GPU machine or a cluster."""
    report_only: bool = False
    """Rebuild results.md and the plots from an existing results.json."""
    fail_on_check: bool = True
    """Exit with status 1 when an expected ordering of the suite's checks fails (--no-fail-on-check: exit 0)."""


QUICK_SUITE = Path(__file__).resolve().parents[2] / "configs" / "bench" / "quick.yaml"
"""The reduced suite `--quick` runs (in a source checkout)."""


def suite(args: SuiteArgs) -> dict:
    from metegs.bench.executors import make_executor
    from metegs.bench.report import write_report
    from metegs.bench.suite import SuiteRunner
    from metegs.bench.suite_config import load_suite

    if args.quick and args.suite is not None:
        raise ConfigError("give a suite file or --quick, not both")
    path = QUICK_SUITE if args.quick else args.suite
    if path is None:
        raise ConfigError("give a suite file (e.g. configs/bench/default.yaml) or --quick")
    if not Path(path).is_file():
        raise ConfigError(
            f"{path}: suite file not found" + (" (--quick needs a source checkout)" if args.quick else "")
        )
    config = load_suite(Path(path))
    console = Console(stderr=True)
    runner = SuiteRunner(
        config,
        output=args.output,
        console=console,
        fail_fast=args.fail_fast,
        only_scenes=args.only_scenes,
        only_conditions=args.only_conditions,
        only_methods=args.only_methods,
    )
    if args.report_only:
        results_path = runner.output / "results.json"
        if not results_path.is_file():
            raise ConfigError(f"{results_path} not found: run the suite first")
        results = json.loads(results_path.read_text())
        write_report(results, runner.output)
        console.print(f"wrote {runner.output / 'results.md'}")
        return results
    if args.dry_run:
        plan = runner.plan()
        for line in plan:
            print(line)
        return {"plan": plan}
    console.print(
        f"[bold]metegs-bench[/] suite {config.name} ({path}): {len(runner.scenes)} scene(s) x "
        f"{len(runner.condition_specs)} condition(s) x {len(runner.methods)} method(s) -> {runner.output}"
    )
    if args.prepare:
        prepared = runner.run(make_executor(args.executor, args.address), prepare=True)
        console.print(f"prepared {len(prepared['prepared'])} job(s) in {prepared['seconds']:.0f} s: {runner.output}")
        if prepared["failed"]:
            raise MetegsError(f"could not prepare {', '.join(prepared['failed'])} (see the log above)")
        return prepared
    results = runner.run(make_executor(args.executor, args.address))
    console.print((runner.output / "results.md").read_text())
    console.print(
        f"[bold]done[/] in {results['total_seconds']:.0f} s: {runner.output / 'results.json'}, "
        f"{runner.output / 'results.md'}, {runner.output / 'plots'}"
    )
    failed_checks = [c for c in results["checks"] if c["passed"] is False]
    if failed_checks:
        lines = ", ".join(f"{c['pair']} ({c['metric']}, {c['scene']}/{c['condition']})" for c in failed_checks)
        console.print(f"[bold red]expected ordering fails[/]: {lines}", highlight=False)
        if args.fail_on_check:
            raise SystemExit(1)
    return results


def _table(title: str, columns: tuple[str, ...]) -> Table:
    table = Table(title=title)
    for col in columns:
        table.add_column(col, justify="right")
    return table


def raster(args: RasterArgs) -> list[dict]:
    from metegs.bench.raster import run_raster_benchmark

    backends = args.setup()
    device = torch.device(args.device)
    try:
        images = [tuple(int(v) for v in s.lower().split("x")) for s in args.images]
    except ValueError:
        images = []
    if not images or any(len(wh) != 2 or min(wh) < 1 for wh in images):
        raise ConfigError(f"--images: expected WIDTHxHEIGHT with sizes of at least 1 pixel, got {args.images}")
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
            torch_threads=args.torch_threads,
            progress=lambda r: status.update(f"done {r.backend} {r.num_gaussians} @ {r.width}x{r.height}"),
        )
    ref = {(r.num_gaussians, r.width, r.height): r.forward_backward_ms for r in records if r.backend == "torch"}

    def row(r: dict) -> list[str]:
        key = (r["num_gaussians"], r["width"], r["height"])
        speedup = f"{ref[key] / r['forward_backward_ms']:.1f}" if key in ref else "-"  # torch not in this run
        return [
            r["backend"],
            str(r["num_gaussians"]),
            f"{r['width']}x{r['height']}",
            str(r["num_intersections"]),
            f"{r['forward_ms']:.1f}",
            f"{r['forward_backward_ms']:.1f}",
            speedup,
            f"{r['forward_backward_ms'] / r['floor_ms']:.1f}",
            "-" if r["machine_floor_ms"] is None else f"{r['forward_backward_ms'] / r['machine_floor_ms']:.1f}",
            "-" if r["machine_peak_gflops"] is None else f"{r['machine_peak_gflops']:.0f}",
            f"{r['peak_mem_mb']:.0f}",
        ]

    table = _table(
        "rasteriser: forward / forward+backward (median ms), speed-up over torch, multiples of the arithmetic floor "
        "at the research note's peak (330 GFLOP/s) and at this machine's peak measured between the steps, peak memory",
        (
            "backend",
            "N",
            "image",
            "pairs",
            "fwd ms",
            "fwd+bwd ms",
            "x torch (f+b)",
            "x floor (f+b)",
            "x floor here (f+b)",
            "peak GFLOP/s here",
            "peak MB",
        ),
    )
    return args.report(records, table, row)


def step(args: StepArgs) -> list[dict]:
    from metegs.bench.step import run_step_benchmark
    from metegs.engine.config import TrainConfig

    backends = args.setup()
    config = TrainConfig(method="3dgs", device=args.device, threads=args.threads or 0, torch_threads=args.torch_threads)
    synth = config.dataset.synthetic
    if args.width or args.height:
        synth = replace(synth, width=args.width or synth.width, height=args.height or synth.height)
        config = replace(config, dataset=replace(config.dataset, synthetic=synth, downscale=1))
    with Console(stderr=True).status("benchmarking training steps ...") as status:
        records = run_step_benchmark(
            config,
            args.sizes,
            backends,
            args.repeats,
            progress=lambda r: status.update(f"done {r.method} {r.backend} {r.num_gaussians}"),
            methods=tuple(args.methods),
        )
    plain = {(r.backend, r.num_gaussians): r.step_ms for r in records if r.method == "3dgs"}

    def row(r: dict) -> list[str]:
        key = (r["backend"], r["num_gaussians"])
        return [
            r["method"],
            r["backend"],
            str(r["num_gaussians"]),
            f"{r['width']}x{r['height']}",
            f"{r['step_ms']:.1f}",
            f"{r['step_ms'] / plain[key]:.2f}" if key in plain else "-",
            f"{r['raster_ms']:.1f}",
            f"{r['step_ms'] / r['raster_ms']:.2f}",
            f"{r['iterations_per_s']:.1f}",
            f"{r['rss_before_mb']:.0f}",
            f"{r['step_peak_mb']:.0f}",
        ]

    table = _table(
        "training step of each method (mid-run, no refinement due), median",
        (
            "method",
            "backend",
            "N",
            "image",
            "ms/step",
            "x 3dgs",
            "raster ms",
            "x raster",
            "it/s",
            "RSS before MB",
            "step peak +MB",
        ),
    )
    return args.report(records, table, row)


def entrypoint() -> None:
    """Console script `metegs-bench`."""

    def main() -> None:
        import sys

        argv = sys.argv[1:]
        if (
            argv
            and argv[0] not in ("raster", "step", "suite")
            and (argv[0].endswith((".yaml", ".yml")) or argv[0] == "--quick")
        ):
            argv = ["suite", *argv]  # `metegs-bench FILE.yaml` and `metegs-bench --quick` run a suite
        args = tyro.extras.subcommand_cli_from_dict(
            {"suite": SuiteArgs, "raster": RasterArgs, "step": StepArgs}, prog="metegs-bench", args=argv
        )
        if isinstance(args, SuiteArgs):
            suite(args)
        elif isinstance(args, RasterArgs):
            raster(args)
        else:
            step(args)

    run_cli(main)
