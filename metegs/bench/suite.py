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
"""

from __future__ import annotations

import json
import math
import platform
import time
import traceback
from dataclasses import dataclass, replace
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
from metegs.files import atomic_write_text

RESULT_KEYS = ("psnr", "ssim", "lpips", "lpips_reason", "num_gaussians", "train_seconds", "steps", "reference")


@dataclass
class Cell:
    """One (scene, condition) of the suite with its prepared data."""

    scene: SceneSpec
    condition: ResolvedCondition
    data: Path
    weather: dict


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
    """Top-level config fields whose value in ``run_dir/config.yml`` differs from ``config`` (empty: same)."""
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
    return sorted(k for k, v in now.items() if k not in VOLATILE_FIELDS and k in saved and saved[k] != v)


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

    # --- configs -----------------------------------------------------------------------------------
    def method_config(self, scene: SceneSpec, method: MethodSpec, **fields):
        """The run config: the method's defaults <- suite ``train`` <- scene ``train`` <- method ``overrides``
        <- the suite's seed/backend/device/threads/eval_every <- ``fields``."""
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
            seed=s.seed,
            backend=s.backend,
            device=s.device,
            threads=s.threads,
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
                    f"[yellow]{label}: reused, but the suite now asks for other {', '.join(changed)} than the run "
                    f"was made with; delete {run_dir} to train it again[/]",
                    highlight=False,
                )
        verb = "reused" if status == "cached" else f"done in {time.perf_counter() - t0:.0f} s"
        if record["status"] == "failed":
            self.console.print(f"[red]{label}: {record['error']}[/]", highlight=False)
        else:
            self.console.print(
                f"{label}: {verb}; PSNR {record['psnr']:.2f} dB, SSIM {record['ssim']:.4f}, "
                f"{record['num_gaussians']} Gaussians, train {record['train_seconds']:.1f} s",
                highlight=False,
            )
        (self.support if support else self.records).append(record)
        return record

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
        self.console.print(
            f"[red]{scene.name} / {condition or 'clean'} / {method.name}: {status}[/]: {error.splitlines()[0]}",
            highlight=False,
        )
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

        for scene in self.scenes:
            methods = [m for m in self.methods if m.runs_on(scene.name, None)]
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

    def run(self) -> dict:
        from metegs.bench.report import write_report

        started = time.perf_counter()
        self.output.mkdir(parents=True, exist_ok=True)
        if self.suite.threads > 0:
            torch.set_num_threads(self.suite.threads)
        conditions = self.resolve_conditions()
        self.write_conditions(conditions)
        for scene in self.scenes:
            self.run_scene(scene, conditions)
            self.write_conditions(conditions)
        results = self.results(conditions, time.perf_counter() - started)
        atomic_write_text(self.output / "results.json", json.dumps(results, indent=1, default=str))
        write_report(results, self.output)
        return results

    def run_scene(self, scene: SceneSpec, conditions: dict[str, ResolvedCondition]) -> None:
        methods = [m for m in self.methods if m.runs_on(scene.name, None)]
        clean_methods = [m for m in methods if m.photos == "clean"]
        weather_methods = [m for m in methods if m.photos != "clean"]
        depth_run = None
        for m in clean_methods:
            run_dir = self.output / scene.name / "clean" / m.name
            rec = self.execute(scene, m, None, run_dir, self.method_config(scene, m, experiment_name=f"clean-{m.name}"))
            if rec["status"] != "failed" and depth_run is None:
                depth_run = run_dir
        needs_depth = not scene.in_memory and any(
            m.runs_on(scene.name, c.name) for m in weather_methods for c in self.conditions_of(scene)
        )
        if needs_depth and depth_run is None:
            helper = MethodSpec(name="_depth-3dgs", method="3dgs", photos="clean")
            run_dir = self.output / scene.name / "clean" / helper.name
            rec = self.execute(
                scene, helper, None, run_dir, self.method_config(scene, helper, experiment_name="depth"), support=True
            )
            depth_run = run_dir if rec["status"] != "failed" else None
        dataset = self.dataset_config(scene)
        for spec in self.conditions_of(scene):
            here = [m for m in weather_methods if m.runs_on(scene.name, spec.name)]
            if not here:
                continue
            condition = conditions[spec.name]
            cell_dir = self.output / scene.name / spec.name
            try:
                if needs_depth and depth_run is None:
                    raise MetegsError(f"no clean run of {scene.name} to take the depth from (it failed)")
                data, weather = self._degraded(scene, condition, cell_dir, dataset, depth_run)
            except Exception as exc:  # noqa: BLE001
                if self.fail_fast:
                    raise
                for m in here:
                    self._failed(scene, m, spec.name, cell_dir / m.name, f"data: {type(exc).__name__}: {exc}")
                continue
            cell = Cell(scene, condition, data, weather)
            for m in here:
                self.run_cell_method(cell, m, dataset)

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

    def run_cell_method(self, cell: Cell, method: MethodSpec, dataset) -> dict:
        from metegs.bench.data import run_conditions

        scene, condition = cell.scene, cell.condition
        run_dir = self.output / scene.name / condition.name / method.name
        conds = run_conditions(condition, cell.weather, scene.synth)
        common = dict(data=cell.data, parser=None, conditions=conds, experiment_name=f"{condition.name}-{method.name}")
        extra: dict[str, Any] = {"data": str(cell.data)}
        if method.photos == "restored":
            try:
                data, info = self._restored(cell, method, dataset)
            except MetegsError as exc:
                if method.optional:
                    return self._failed(scene, method, condition.name, run_dir, str(exc), status="skipped")
                if self.fail_fast:
                    raise
                return self._failed(scene, method, condition.name, run_dir, f"restorer: {exc}")
            config = self.method_config(scene, method, **common)
            config = replace(config, data=data, dataset=replace(config.dataset, downscale=1))
            extra = {
                "data": str(data),
                "restorer": info["restorer"],
                "preprocess_seconds": info["restore_seconds"],
                "restored_from": str(cell.data),
            }
        else:
            config = self.method_config(scene, method, **common)
        return self.execute(scene, method, condition.name, run_dir, config, extra)

    def _restored(self, cell: Cell, method: MethodSpec, dataset):
        from metegs.bench.data import restored_dataset
        from metegs.restore import restorer_for_kinds

        names = {**{"rain": "kang2012", "fog": "dcp"}, **method.restorer}
        kinds = [k for k in ("rain", "fog") if k in cell.condition.kind.split("+")]
        folder = "restored-" + "+".join(names[k] for k in kinds)
        target = self.output / cell.scene.name / cell.condition.name / folder
        if (target / "restore.json").is_file():
            return target, json.loads((target / "restore.json").read_text())
        restorer = restorer_for_kinds(cell.condition.kind, names, method.restorer_options)
        self.console.print(f"{cell.scene.name} / {cell.condition.name}: restoring the photos with {restorer.name}")
        return restored_dataset(target, cell.data, dataset, restorer)

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
            "scenes": [s.name for s in self.scenes],
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
                }
                for m in self.methods
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
