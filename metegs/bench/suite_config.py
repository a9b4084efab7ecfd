"""The benchmark suite file (``configs/bench/*.yaml``): scenes x conditions x methods, checks, options.

    name: default                       # suite name (the output folder's default name)
    output: outputs/bench/default       # relative to the current directory
    seed: 0
    eval_every: 0.1                     # test-view evaluation every this fraction of each run
    fps_repeats: 3                      # passes over the test views when timing the final model's renders
    train: {max_steps: 3000}            # overrides of every run's config (any metegs-train field)
    scenes:
      - {name: synthetic, train: {dataset: {synthetic: {width: 160, height: 120}}}}
      - {name: ethiopianhead, data: ../../../shared/data/scenes/ethiopianhead-llff, synth: {assumed_depth_m: 1.0}}
    conditions:
      - {name: rain-heavy, kind: rain, rain: {record: PRSA.csv, class: heavy}}
      - {name: fog-500, kind: fog, fog: {record: DS3505.txt, visibility_m: 500}}
    methods:
      - {name: 3dgs, method: 3dgs}
      - {name: 3dgs-clean, method: 3dgs, photos: clean, oracle: true}
      - {name: restore+3dgs, method: 3dgs, photos: restored, restorer: {rain: kang2012, fog: dcp}}
      - {name: metegs-full, method: metegs-full}
      - {name: metegs-blind, method: metegs-full, overrides: {clean_supervision: false}}
    checks:
      - {expect: "metegs-full > 3dgs", metrics: [psnr, ssim]}

Paths in the file (``data``, ``record``) are relative to the file's folder; ``$VARS`` and ``~`` expand;
``record: storm`` is the storm excerpt shipped with metegs.
"""

from __future__ import annotations

import dataclasses
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from metegs.bench.conditions import ConditionSpec
from metegs.config import load_yaml
from metegs.errors import ConfigError

PHOTOS = ("degraded", "clean", "restored")


@dataclass
class SceneSpec:
    """A scene of the suite."""

    name: str
    """Folder and table name."""
    data: Path | None = None
    """Scene folder (any format); None: the built-in synthetic scene."""
    parser: str | None = None
    """Force a data parser."""
    train: dict[str, Any] = field(default_factory=dict)
    """Overrides of every run on this scene (after the suite's ``train``)."""
    synth: dict[str, Any] = field(default_factory=dict)
    """Extra `metegs-synth` options for scenes from files (e.g. ``assumed_depth_m``, ``metres_per_unit``)."""
    conditions: list[str] | None = None
    """Only these conditions on this scene (None: all)."""

    @property
    def in_memory(self) -> bool:
        """True for the built-in synthetic scene: degraded in memory (it has exact depth), not written."""
        return self.data is None


