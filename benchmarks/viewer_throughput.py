"""Training throughput with the live viewer open in a browser, as a ratio of throughput without it.

    python benchmarks/viewer_throughput.py                    # 2 threads, 3 repetitions, synthetic 160x120
    python benchmarks/viewer_throughput.py --threads 1 --steps 300 --repeats 5 --json out.json
    python benchmarks/viewer_throughput.py --env GOMP_SPINCOUNT=0   # an OpenMP setting for both modes

Each repetition trains `3dgs` on the built-in synthetic scene twice, once alone and once with `metegs-train
--viewer`'s live viewer attached and a headless Chromium showing it (the user watching the clean render while
it trains). Each run is its own Python process started with the environment `metegs-train` gives that mode
(`metegs.cli.train.thread_env`: the viewer mode sets a short OpenMP spin, which libgomp reads only when
torch loads), so the ratio is that of the two commands a user runs. Steps/s are measured from step 20 on
(after the page's start-up), and the table reports the median of each mode and the ratio. Needs Chromium and
chromedriver (Debian: ``apt-get install chromium chromium-driver``) and selenium.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

from rich.console import Console
from rich.table import Table

WARMUP_STEPS = 20
"""Steps not timed (Gaussian growth starts, caches fill, the page settles)."""


def browser(window: str = "1280,800"):
    """A headless Chromium driven by selenium. window: "WIDTH,HEIGHT" in CSS pixels."""
    from selenium import webdriver
    from selenium.webdriver.chrome.options import Options
    from selenium.webdriver.chrome.service import Service

    options = Options()
    for arg in (
        "--headless=new",
        "--no-sandbox",
        "--disable-gpu",
        f"--window-size={window}",
        "--disable-dev-shm-usage",
    ):
        options.add_argument(arg)
    binary = shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")
    if binary:
        options.binary_location = binary
    return webdriver.Chrome(service=Service(shutil.which("chromedriver")), options=options)


def browser_cpu_seconds() -> float:
    """CPU time (user + system, s) used so far by every running Chromium process of this machine."""
    total = 0
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            if b"chrom" not in Path(f"/proc/{pid}/cmdline").read_bytes():
                continue
            fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        total += int(fields[11]) + int(fields[12])
    return total / os.sysconf("SC_CLK_TCK")


def train_rate(
    steps: int,
    threads: int,
    with_viewer: bool,
    out: Path,
    settle_s: float,
    window: str,
    with_browser: bool = True,
    viewer_options: dict | None = None,
) -> dict:
    """Steps/s of one 3dgs run after the warm-up, with or without the viewer and a browser on it."""
    from metegs.data.config import DatasetConfig, SyntheticSceneConfig
    from metegs.registry import registry

    base = registry("method").get("3dgs")()
    config = replace(
        base,
        max_steps=steps,
        output_dir=out,
        experiment_name="viewer" if with_viewer else "alone",
        progress=False,
        dataset=DatasetConfig(synthetic=SyntheticSceneConfig()),
        eval_every=0.0,
        checkpoint_every=0,
        save_renders=False,
        device="cpu",
        threads=threads,
    )
    trainer = config.setup()
    stamps: list[tuple[int, float]] = []
    trainer.step_hooks.append(lambda tr, stats: stamps.append((tr.step, time.perf_counter())))
    viewer = driver = None
    if with_viewer:
        from metegs.viewer import Viewer, ViewerConfig

        viewer = Viewer(trainer, ViewerConfig(port=0, **(viewer_options or {})), live=True)
        if with_browser:
            driver = browser(window)
            driver.get(viewer.url)
        if with_browser and not viewer.wait_for_frames(1, 60):
            raise RuntimeError("the browser showed no frame within 60 s")
        time.sleep(settle_s)  # the page's one-off start-up is not a training-time cost
    cpu0, wall0 = browser_cpu_seconds(), time.perf_counter()
    try:
        trainer.train()
    finally:
        frames = None if viewer is None else viewer.stats.count
        browser_share = (browser_cpu_seconds() - cpu0) / (time.perf_counter() - wall0) if with_viewer else None
        if viewer is not None:
            viewer.training_finished()
            if driver is not None:
                driver.quit()
            viewer.close()
    (s0, t0), (s1, t1) = next(p for p in stamps if p[0] >= WARMUP_STEPS), stamps[-1]
    return {
        "viewer": with_viewer,
        "it_s": (s1 - s0) / (t1 - t0),
        "frames": frames,
        "gaussians": len(trainer.model),
        "browser_cpu": browser_share,
        "browser": with_browser,
    }


def viewer_options(pairs: list[str]) -> dict:
    """--viewer FIELD=VALUE pairs -> ViewerConfig keyword arguments (values parsed as YAML scalars)."""
    import yaml

    from metegs.meteo.readers import parse_options

    return {key: yaml.safe_load(value) for key, value in parse_options(pairs, "--viewer").items()}


def run_worker(mode: str, args: argparse.Namespace, out: Path) -> dict:
    """One training run of ``mode`` ("alone" or "viewer") in a fresh process; its record."""
    from metegs.cli.train import thread_env
    from metegs.meteo.readers import parse_options

    env = dict(os.environ)
    env.update(parse_options(args.env, "--env"))
    if mode == "viewer":
        env.update({k: v for k, v in thread_env(["--viewer"]).items() if k not in env})
    cmd = [
        sys.executable,
        __file__,
        "--worker",
        mode,
        "--steps",
        str(args.steps),
        "--threads",
        str(args.threads),
        "--settle",
        str(args.settle),
        "--window",
        args.window,
        "--out",
        str(out),
    ]
    cmd += ["--no-browser"] if args.no_browser else []
    for kv in args.viewer:
        cmd += ["--viewer", kv]
    done = subprocess.run(cmd, env=env, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"{mode} run failed:\n{done.stderr[-3000:]}")
    record = json.loads(done.stdout.strip().splitlines()[-1])
    record["env"] = {k: env[k] for k in sorted(env) if k.startswith(("GOMP_", "OMP_"))}
    return record


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=2, help="torch threads of training (0: torch's default)")
    parser.add_argument("--steps", type=int, default=300, help="training steps per run")
    parser.add_argument("--repeats", type=int, default=3, help="repetitions of each mode (alternating)")
    parser.add_argument("--settle", type=float, default=10.0, help="seconds for the page to start before training")
    parser.add_argument("--window", default="1280,800", help="browser window size WIDTH,HEIGHT (CSS pixels)")
    parser.add_argument("--no-browser", action="store_true", help="attach the viewer but open no browser on it")
    parser.add_argument(
        "--viewer",
        action="append",
        default=[],
        metavar="FIELD=VALUE",
        help="a ViewerConfig field for the watched runs (repeatable), e.g. live_refresh_s=6",
    )
    parser.add_argument(
        "--env",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="environment variable for both modes' processes (repeatable), e.g. GOMP_SPINCOUNT=0",
    )
    parser.add_argument("--json", type=Path, default=None, help="also write the records and the summary here")
    parser.add_argument("--worker", choices=("alone", "viewer"), default=None, help=argparse.SUPPRESS)
    parser.add_argument("--out", type=Path, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker is not None:  # one run, in this process: its record on the last stdout line
        rec = train_rate(
            args.steps,
            args.threads,
            args.worker == "viewer",
            args.out,
            args.settle,
            args.window,
            not args.no_browser,
            viewer_options(args.viewer),
        )
        print(json.dumps(rec))
        return
    from metegs.errors import ConfigError
    from metegs.meteo.readers import parse_options

    try:  # checked here, before any run starts
        parse_options(args.env, "--env")
        viewer_options(args.viewer)
    except ConfigError as exc:
        parser.error(str(exc))
    console = Console()
    records = []
    with tempfile.TemporaryDirectory() as tmp:
        for rep in range(args.repeats):
            for mode in ("alone", "viewer"):
                rec = run_worker(mode, args, Path(tmp))
                records.append({**rec, "repeat": rep})
                console.print(
                    f"repeat {rep}: {mode} {rec['it_s']:.2f} it/s, frames {rec['frames']}"
                    + ("" if rec["browser_cpu"] is None else f", browser {rec['browser_cpu']:.2f} of a core")
                    + (f", {rec['env']}" if rec["env"] else "")
                )
    alone = statistics.median(r["it_s"] for r in records if not r["viewer"])
    watched = statistics.median(r["it_s"] for r in records if r["viewer"])
    browser_cpu = [r["browser_cpu"] for r in records if r["browser_cpu"] is not None]
    summary = {
        "threads": args.threads,
        "steps": args.steps,
        "env": args.env,
        "alone_it_s": alone,
        "viewer_it_s": watched,
        "ratio": watched / alone,
        "loss_percent": 100 * (1 - watched / alone),
        "browser_cpu": statistics.median(browser_cpu) if browser_cpu else None,
    }
    table = Table(title=f"3dgs on the synthetic scene, {args.threads} thread(s), median of {args.repeats}")
    for col in ("mode", "it/s", "ratio"):
        table.add_column(col, justify="right")
    table.add_row("no viewer", f"{alone:.2f}", "1.00")
    table.add_row("viewer" + ("" if args.no_browser else " + browser"), f"{watched:.2f}", f"{watched / alone:.2f}")
    console.print(table)
    console.print(f"throughput loss with the viewer open: {summary['loss_percent']:.1f} %")
    if args.json is not None:
        args.json.write_text(json.dumps({"records": records, "summary": summary}, indent=1) + "\n")


if __name__ == "__main__":
    main()
