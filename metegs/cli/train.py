"""`metegs-train <method> [flags]`: one tyro subcommand per registered method.

`--config FILE.yaml` (or `--load-config`, anywhere on the line) applies a YAML of overrides, such as a run's
saved config.yml, before the command-line flags, which win.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Any

import tyro
from rich.console import Console

from metegs.cli import run_cli
from metegs.config import apply_overrides
from metegs.engine.run import read_config_file
from metegs.errors import MetegsError
from metegs.registry import registry


def method_configs() -> dict[str, tuple[str, Any]]:
    """name -> (description, default TrainConfig) for every registered method, plugins included."""
    out = {}
    for entry in registry("method").entries():
        try:
            factory = entry.load()
            out[entry.name] = (entry.description or (factory.__doc__ or "").strip(), factory())
        except MetegsError as exc:
            Console(stderr=True).print(f"[yellow]warning:[/] method {entry.name!r} unavailable: {exc}")
    return out


COMPONENT_KINDS = ("weather", "parser", "rasterizer", "meteo_reader", "restorer")
"""Registry kinds listed by ``metegs-train --help`` (methods are the subcommands)."""


def components_help() -> str:
    """One line per registry kind: its registered names, plugins marked with the package that added them."""
    from metegs.registry import failed_plugins

    lines = ["Registered components (plugins in brackets):"]
    for kind in COMPONENT_KINDS:
        names = [e.name if e.source == "metegs" else f"{e.name} [{e.source}]" for e in registry(kind).entries()]
        lines.append(f"  {kind}: {', '.join(names)}")
    lines += [f"  plugin {name!r} failed to load: {why}" for name, why in failed_plugins.items()]
    return "\n".join(lines)


CONFIG_FLAGS = ("--config", "--load-config")
"""Flags of the YAML applied before the command line (``--load-config`` as nerfstudio's ``ns-train`` spells it)."""


def pop_config_flag(argv: list[str]) -> tuple[list[str], Path | None]:
    """Remove ``--config PATH`` / ``--config=PATH`` (or ``--load-config``) from argv; return the rest and the path."""
    rest, path = [], None
    it = iter(range(len(argv)))
    for i in it:
        arg = argv[i]
        flag, eq, value = arg.partition("=")
        if flag in CONFIG_FLAGS and eq:
            path = Path(value)
        elif arg in CONFIG_FLAGS:
            if i + 1 >= len(argv):
                raise MetegsError(f"{arg} needs a YAML file path")
            path = Path(argv[i + 1])
            next(it, None)
        else:
            rest.append(arg)
    return rest, path


LIVE_VIEWER_ENV = {"GOMP_SPINCOUNT": "2000"}
"""OpenMP settings of ``metegs-train --viewer`` (unless the user set them): torch's OpenMP threads sleep after
about 2000 spins instead of 300000 when they wait, so a browser on the same cores does not make every
parallel region of a training step wait for a descheduled thread (docs/benchmark.md has the measurement)."""


def thread_env(argv: list[str]) -> dict[str, str]:
    """Environment variables ``metegs-train`` sets for this command line before torch loads (libgomp reads them
    once, at load)."""
    if "--viewer" not in argv:
        return {}
    return {k: v for k, v in LIVE_VIEWER_ENV.items() if k not in os.environ}


def parse_args(argv: list[str]) -> Any:
    """The TrainConfig that ``argv`` describes."""
    argv, config_path = pop_config_flag(argv)
    methods = method_configs()
    if config_path is not None:
        overrides = read_config_file(config_path)
        saved_method = overrides.pop("method", None)
        chosen = next((a for a in argv if a in methods), saved_method)
        if chosen is None:
            raise MetegsError(f"{config_path}: no method given on the command line or in the file")
        if chosen not in methods:
            raise MetegsError(f"{config_path}: unknown method {chosen!r}; available: {', '.join(methods)}")
        try:
            desc, base = methods[chosen]
            methods[chosen] = (desc, apply_overrides(base, overrides))
        except MetegsError as exc:
            raise MetegsError(f"{config_path}: {exc}") from exc
        if chosen not in argv:
            argv = [chosen, *argv]
    defaults = {name: cfg for name, (_, cfg) in methods.items()}
    descriptions = {name: desc for name, (desc, _) in methods.items()}
    union = tyro.extras.subcommand_type_from_defaults(defaults, descriptions)
    return tyro.cli(
        union,
        args=argv,
        prog="metegs-train",
        config=(tyro.conf.SuppressFixed,),
        description="Train a metegs method. Run `metegs-train <method> --help` for its flags.\n\n" + components_help(),
    )


def main(argv: list[str] | None = None) -> dict:
    console = Console(stderr=True)
    argv = sys.argv[1:] if argv is None else argv
    os.environ.update(thread_env(argv))  # no effect once torch is loaded (when main() is called in-process)
    config = parse_args(argv)
    trainer = config.setup(console=console)
    c = trainer.config
    console.print(
        f"[bold]metegs[/] {c.method} on {trainer.scene.parser} scene "
        f"({len(trainer.dataset.train_indices)} train / {len(trainer.dataset.test_indices)} test views, "
        f"{int(trainer.dataset.cameras.width[0])}x{int(trainer.dataset.cameras.height[0])} px), "
        f"backend [bold]{c.backend}[/] on {c.device}, {len(trainer.model)} initial Gaussians"
    )
    viewer = None
    if getattr(c, "viewer", False):
        from metegs.viewer import start_live_viewer

        viewer = start_live_viewer(trainer, console)
    metrics = trainer.train()
    if viewer is not None:
        viewer.training_finished()
    lp = metrics["lpips"]
    console.print(
        f"[bold green]done[/]: {metrics['train_seconds']:.1f} s training, {metrics['wall_seconds']:.1f} s wall; {metrics['split']} PSNR {metrics['psnr']:.2f} dB, "
        f"SSIM {metrics['ssim']:.4f}, LPIPS "
        + (f"{lp:.4f}" if lp is not None else "null (backbone weights unavailable; the reason is in metrics.json)")
        + f", {metrics['num_gaussians']} Gaussians; wrote {trainer.run_dir}"
    )
    if getattr(c, "compare_baseline", False):
        from metegs.engine.compare import comparison_table, train_baseline, train_blind, write_comparison

        console.print(f"[bold]baseline[/]: plain 3dgs on the same photos -> {trainer.run_dir / 'baseline-3dgs'}")
        rows = {"3dgs": {**train_baseline(trainer, console), "inputs": "photos"}}
        if getattr(trainer, "use_clean", False):  # like for like with 3dgs: the same method without clean references
            console.print(f"[bold]blind[/]: {c.method} without clean references -> {trainer.run_dir / 'blind'}")
            rows[f"{c.method} (blind)"] = {**train_blind(trainer, console), "inputs": "blind"}
            rows[f"{c.method} (clean references)"] = {**metrics, "inputs": "clean"}
        else:
            rows[c.method] = {**metrics, "inputs": "blind"}
        console.print(comparison_table(rows))
        write_comparison(trainer.run_dir / "comparison.json", rows)
        metrics = {**metrics, "baseline": rows["3dgs"], "blind": rows.get(f"{c.method} (blind)")}
    if viewer is not None:
        console.print(f"[bold]viewer[/] still open at {viewer.url}; Ctrl+C quits")
        viewer.serve_forever()
    return metrics


def entrypoint() -> None:
    run_cli(main)


if __name__ == "__main__":
    entrypoint()