@dataclass
class MethodSpec:
    """A method row of the suite."""

    name: str
    """Row name in tables and plots (unique)."""
    method: str = "3dgs"
    """Registered method (3dgs, metegs-full, ...)."""
    photos: str = "degraded"
    """What the method trains on: ``degraded`` photos, ``clean`` photos (the upper bound; trained once per
    scene), or ``restored`` photos (each degraded view through ``restorer`` first)."""
    restorer: dict[str, str] = field(default_factory=dict)
    """With ``photos: restored``: restorer per weather kind (``{rain: kang2012, fog: dcp}``; missing kinds
    take those defaults)."""
    restorer_options: dict[str, dict[str, Any]] = field(default_factory=dict)
    """Config overrides per restorer name (e.g. ``{restormer: {weights: FILE}}``)."""
    overrides: dict[str, Any] = field(default_factory=dict)
    """Overrides of the method's config (e.g. ``{clean_supervision: false}``)."""
    group: str = "main"
    """``main`` (the comparison tables) or ``ablation`` (the ablation table)."""
    oracle: bool = False
    """Not ranked (bold/underline) in the tables: it sees what the others cannot (clean photos)."""
    optional: bool = False
    """Skip with a note, instead of failing, when it cannot be set up (e.g. a learned restorer's weights)."""
    scenes: list[str] | None = None
    """Only on these scenes (None: all)."""
    conditions: list[str] | None = None
    """Only on these conditions (None: all)."""
    seed: int | None = None
    """Training seed of this row's runs (None: the suite's); the degraded photos stay the suite seed's draw, so rows
    that differ only in seed measure training's own spread."""
    seeds: list[int] = field(default_factory=list)
    """Also train this row with these seeds, as rows ``NAME-seedK`` (ablation group); results.md then gives each
    cell's mean and standard deviation over the seeds."""
    seed_of: str | None = None
    """The row this one repeats with another seed (set on the rows that ``seeds`` adds)."""
    label: str | None = None
    """Row label in tables (default: ``name``)."""
    ablation_label: str | None = None
    """Also list this (main) method in the ablation table under this label (e.g. ``(e) full`` for
    ``metegs-full``, which is the last ablation row: no separate run)."""
    resources: dict[str, float] | None = None
    """What each of its runs asks a Ray cluster for (``{cpus: 4, gpus: 1}``; None: the suite's ``resources``)."""
    peer: dict[str, str] | None = None
    """A row of another toolkit's result, trained elsewhere: ``{ply: FILE, like: METHOD}`` scores the Gaussians of FILE
    (``{scene}`` and ``{condition}`` in it are filled in; ``clean`` for clean photos) on the views and with the evaluator
    of METHOD's run in the same cell, as ``metegs-eval RUN --ply FILE`` does. Nothing is trained for it."""

    def __post_init__(self) -> None:
        check_resources(self.resources, f"method {self.name!r}")
        if self.peer is not None:
            if not isinstance(self.peer, dict) or set(self.peer) != {"ply", "like"}:
                raise ConfigError(f"method {self.name!r}: peer must be {{ply: FILE, like: METHOD}}, got {self.peer!r}")
        if self.photos not in PHOTOS:
            raise ConfigError(f"method {self.name!r}: photos must be one of {', '.join(PHOTOS)}, got {self.photos!r}")
        if self.group not in ("main", "ablation"):
            raise ConfigError(f"method {self.name!r}: group must be main or ablation, got {self.group!r}")
        if self.photos == "clean" and self.conditions is not None:
            raise ConfigError(f"method {self.name!r}: a clean-photo method runs once per scene; drop 'conditions'")

    def runs_on(self, scene: str, condition: str | None) -> bool:
        return (self.scenes is None or scene in self.scenes) and (
            condition is None or self.conditions is None or condition in self.conditions
        )


def check_resources(resources: dict[str, float] | None, where: str) -> None:
    """ConfigError unless ``resources`` is None or maps ``cpus`` / ``gpus`` to non-negative numbers."""
    if resources is None:
        return
    if not isinstance(resources, dict):
        raise ConfigError(f"{where}: resources must be a mapping such as {{cpus: 2, gpus: 1}}, got {resources!r}")
    unknown = sorted(set(resources) - {"cpus", "gpus"})
    if unknown:
        raise ConfigError(f"{where}: unknown resource(s) {unknown}; give cpus and/or gpus")
    for key, value in resources.items():
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not value >= 0:
            raise ConfigError(f"{where}: resources.{key} must be a non-negative number, got {value!r}")


_EXPECT = re.compile(r"\s*(>=|>)\s*")


