"""Run a benchmark suite: scenes x conditions x methods, each run in its own folder, gathered into results.json.

Layout of the suite folder (``output``):

    conditions.json                       the conditions: records, times, picks, θ per scene
    results.json  results.md  plots/      every run's metrics and curves; the tables; PSNR-vs-time PNGs
    <scene>/clean/<method>/               runs on the clean photos (once per scene; also the depth of
                                          scenes from files)
    <scene>/<condition>/data/             the degraded photos + clean references (metegs-synth)
    <scene>/<condition>/condition.json    record, time and θ of this condition for this scene
    <scene>/<condition>/restored-<name>/  the degraded photos through a 2D restorer (nerfstudio dataset)
    <scene>/<condition>/<method>/         one training run (config.yml, metrics.json, bench.json, ...)

A run whose ``metrics.json`` and ``bench.json`` exist is not repeated; an interrupted run resumes from its
latest checkpoint. Every run evaluates the test views at step 0 and every ``eval_every`` of its
schedule (``metrics.json`` ``history``: PSNR / SSIM against training seconds), and the final model's
render speed is timed over the test views (``bench.json``).

The suite is a list of jobs (`Job`: a run, the depth source of a scene from files, a condition's degraded or restored
photos) that `SuiteRunner.perform` does one at a time, given the values of the jobs it needs; `metegs.bench.executors`
runs them here one after the other, or as tasks of a Ray cluster.
"""

from __future__ import annotations

import json
import math
import os
import platform
import time
import traceback
from dataclasses import dataclass, field, replace
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import torch
from rich.console import Console

from metegs.bench.conditions import ResolvedCondition, resolve_condition
from metegs.bench.memory import sync
from metegs.bench.suite_config import MethodSpec, SceneSpec, SuiteConfig
from metegs.config import apply_overrides, to_dict
from metegs.errors import ConfigError, MetegsError
from metegs.files import atomic_write_text, same_files

DEFAULT_RESTORERS = {"rain": "kang2012", "fog": "dcp"}
"""The 2D restorer of each weather kind for methods on restored photos that name none."""

RESULT_KEYS = ("psnr", "ssim", "lpips", "lpips_reason", "num_gaussians", "train_seconds", "steps", "reference")


@dataclass(frozen=True)
class Job:
    """One step of a suite: a training run, or what runs need (the depth source, degraded or restored photos)."""

    key: str
    """Unique name, its folder in the suite (``<scene>/<condition>/<method>``, ``<scene>/<condition>/data`` ...)."""
    action: str
    """``clean`` (a run on the clean photos), ``depth``, ``data`` (degraded photos), ``restore``, ``run`` or ``peer``
    (another toolkit's PLY scored like a run)."""
    scene: str
    condition: str | None = None
    method: str | None = None
    deps: tuple[str, ...] = ()
    """Keys of the jobs whose values it needs, in order."""
    resources: dict[str, float] = field(default_factory=dict)
    """What it asks a cluster for: ``cpus``, ``gpus`` (the suite's ``resources``, or its method's)."""


@dataclass
class JobResult:
    """What a job gives back: its value for the jobs that need it, and the run records it made."""

    value: Any
    records: list[dict] = field(default_factory=list)
    support: list[dict] = field(default_factory=list)
    thetas: dict[str, dict[str, Any]] = field(default_factory=dict)


@torch.no_grad()
def render_fps(trainer, repeats: int = 3) -> tuple[float | None, int]:
    """(frames per second, views timed) of the trainer's current model over its test views (clean branch)."""
    idx = list(trainer.dataset.test_indices or trainer.dataset.train_indices)
    if not idx or repeats <= 0:
        return None, 0
    trainer.render(idx[0])  # warm-up (kernels, caches)
    sync(trainer.device)
    t0 = time.perf_counter()
    for _ in range(repeats):
        for i in idx:
            trainer.render(i)
    sync(trainer.device)
    elapsed = time.perf_counter() - t0
    return (repeats * len(idx) / elapsed if elapsed > 0 else None), len(idx)


def latest_checkpoint(run_dir: Path) -> Path | None:
    ckpts = sorted((Path(run_dir) / "checkpoints").glob("step-*.ckpt"))
    return ckpts[-1] if ckpts else None


VOLATILE_FIELDS = (
    "load_checkpoint",
    "progress",
    "backend",
    "device",
    "threads",
    "output_dir",
    "experiment_name",
    "lpips_download",
)
"""Run-config fields that may differ between a finished run and the suite without making it another run (whether
LPIPS may download its backbone changes no training)."""


def config_changes(run_dir: Path, config) -> list[str]:
    """Config fields whose value in ``run_dir/config.yml`` differs from ``config``, as dotted paths to the values that
    differ (``dataset.auto_max_side``; empty: same). Top-level fields in `VOLATILE_FIELDS` are left out."""
    from metegs.config import load_yaml
    from metegs.data.config import auto_max_side

    path = Path(run_dir) / "config.yml"
    if not path.is_file():
        return []
    saved = load_yaml(path)
    if config.dataset.auto_max_side is None:  # the run recorded the size its device chose
        size = auto_max_side(config.dataset, str(saved.get("device", "cpu")))
        config = replace(config, dataset=replace(config.dataset, auto_max_side=size))
    now = json.loads(json.dumps(to_dict(config), default=str))
    saved = json.loads(json.dumps(saved, default=str))
    return sorted(
        path
        for k, v in now.items()
        if k not in VOLATILE_FIELDS and k in saved
        for path, was, is_now in _differing_values(saved[k], v, k)
        if not _same_input(was, is_now)
    )


def _differing_values(saved: Any, now: Any, path: str) -> list[tuple[str, Any, Any]]:
    """(dotted path, saved value, value now) under ``path`` where the plain values ``saved`` and ``now`` differ
    (nested dicts compared key by key; a key only one side has is left out, as a field added since the run was
    made)."""
    if isinstance(saved, dict) and isinstance(now, dict):
        return [d for k in now if k in saved for d in _differing_values(saved[k], now[k], f"{path}.{k}")]
    return [] if saved == now else [(path, saved, now)]


def _same_input(saved: Any, now: Any) -> bool:
    """Whether two differing values name files or folders with the same contents: a suite folder copied or moved
    elsewhere still holds the photos its runs were made from. Only values with a path separator are looked up, so
    that a plain word (``method: 3dgs``) is never read as a file of the working folder."""
    paths = (saved, now)
    return all(isinstance(v, str) for v in paths) and any(os.sep in v for v in paths) and same_files(saved, now)


def _finite(v: Any) -> Any:
    return None if isinstance(v, float) and not math.isfinite(v) else v