@dataclass
class CheckSpec:
    """An expected ordering, e.g. ``"3dgs-clean >= metegs-full > 3dgs"`` on every (scene, condition) cell."""

    expect: str
    metrics: list[str] = field(default_factory=lambda: ["psnr"])
    """Metrics it must hold for (psnr, ssim: higher is better; lpips: lower is better)."""
    scenes: list[str] | None = None
    conditions: list[str] | None = None
    kinds: list[str] | None = None
    """Only conditions of these kinds (rain, fog, rain+fog)."""
    tolerance: float = 0.0
    """Slack of ``>=`` (in the metric's unit)."""
    margin: float = 0.0
    """How much the left of ``>`` must pass the right by (in the metric's unit: "3 dB over 3DGS")."""

    def chain(self) -> list[tuple[str, str, str]]:
        """[(left, op, right)] pairs of the expectation."""
        parts = _EXPECT.split(self.expect.strip())
        if len(parts) < 3 or len(parts) % 2 == 0:
            raise ConfigError(f"check {self.expect!r}: expected 'A > B', 'A >= B > C', ...")
        names, ops = parts[0::2], parts[1::2]
        return [(names[i], ops[i], names[i + 1]) for i in range(len(ops))]

    def __post_init__(self) -> None:
        self.chain()
        bad = [m for m in self.metrics if m not in ("psnr", "ssim", "lpips")]
        if bad:
            raise ConfigError(f"check {self.expect!r}: unknown metric(s) {bad}; use psnr, ssim, lpips")
        if self.margin < 0 or self.tolerance < 0:
            raise ConfigError(f"check {self.expect!r}: margin and tolerance are amounts (>= 0)")


@dataclass
class SuiteConfig:
    """A whole suite (see the module docstring)."""

    name: str
    scenes: list[SceneSpec]
    conditions: list[ConditionSpec]
    methods: list[MethodSpec]
    output: Path | None = None
    seed: int = 0
    backend: str = "auto"
    device: str = "auto"
    threads: int = 0
    eval_every: float = 0.1
    fps_repeats: int = 3
    train: dict[str, Any] = field(default_factory=dict)
    checks: list[CheckSpec] = field(default_factory=list)
    description: str = ""
    resources: dict[str, float] = field(default_factory=lambda: {"cpus": 1, "gpus": 0})
    """What each job (a run, the synthesis or restoration of a condition's photos) asks a Ray cluster for
    (``metegs-bench suite --executor ray``): ``cpus`` and ``gpus``; a method's ``resources`` replace it for its runs."""
    source: Path | None = None
    """The file it was read from."""

    def __post_init__(self) -> None:
        check_resources(self.resources, self.where)
        self.resources = {"cpus": 1, "gpus": 0, **self.resources}
        for what, items in (("scene", self.scenes), ("condition", self.conditions), ("method", self.methods)):
            names = [i.name for i in items]
            dup = sorted({n for n in names if names.count(n) > 1})
            if dup:
                raise ConfigError(f"{self.where}: duplicate {what} name(s): {', '.join(dup)}")
            bad = [n for n in names if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_.+()-]*", n)]
            if bad:
                raise ConfigError(f"{self.where}: {what} names must be folder-safe (letters, digits, _.+()-): {bad}")
        if not self.scenes or not self.methods:
            raise ConfigError(f"{self.where}: a suite needs at least one scene and one method")
        if not self.conditions and any(m.photos != "clean" for m in self.methods):
            raise ConfigError(f"{self.where}: methods on degraded or restored photos need at least one condition")
        if not 0 <= self.eval_every <= 1:
            raise ConfigError(f"{self.where}: eval_every must be a fraction in [0, 1], got {self.eval_every}")
        condition_names = {c.name for c in self.conditions}
        for scene in self.scenes:
            missing = sorted(set(scene.conditions or ()) - condition_names)
            if missing:
                raise ConfigError(f"{self.where}: scene {scene.name!r} names unknown condition(s) {missing}")
        method_names = {m.name for m in self.methods}
        for m in self.methods:
            if m.peer is not None:
                like = next((o for o in self.methods if o.name == m.peer["like"]), None)
                if like is None or like.peer is not None:
                    raise ConfigError(
                        f"{self.where}: method {m.name!r}: peer.like must name a method the suite trains, "
                        f"got {m.peer['like']!r}"
                    )
        for check in self.checks:
            missing = sorted({n for a, _, b in check.chain() for n in (a, b)} - method_names)
            if missing:
                raise ConfigError(f"{self.where}: check {check.expect!r} names unknown method(s) {missing}")

    @property
    def where(self) -> str:
        return str(self.source) if self.source else f"suite {self.name!r}"

    def method(self, name: str) -> MethodSpec:
        return next(m for m in self.methods if m.name == name)