class SuiteRunner:
    """Runs a `SuiteConfig` into ``output`` (see the module docstring)."""

    def __init__(
        self,
        suite: SuiteConfig,
        output: Path | None = None,
        console: Console | None = None,
        fail_fast: bool = False,
        only_scenes: list[str] | None = None,
        only_conditions: list[str] | None = None,
        only_methods: list[str] | None = None,
    ):
        self.suite = suite
        self.output = Path(output or suite.output or Path("outputs") / "bench" / suite.name)
        self.console = console or Console(stderr=True)
        self.fail_fast = fail_fast
        for what, given, known in (
            ("scene", only_scenes, [s.name for s in suite.scenes]),
            ("condition", only_conditions, [c.name for c in suite.conditions]),
            ("method", only_methods, [m.name for m in suite.methods]),
        ):
            unknown = sorted(set(given or []) - set(known))
            if unknown:
                raise ConfigError(f"--only-{what}s: unknown {what}(s) {unknown}; the suite has {known}")
        self.scenes = [s for s in suite.scenes if not only_scenes or s.name in only_scenes]
        self.condition_specs = [c for c in suite.conditions if not only_conditions or c.name in only_conditions]
        self.methods = [m for m in suite.methods if not only_methods or m.name in only_methods]
        self.records: list[dict] = []
        self.support: list[dict] = []
        self.thetas: dict[str, dict[str, Any]] = {}
        self.resolved: dict[str, ResolvedCondition] = {}
        """The suite's conditions as runs take them (`resolve_conditions`, set by `run`)."""
        self.job_threads = 0
        """Threads of the job being performed (0: the suite's)."""

    # --- configs -----------------------------------------------------------------------------------
    def method_config(self, scene: SceneSpec, method: MethodSpec, **fields):
        """The run config: the method's defaults <- suite ``train`` <- scene ``train`` <- method ``overrides``
        <- the suite's (or the row's) seed, the suite's backend/device/threads/eval_every <- ``fields``."""
        from metegs.registry import registry

        s = self.suite
        config = registry("method").get(method.method)()
        layers = (
            (s.train, "train"),
            (scene.train, f"scenes[{scene.name}].train"),
            (method.overrides, f"methods[{method.name}].overrides"),
        )
        for layer, where in layers:
            try:
                config = apply_overrides(config, layer or {})
            except MetegsError as exc:
                raise ConfigError(f"{s.where}: {where}: {exc}") from exc
        config = replace(
            config,
            seed=s.seed if method.seed is None else method.seed,
            backend=s.backend,
            device=s.device,
            threads=self.job_threads or s.threads,
            eval_every=s.eval_every,
            progress=self.console.is_terminal,  # a bar per run in a terminal; logs get a line as each run starts
            degrade="off",
            data=scene.data,
            parser=scene.parser,
            output_dir=self.output,
        )
        if hasattr(config, "compare_baseline"):
            config = replace(config, compare_baseline=False)
        return replace(config, **fields)

    def dataset_config(self, scene: SceneSpec):
        from metegs.registry import registry

        base = registry("method").get("3dgs")()
        for layer in (self.suite.train, scene.train):
            base = apply_overrides(base, {"dataset": (layer or {}).get("dataset", {})})
        return base.dataset

    # --- conditions --------------------------------------------------------------------------------
    def resolve_conditions(self) -> dict[str, ResolvedCondition]:
        """Every condition of the suite, picked from its records (cached in conditions.json by spec)."""
        from metegs.weather.conditions import ConditionsConfig

        cache_path = self.output / "conditions.json"
        cache = json.loads(cache_path.read_text()).get("conditions", {}) if cache_path.is_file() else {}
        base = self.suite.source.parent if self.suite.source else None
        resolved = {}
        for spec in self.condition_specs:
            key = to_dict(spec)
            hit = cache.get(spec.name)
            if hit and hit.get("spec") == key:
                c = dict(hit["conditions"])
                c["record"] = None if c.get("record") is None else Path(c["record"])
                prov = {k: v for k, v in hit.items() if k in ("rain", "fog")}
                resolved[spec.name] = ResolvedCondition(spec.name, spec.kind, ConditionsConfig(**c), prov, spec.family)
                continue
            resolved[spec.name] = resolve_condition(spec, base)
            self.console.print(f"condition {spec.name}: {_describe_pick(resolved[spec.name])}", highlight=False)
        return resolved

    def write_conditions(self, resolved: dict[str, ResolvedCondition]) -> None:
        record = {
            name: {
                "spec": to_dict(next(c for c in self.condition_specs if c.name == name)),
                **r.to_dict(),
                "theta": self.thetas.get(name, {}),
            }
            for name, r in resolved.items()
        }
        atomic_write_text(self.output / "conditions.json", json.dumps({"conditions": record}, indent=1, default=str))

    # --- runs --------------------------------------------------------------------------------------
    def execute(
        self,
        scene: SceneSpec,
        method: MethodSpec,
        condition: str | None,
        run_dir: Path,
        config,
        extra: dict[str, Any] | None = None,
        support: bool = False,
    ) -> dict:
        """Train (or reuse) one run; its record."""
        extra = dict(extra or {})
        label = f"{scene.name} / {condition or 'clean'} / {method.name}"
        metrics_path, bench_path = run_dir / "metrics.json", run_dir / "bench.json"
        t0 = time.perf_counter()
        try:
            if metrics_path.is_file() and bench_path.is_file():
                status = "cached"
            elif metrics_path.is_file():  # finished, render speed not yet timed
                from metegs.engine.run import load_run

                trainer = load_run(run_dir, device=None)
                fps, views = render_fps(trainer, self.suite.fps_repeats)
                self._write_bench(bench_path, scene, method, condition, extra, fps, views, trainer.config, t0)
                status = "done"
            else:
                resume = latest_checkpoint(run_dir)
                if resume is not None:
                    config = replace(config, load_checkpoint=resume)
                    self.console.print(f"[dim]{label}: resuming from {resume.name}[/]")
                trainer = config.setup(run_dir=run_dir, console=None)
                self.console.print(f"[dim]{label}: training {trainer.config.max_steps} steps[/]", highlight=False)
                if resume is None:
                    trainer.record_eval(quick=True)  # the curve's first point: the initial model at 0 s
                trainer.train()
                fps, views = render_fps(trainer, self.suite.fps_repeats)
                self._write_bench(bench_path, scene, method, condition, extra, fps, views, trainer.config, t0)
                status = "done"
        except MetegsError as exc:
            if self.fail_fast:
                raise
            return self._failed(scene, method, condition, run_dir, f"{type(exc).__name__}: {exc}", support)
        except Exception as exc:  # noqa: BLE001 - one broken run must not end a suite of hours
            if self.fail_fast:
                raise
            tb = traceback.format_exc(limit=6)
            return self._failed(scene, method, condition, run_dir, f"{type(exc).__name__}: {exc}\n{tb}", support)
        record = self._record(scene, method, condition, run_dir, status)
        if status == "cached":
            changed = config_changes(run_dir, config)
            if changed:
                record["config_changed"] = changed
                self.console.print(
                    f"[yellow]{label}: reused, but the suite now sets {', '.join(changed)} otherwise than the run "
                    f"was made with; delete {run_dir} to train it again[/]",
                    highlight=False,
                )
        (self.support if support else self.records).append(record)
        return record

    def announce(self, record: dict) -> None:
        """One line for a run that ended (what the local and the Ray executors print as each run ends)."""
        label = f"{record['scene']} / {record['condition'] or 'clean'} / {record['method']}"
        log = f" (log: {record['log']})" if record.get("log") else ""
        if record["status"] in ("failed", "skipped"):
            first = str(record.get("error", "")).splitlines()[0] if record.get("error") else ""
            self.console.print(f"[red]{label}: {record['status']}[/]: {first}{log}", highlight=False)
            return
        verb = "reused" if record["status"] == "cached" else f"done in {record.get('wall_seconds') or 0:.0f} s"
        train = record.get("train_seconds")
        self.console.print(
            f"{label}: {verb}; PSNR {record['psnr']:.2f} dB, SSIM {record['ssim']:.4f}, {record['num_gaussians']} "
            f"Gaussians, " + (f"train {train:.1f} s" if train is not None else "scored (trained elsewhere)"),
            highlight=False,
        )

    def _write_bench(self, path, scene, method, condition, extra, fps, views, config, started: float) -> None:
        record = {
            "suite": self.suite.name,
            "scene": scene.name,
            "condition": condition,
            "method": method.name,
            "registered_method": method.method,
            "photos": method.photos,
            "render_fps": fps,
            "render_fps_views": views,
            "render_fps_repeats": self.suite.fps_repeats,
            "backend": getattr(config, "backend", None),
            "device": getattr(config, "device", None),
            "wall_seconds": round(time.perf_counter() - started, 3),  # this invocation: setup, training, evaluation
            **extra,
        }
        atomic_write_text(path, json.dumps(record, indent=2, default=str))

    def _record(self, scene, method, condition, run_dir: Path, status: str) -> dict:
        metrics = json.loads((run_dir / "metrics.json").read_text())
        bench = json.loads((run_dir / "bench.json").read_text())
        pre = float(bench.get("preprocess_seconds") or 0.0)
        history = [
            {
                "step": h.get("step"),
                "train_seconds": h.get("train_seconds"),
                "time_seconds": None if h.get("train_seconds") is None else round(h["train_seconds"] + pre, 3),
                "psnr": _finite(h.get("psnr")),
                "ssim": _finite(h.get("ssim")),
                "num_gaussians": h.get("num_gaussians"),
            }
            for h in metrics.get("history", [])
        ]
        record = {
            **self._identity(scene, method, condition, run_dir, status),
            **{k: _finite(metrics.get(k)) for k in RESULT_KEYS},
            "preprocess_seconds": pre,
            "time_seconds": round(float(metrics.get("train_seconds") or 0.0) + pre, 3),
            "render_fps": bench.get("render_fps"),
            "wall_seconds": bench.get("wall_seconds"),
            "restorer": bench.get("restorer"),
            "image_size": metrics.get("image_size"),
            "history": history,
        }
        if record["psnr"] is None or record["ssim"] is None:
            record["status"] = "failed"
            record["error"] = "the final metrics are not finite (NaN/Inf): see the run's metrics.json"
        return record

    def _identity(self, scene, method, condition, run_dir, status: str) -> dict:
        """The fields naming a run in results.json (what, where, and how it ended)."""
        return {
            "scene": scene.name,
            "condition": condition,
            "method": method.name,
            "label": method.label or method.name,
            "group": method.group,
            "oracle": method.oracle,
            "photos": method.photos,
            "status": status,
            "run_dir": _rel(run_dir, self.output),
        }

    def _failed(self, scene, method, condition, run_dir, error: str, support: bool = False, status="failed") -> dict:
        record = {
            **self._identity(scene, method, condition, run_dir, status),
            "error": error,
        }
        (self.support if support else self.records).append(record)
        return record

    # --- the suite ---------------------------------------------------------------------------------
    def plan(self) -> list[str]:
        """One line per run the suite would make: where it goes and whether it is already finished."""
        lines = []

        def state(run_dir: Path) -> str:
            if (run_dir / "metrics.json").is_file():
                return "finished"
            return "resumes" if latest_checkpoint(run_dir) is not None else "to run"

        keys = {j.key: j for j in self.plan_jobs()}
        for key, job in keys.items():
            if job.action == "peer":
                d = self.output / key
                done = "scored" if (d / "eval.json").is_file() else "to score"
                lines.append(
                    f"{key.replace('/', ' / ')}: {d} ({done} from {self.suite.method(job.method).peer['ply']})"
                )
        for scene in self.scenes:
            methods = [m for m in self.methods if m.runs_on(scene.name, None) and m.peer is None]
            for m in (m for m in methods if m.photos == "clean"):
                d = self.output / scene.name / "clean" / m.name
                lines.append(f"{scene.name} / clean / {m.name}: {d} ({state(d)})")
            for spec in self.conditions_of(scene):
                for m in (m for m in methods if m.photos != "clean" and m.runs_on(scene.name, spec.name)):
                    d = self.output / scene.name / spec.name / m.name
                    lines.append(f"{scene.name} / {spec.name} / {m.name}: {d} ({state(d)})")
        return lines

    def conditions_of(self, scene: SceneSpec) -> list:
        """The suite's (selected) condition specs that run on ``scene``."""
        return [c for c in self.condition_specs if scene.conditions is None or c.name in scene.conditions]

    def run(self, executor=None, prepare: bool = False) -> dict:
        """Run the suite's jobs (`plan_jobs`) on ``executor`` (default: `LocalExecutor`, one after the other in this
        process) and gather the results; every executor resumes from the same suite folder. ``prepare``: only what
        the weather runs need (clean-photo runs, depth, degraded and restored photos), no results written."""
        from metegs.bench.executors import LocalExecutor
        from metegs.bench.report import write_report

        started = time.perf_counter()
        self.output.mkdir(parents=True, exist_ok=True)
        if self.suite.threads > 0:
            torch.set_num_threads(self.suite.threads)
        conditions = self.resolve_conditions()
        self.resolved = conditions
        self.write_conditions(conditions)
        jobs = self.plan_jobs()
        if prepare:
            jobs = [j for j in jobs if j.action not in ("run", "peer")]
        outputs = (executor or LocalExecutor()).run(self, jobs)
        self.records, self.support, self.thetas = [], [], {}
        for job in jobs:  # in plan order, whichever order the jobs ended in
            out = outputs[job.key]
            self.records += out.records
            self.support += out.support
            for name, by_scene in out.thetas.items():
                self.thetas.setdefault(name, {}).update(by_scene)
        self.write_conditions(conditions)
        if prepare:
            failed = [j.key for j in jobs if isinstance(outputs[j.key].value, dict) and "error" in outputs[j.key].value]
            return {"prepared": [j.key for j in jobs], "failed": failed, "seconds": time.perf_counter() - started}
        earlier, earlier_conditions = self.earlier_records()
        self.records = earlier + self.records
        results = self.results(conditions, time.perf_counter() - started)
        results["runs_from_earlier_calls"] = len(earlier)
        merged = {**earlier_conditions, **results["conditions"]}
        results["conditions"] = {c.name: merged[c.name] for c in self.suite.conditions if c.name in merged}
        atomic_write_text(self.output / "results.json", json.dumps(results, indent=1, default=str))
        write_report(results, self.output)
        return results

    def earlier_records(self) -> tuple[list[dict], dict[str, dict]]:
        """The records of the folder's results.json that this call did not redo and that still stand: the suite
        still has their scene, condition and row, and a finished run's metrics are still on disk. So a call limited
        by ``--only-…`` adds to the report of earlier sittings instead of replacing it. Also their conditions."""
        path = self.output / "results.json"
        try:
            earlier = json.loads(path.read_text()) if path.is_file() else {}
            old, old_conditions = list(earlier.get("runs", [])), dict(earlier.get("conditions", {}))
        except (OSError, ValueError, TypeError, AttributeError):
            return [], {}  # unreadable: this call's report stands alone
        redone = {(r["scene"], r["condition"], r["method"]) for r in self.records}
        scenes = {s.name for s in self.suite.scenes}
        conditions = {c.name for c in self.suite.conditions}
        methods = {m.name for m in self.suite.methods}
        kept = []
        for r in old:
            key = (r.get("scene"), r.get("condition"), r.get("method"))
            if key in redone or key[0] not in scenes or key[2] not in methods:
                continue
            if key[1] is not None and key[1] not in conditions:
                continue
            if (
                r.get("status") in ("done", "cached")
                and not (self.output / str(r.get("run_dir")) / "metrics.json").is_file()
            ):
                continue
            kept.append(r)
        return kept, {k: v for k, v in old_conditions.items() if any(r["condition"] == k for r in kept)}

    # --- jobs --------------------------------------------------------------------------------------
    def plan_jobs(self) -> list[Job]:
        """Every job of the suite in an order that runs each after the jobs it needs: per scene its clean-photo
        runs, the depth source (a scene from files), then per condition the degraded data, the restored photos
        and the runs on them."""
        jobs: list[Job] = []
        default = self.suite.resources
        for scene in self.scenes:
            methods = [m for m in self.methods if m.runs_on(scene.name, None) and m.peer is None]
            clean = []
            for m in (m for m in methods if m.photos == "clean"):
                key = f"{scene.name}/clean/{m.name}"
                jobs.append(Job(key, "clean", scene.name, method=m.name, resources=m.resources or default))
                clean.append(key)
            jobs += self._peer_jobs(scene, None, [m for m in methods if m.photos == "clean"])
            weather_methods = [m for m in methods if m.photos != "clean"]
            needs_depth = not scene.in_memory and any(
                m.runs_on(scene.name, c.name) for m in weather_methods for c in self.conditions_of(scene)
            )
            depth = ()
            if needs_depth:
                jobs.append(Job(f"{scene.name}/depth", "depth", scene.name, deps=tuple(clean), resources=default))
                depth = (f"{scene.name}/depth",)
            for spec in self.conditions_of(scene):
                here = [m for m in weather_methods if m.runs_on(scene.name, spec.name)]
                if not here:
                    continue
                data = f"{scene.name}/{spec.name}/data"
                jobs.append(Job(data, "data", scene.name, spec.name, deps=depth, resources=default))
                restores: dict[str, str] = {}
                for m in (m for m in here if m.photos == "restored"):
                    folder = self.restored_folder(spec.kind, m)
                    if folder not in restores:
                        restores[folder] = f"{scene.name}/{spec.name}/{folder}"
                        jobs.append(Job(restores[folder], "restore", scene.name, spec.name, m.name, (data,), default))
                for m in here:
                    deps = (data,) + ((restores[self.restored_folder(spec.kind, m)],) if m.photos == "restored" else ())
                    key = f"{scene.name}/{spec.name}/{m.name}"
                    jobs.append(Job(key, "run", scene.name, spec.name, m.name, deps, m.resources or default))
                jobs += self._peer_jobs(scene, spec.name, here)
        return jobs

    def _peer_jobs(self, scene: SceneSpec, condition: str | None, trained: list[MethodSpec]) -> list[Job]:
        """The peer rows of a cell (``peer:`` methods scored like one of ``trained``), after the runs they need."""
        names = {m.name for m in trained}
        cell = f"{scene.name}/{condition or 'clean'}"
        return [
            Job(f"{cell}/{m.name}", "peer", scene.name, condition, m.name, (f"{cell}/{m.peer['like']}",))
            for m in self.methods
            if m.peer is not None and m.peer["like"] in names and m.runs_on(scene.name, condition)
        ]

    def perform(self, job: Job, inputs: dict[str, Any], threads: int = 0) -> JobResult:
        """Do one job with the values of the jobs it needs (``inputs``, by key); what it recorded comes back with
        its value. ``threads``: torch and kernel threads of its training (0: the suite's)."""
        self.records, self.support, self.thetas = [], [], {}
        self.job_threads = threads
        if threads > 0:
            torch.set_num_threads(threads)
        scene = next(s for s in self.suite.scenes if s.name == job.scene)
        method = self.suite.method(job.method) if job.method else None
        value = getattr(self, f"_job_{job.action}")(job, scene, method, inputs)
        return JobResult(value, self.records, self.support, self.thetas)

    def job_failed(self, job: Job, error: str, log: str | None = None) -> JobResult:
        """What a job that could not run at all (its worker died, a job it needs failed) records."""
        self.records, self.support, self.thetas = [], [], {}
        if job.action in ("clean", "run", "peer"):
            scene = next(s for s in self.suite.scenes if s.name == job.scene)
            run_dir = self.output / job.scene / (job.condition or "clean") / job.method
            self._failed(scene, self.suite.method(job.method), job.condition, run_dir, error)
            if log:
                self.records[-1]["log"] = log
        value = {"error": error} if job.action in ("data", "restore") else None
        return JobResult(value, self.records, self.support, self.thetas)

    def _job_clean(self, job, scene, method, inputs):
        run_dir = self.output / scene.name / "clean" / method.name
        rec = self.execute(
            scene, method, None, run_dir, self.method_config(scene, method, experiment_name=f"clean-{method.name}")
        )
        return str(run_dir) if rec["status"] != "failed" else None

    def _job_depth(self, job, scene, method, inputs):
        """The run the degraded data takes its depth from: the first clean-photo run that worked, else a 3dgs
        run on the clean photos made for it (a support run)."""
        for key in job.deps:
            if inputs.get(key):
                return inputs[key]
        for m in self.suite.methods:  # a clean-photo row that ``--only-methods`` left out but an earlier call trained
            run_dir = self.output / scene.name / "clean" / m.name
            if (
                m.photos == "clean"
                and m.peer is None
                and m.runs_on(scene.name, None)
                and (run_dir / "metrics.json").is_file()
            ):
                return str(run_dir)
        helper = MethodSpec(name="_depth-3dgs", method="3dgs", photos="clean")
        run_dir = self.output / scene.name / "clean" / helper.name
        rec = self.execute(
            scene, helper, None, run_dir, self.method_config(scene, helper, experiment_name="depth"), support=True
        )
        return str(run_dir) if rec["status"] != "failed" else None

    def _job_data(self, job, scene, method, inputs):
        condition = self.resolved[job.condition]
        depth_run = inputs[job.deps[0]] if job.deps else None
        try:
            if job.deps and depth_run is None:
                raise MetegsError(f"no clean run of {scene.name} to take the depth from (it failed)")
            cell_dir = self.output / scene.name / job.condition
            data, weather = self._degraded(
                scene, condition, cell_dir, self.dataset_config(scene), None if depth_run is None else Path(depth_run)
            )
        except Exception as exc:  # noqa: BLE001 - every run of the cell records it
            if self.fail_fast:
                raise
            return {"error": f"{type(exc).__name__}: {exc}"}
        return {"data": str(data), "weather": weather}

    @staticmethod
    def restorer_names(method: MethodSpec) -> dict[str, str]:
        """The restorer of each weather kind for ``method``: its ``restorer``, else kang2012 for rain, dcp for fog."""
        return {**DEFAULT_RESTORERS, **method.restorer}

    def restored_folder(self, kind: str, method: MethodSpec) -> str:
        """The folder of a condition's photos restored for ``method`` (shared by methods with the same restorers)."""
        names = self.restorer_names(method)
        return "restored-" + "+".join(names[k] for k in ("rain", "fog") if k in kind.split("+"))

    def _job_restore(self, job, scene, method, inputs):
        from metegs.bench.data import restored_dataset
        from metegs.restore import restorer_for_kinds

        data = inputs[job.deps[0]]
        if "error" in data:
            return {"error": data["error"], "data_failed": True}
        condition = self.resolved[job.condition]
        target = self.output / scene.name / job.condition / self.restored_folder(condition.kind, method)
        if (target / "restore.json").is_file():
            return {"data": str(target), "info": json.loads((target / "restore.json").read_text())}
        try:
            restorer = restorer_for_kinds(condition.kind, self.restorer_names(method), method.restorer_options)
            self.console.print(f"{scene.name} / {condition.name}: restoring the photos with {restorer.name}")
            folder, info = restored_dataset(target, Path(data["data"]), self.dataset_config(scene), restorer)
        except MetegsError as exc:
            return {"error": str(exc), "metegs": True}
        return {"data": str(folder), "info": info}

    def _job_run(self, job, scene, method, inputs):
        from metegs.bench.data import run_conditions

        condition = self.resolved[job.condition]
        run_dir = self.output / scene.name / condition.name / method.name
        data = inputs[job.deps[0]]
        if "error" in data:
            return self._failed(scene, method, condition.name, run_dir, f"data: {data['error']}")
        weather = data["weather"]
        conds = run_conditions(condition, weather, scene.synth)
        common = dict(
            data=Path(data["data"]), parser=None, conditions=conds, experiment_name=f"{condition.name}-{method.name}"
        )
        extra: dict[str, Any] = {"data": data["data"]}
        config = self.method_config(scene, method, **common)
        if method.photos == "restored":
            restored = inputs[job.deps[1]]
            if "error" in restored:
                if method.optional and restored.get("metegs"):
                    return self._failed(scene, method, condition.name, run_dir, restored["error"], status="skipped")
                if self.fail_fast:
                    raise MetegsError(f"restorer: {restored['error']}")
                return self._failed(scene, method, condition.name, run_dir, f"restorer: {restored['error']}")
            info = restored["info"]
            config = replace(config, data=Path(restored["data"]), dataset=replace(config.dataset, downscale=1))
            extra = {
                "data": restored["data"],
                "restorer": info["restorer"],
                "preprocess_seconds": info["restore_seconds"],
                "restored_from": data["data"],
            }
        return self.execute(scene, method, condition.name, run_dir, config, extra)

    def _job_peer(self, job, scene, method, inputs):
        """Score a peer's PLY on the views of the run it is ``like`` (cached in its folder's eval.json while the file
        is unchanged)."""
        from metegs.engine.run import evaluate_run, load_run

        cell = self.output / scene.name / (job.condition or "clean")
        run_dir, like = cell / method.name, cell / method.peer["like"]
        ply = Path(method.peer["ply"].format(scene=scene.name, condition=job.condition or "clean"))
        if not (like / "metrics.json").is_file():
            return self._failed(
                scene, method, job.condition, run_dir, f"the run it is scored like ({like}) did not end"
            )
        if not ply.is_file():
            return self._failed(scene, method, job.condition, run_dir, f"{ply}: the peer's PLY file is not there")
        stamp = {"ply": str(ply.resolve()), "size": ply.stat().st_size, "mtime": ply.stat().st_mtime}
        path = run_dir / "eval.json"
        cached = json.loads(path.read_text()) if path.is_file() else None
        status = "cached" if cached is not None and cached.get("peer") == stamp else "done"
        if status == "done":
            self.console.print(f"{scene.name} / {job.condition or 'clean'} / {method.name}: scoring {ply}")
            try:
                metrics = evaluate_run(load_run(like, ply=ply))
            except MetegsError as exc:
                return self._failed(scene, method, job.condition, run_dir, f"{type(exc).__name__}: {exc}")
            cached = {**metrics, "peer": stamp, "like": str(like)}
            run_dir.mkdir(parents=True, exist_ok=True)
            atomic_write_text(path, json.dumps(cached, indent=2, default=str))
        record = {
            **self._identity(scene, method, job.condition, run_dir, status),
            **{k: _finite(cached.get(k)) for k in RESULT_KEYS},
            "peer_ply": stamp["ply"],
            "history": [],
        }
        self.records.append(record)
        return record

    def __getstate__(self) -> dict:
        """Pickled for the Ray executor's workers: without the console (a worker writes to its job's log)."""
        state = dict(self.__dict__)
        state["console"] = None
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        if self.console is None:
            self.console = Console(stderr=True)

    def _degraded(self, scene, condition, cell_dir: Path, dataset, depth_run):
        from metegs.bench.data import degraded_dataset

        data, weather = degraded_dataset(
            cell_dir / "data",
            scene.data,
            scene.parser,
            condition,
            dataset,
            self.suite.seed,
            depth_run=None if scene.in_memory else depth_run,
            synth_options=scene.synth,
            console=self.console,
        )
        views = weather.get("views") or [{}]
        theta = views[0].get("theta") or {}
        summary = _theta_summary(theta, views, weather)
        self.thetas.setdefault(condition.name, {})[scene.name] = summary
        record = {
            "scene": scene.name,
            **condition.to_dict(),
            "data": str(data),
            "metres_per_unit": weather.get("metres_per_unit"),
            "metres_per_unit_source": weather.get("metres_per_unit_source"),
            "depth": weather.get("depth"),
            "theta_summary": summary,
            "theta": theta,
        }
        atomic_write_text(cell_dir / "condition.json", json.dumps(record, indent=1, default=str))
        return data, weather

    # --- results -----------------------------------------------------------------------------------
    def results(self, conditions: dict[str, ResolvedCondition], seconds: float) -> dict:
        from metegs.bench.report import evaluate_checks

        checks = evaluate_checks(self.suite, self.records, conditions)
        return {
            "suite": self.suite.name,
            "source": str(self.suite.source) if self.suite.source else None,
            "description": self.suite.description,
            "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "total_seconds": round(seconds, 1),
            "runs_wall_seconds": round(sum(r.get("wall_seconds") or 0.0 for r in self.records), 1),
            "runs_wall_unknown": sum(
                1 for r in self.records if r.get("status") in ("done", "cached") and r.get("wall_seconds") is None
            ),
            "host": {
                "python": platform.python_version(),
                "torch": torch.__version__,
                "threads": torch.get_num_threads(),
                "machine": platform.machine(),
                "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
            },
            "scenes": [s.name for s in self.suite.scenes if any(r["scene"] == s.name for r in self.records)],
            "methods": [
                {
                    "name": m.name,
                    "label": m.label or m.name,
                    "method": m.method,
                    "photos": m.photos,
                    "group": m.group,
                    "oracle": m.oracle,
                    "overrides": m.overrides,
                    "restorer": m.restorer,
                    "ablation_label": m.ablation_label,
                    "seed": self.suite.seed if m.seed is None else m.seed,
                    "seed_of": m.seed_of,
                }
                for m in self.suite.methods
                if any(r["method"] == m.name for r in self.records)
            ],
            "conditions": {name: {**c.to_dict(), "theta": self.thetas.get(name, {})} for name, c in conditions.items()},
            "runs": self.records,
            "support_runs": self.support,
            "checks": checks,
            "all_checks_passed": all(c["passed"] is not False for c in checks),
        }


def _rel(path: Path, base: Path) -> str:
    try:
        return str(Path(path).resolve().relative_to(Path(base).resolve()))
    except ValueError:
        return str(path)


def _theta_summary(theta: dict, views: list[dict], weather: dict) -> dict:
    rain, fog, cond = theta.get("rain") or {}, theta.get("fog") or {}, theta.get("conditions") or {}
    beta = fog.get("beta_rgb_per_m") or [None]
    return {
        "precip_mm_h": cond.get("precip_mm_per_h"),
        "wmo_class": rain.get("intensity_class"),
        "visibility_m": cond.get("visibility_m"),
        "wind_m_s": cond.get("wind_speed_m_per_s"),
        "rain_active": rain.get("active"),
        "fog_active": fog.get("active"),
        "streaks_per_view": rain.get("count") if rain.get("active") else 0,
        "rain_gaussians_drawn_per_view": round(
            sum(v.get("num_rain_gaussians", 0) for v in views) / max(len(views), 1), 1
        ),
        "rain_coverage": round(sum(v.get("rain_coverage", 0.0) for v in views) / max(len(views), 1), 5),
        "fog_beta_per_m": None if beta[0] is None else sum(beta) / len(beta),
        "exposure_s": (theta.get("camera") or {}).get("exposure_s"),
        "metres_per_unit": weather.get("metres_per_unit"),
        "kinds": weather.get("kinds"),
    }


def _describe_pick(c: ResolvedCondition) -> str:
    parts = []
    if "rain" in c.provenance:
        r = c.provenance["rain"]
        parts.append(
            f"rain {r.get('precip_mm_h')} mm/h ({r.get('wmo_class', 'explicit')})"
            + (f" at {r['time']} from {Path(r['record']).name}" if "record" in r else "")
        )
    if "fog" in c.provenance:
        f = c.provenance["fog"]
        parts.append(
            f"visibility {f.get('visibility_m')} m"
            + (
                f" ({', '.join(f.get('present_weather') or [])}) at {f['time']} from {Path(f['record']).name}"
                if "record" in f
                else ""
            )
        )
    return "; ".join(parts)