def _expand(value: Any, base: Path | None) -> Path:
    text = os.path.expandvars(os.path.expanduser(str(value)))
    p = Path(text)
    return Path(os.path.normpath(p if p.is_absolute() or base is None else base / p))


def _record_path(value: Any, base: Path | None) -> str:
    if str(value) == "storm":
        from metegs.meteo import default_storm_path

        return str(default_storm_path())
    return str(_expand(value, base))


def _build(cls, data: Any, where: str):
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: expected a mapping, got {data!r}")
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {', '.join(unknown)}; allowed: {', '.join(sorted(names))}")
    try:
        return cls(**data)
    except TypeError as exc:
        raise ConfigError(f"{where}: {exc}") from exc


def reseeded(method: MethodSpec, suite_seed: int, where: str) -> list[MethodSpec]:
    """The rows ``NAME-seedK`` that ``method.seeds`` asks for: the same row with training seed K."""
    own = suite_seed if method.seed is None else method.seed
    if len(set(method.seeds)) != len(method.seeds) or own in method.seeds:
        raise ConfigError(f"{where}: seeds {method.seeds} must differ from each other and from the row's own ({own})")
    return [
        dataclasses.replace(
            method,
            name=f"{method.name}-seed{k}",
            label=f"{method.label or method.name}, seed {k}",
            seed=k,
            seeds=[],
            seed_of=method.name,
            group="ablation",
            ablation_label=None,
        )
        for k in method.seeds
    ]


def suite_from_dict(data: dict[str, Any], source: Path | None = None) -> SuiteConfig:
    """A `SuiteConfig` from parsed YAML (paths relative to ``source``'s folder)."""
    where = str(source) if source else "suite"
    base = source.parent if source is not None else None
    data = dict(data)
    scenes = []
    for i, s in enumerate(data.pop("scenes", None) or []):
        s = dict(s) if isinstance(s, dict) else s
        if isinstance(s, dict) and s.get("data") is not None:
            s["data"] = _expand(s["data"], base)
        scenes.append(_build(SceneSpec, s, f"{where}: scenes[{i}]"))
    conditions = []
    for i, c in enumerate(data.pop("conditions", None) or []):
        c = dict(c) if isinstance(c, dict) else c
        if isinstance(c, dict):
            for key in ("rain", "fog"):
                src = c.get(key)
                if isinstance(src, dict) and "record" in src:
                    c[key] = {**src, "record": _record_path(src["record"], base)}
        conditions.append(_build(ConditionSpec, c, f"{where}: conditions[{i}]"))
    methods = []
    for i, m in enumerate(data.pop("methods", None) or []):
        if isinstance(m, dict) and isinstance(m.get("peer"), dict) and "ply" in m["peer"]:
            m = {**m, "peer": {**m["peer"], "ply": str(_expand(m["peer"]["ply"], base))}}
        methods.append(_build(MethodSpec, m, f"{where}: methods[{i}]"))
        methods += reseeded(methods[-1], data.get("seed", 0), f"{where}: methods[{i}]")
    checks = [_build(CheckSpec, c, f"{where}: checks[{i}]") for i, c in enumerate(data.pop("checks", None) or [])]
    if "output" in data and data["output"] is not None:
        data["output"] = Path(os.path.expandvars(os.path.expanduser(str(data["output"]))))
    data.setdefault("name", source.stem if source is not None else "suite")
    return _build(
        SuiteConfig,
        {**data, "scenes": scenes, "conditions": conditions, "methods": methods, "checks": checks, "source": source},
        where,
    )


def load_suite(path: Path) -> SuiteConfig:
    """Read a suite YAML file (clear errors name the file and the entry)."""
    path = Path(path)
    return suite_from_dict(load_yaml(path), source=path.resolve())
