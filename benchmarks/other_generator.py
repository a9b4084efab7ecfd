"""Blind MeteGS under weather from a third generator, neither metegs's models nor its independent family.

Fog as in the RESIDE dehazing sets: uniform, β = 3.912 / visibility in every channel, under one tinted airlight.
Rain as in Garg and Nayar's photometric model: streaks of one direction (±3° per view) alpha-blended towards a fixed
radiance (neither the independent family's screen blend nor any veil of the rain), optionally a gain per photo as
a phone's auto-exposure gives. It stands in for the independent family's engine within `drawing`.

    python benchmarks/other_generator.py probe VARIANT [--size 160] [--steps 700]   # built-in scene: blind vs 3dgs
    python benchmarks/other_generator.py synth VARIANT -- METEGS_SYNTH_OPTIONS      # a degraded copy of any scene
    python benchmarks/other_generator.py suite VARIANT SUITE.yaml [-- SUITE_OPTIONS]  # a suite's independent cells

`probe` trains as the CI weather-removal test does (24 views, every 6th held out, heavy rain 22 mm/h and 300 m
visibility where the variant has them) and prints blind MeteGS's and 3dgs's metrics as JSON; `synth` runs
`metegs-synth --family independent --kinds ...` with this generator (pass the scene, `--depth-from`, the weather);
`suite` runs `metegs-bench suite` with this generator drawing the suite's `family: independent` conditions
(`configs/bench/real-other.yaml`), and refuses a cell whose photos another generator drew.
"""

from __future__ import annotations

import argparse
import inspect
import json
import sys
import tempfile
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np


@dataclass(frozen=True)
class Variant:
    """What one variant of the generator draws."""

    airlight: tuple[float, float, float]
    streak_radiance: float | None
    """Radiance the streaks blend towards (None: no rain)."""
    alpha: tuple[float, float] = (0.35, 0.6)
    """Range of the streaks' peak opacity, drawn per view."""
    exposure_spread: float = 0.0
    """Each photo is scaled by a gain drawn from 1 ± this."""
    fog: bool = True
    angle_deg: float = 15.0

    @property
    def kinds(self) -> tuple[str, ...]:
        """The weather kinds it draws, in `degrade`'s order (``("rain", "fog")``, ``("fog",)`` …)."""
        return tuple(k for k, on in (("rain", self.streak_radiance is not None), ("fog", self.fog)) if on)


VARIANTS = {
    "smog": Variant((0.72, 0.70, 0.62), 0.85),
    "smog-exp": Variant((0.72, 0.70, 0.62), 0.85, exposure_spread=0.15),
    "dark-streaks": Variant((0.88, 0.92, 1.0), 0.55, alpha=(0.3, 0.5), angle_deg=-10.0),
    "fog": Variant((0.8, 0.8, 0.8), None),
    "fog-exp": Variant((0.8, 0.8, 0.8), None, exposure_spread=0.15),
    "rain": Variant((0.8, 0.8, 0.8), 0.85, fog=False),
    "rain-exp": Variant((0.8, 0.8, 0.8), 0.85, exposure_spread=0.15, fog=False),
}
"""smog: grey-yellow airlight, bright streaks; dark-streaks: a bright blue airlight, streaks darker than the haze."""


def streak_mask(rng: np.random.Generator, height: int, width: int, angle_deg: float) -> np.ndarray:
    """[H, W] in [0, 1]: seeds at 0.004 per pixel smeared along a line 48 px long per 640 px of width."""
    from metegs.weather.independent import line_kernel

    seeds = (rng.random((height, width)) < 0.004).astype(np.float32)
    kernel = line_kernel(round(48 * width / 640), angle_deg)
    return np.clip(cv2.filter2D(seeds, -1, kernel, borderType=cv2.BORDER_REFLECT), 0.0, 1.0)


def engine_view(variant: Variant, name: str | None = None):
    """A replacement of `IndependentEngine.view` that draws ``variant`` (``name``: recorded in each view's record)."""
    from metegs.weather.independent import KOSCHMIEDER, pixel_rays

    def view(self, i: int, image: np.ndarray, depth: np.ndarray) -> tuple[np.ndarray, dict]:
        cond = self.conditions[i]
        rng = np.random.default_rng([self.seed, i, 99])
        out, kinds = np.asarray(image, np.float64), []
        if variant.fog and "fog" in self.kinds and cond.visibility_m is not None:
            _, _, per_depth = pixel_rays(self.scene.cameras[i], *depth.shape)
            distance_m = np.minimum(depth * per_depth * self.mpu, 5.0 * cond.visibility_m)
            t = np.exp(-KOSCHMIEDER / cond.visibility_m * distance_m)[..., None]
            out = out * t + np.asarray(variant.airlight) * (1.0 - t)
            kinds.append("fog")
        rains = cond.precip_mm_per_h is not None and cond.precip_mm_per_h > 2.5
        if variant.streak_radiance is not None and "rain" in self.kinds and rains:
            mask = streak_mask(rng, *depth.shape, variant.angle_deg + rng.normal(0.0, 3.0))
            alpha = mask[..., None] * rng.uniform(*variant.alpha)
            out = out * (1.0 - alpha) + variant.streak_radiance * alpha
            kinds.insert(0, "rain")
        if variant.exposure_spread:
            out = out * rng.uniform(1.0 - variant.exposure_spread, 1.0 + variant.exposure_spread)
        record = {"view": i, "name": self.scene.names[i], "family": "other generator", "kinds": "+".join(kinds)}
        if name is not None:
            record["variant"] = name
        return np.clip(out, 0.0, 1.0).astype(np.float32), record

    return view


@contextmanager
def drawing(variant: Variant, name: str | None = None):
    """Within the block the independent family draws ``variant`` (its engine's `view` replaced, then restored;
    ``name`` goes into each view's record)."""
    from metegs.weather.independent import IndependentEngine

    original = IndependentEngine.view
    IndependentEngine.view = engine_view(variant, name)
    try:
        yield
    finally:
        IndependentEngine.view = original


def drawn_by(weather: dict) -> str | None:
    """The variant that drew a degraded copy (its `weather.json`), None where this generator did not."""
    views = weather.get("views") or [{}]
    return views[0].get("variant") if views[0].get("family") == "other generator" else None


@contextmanager
def guarded_cells(variant_name: str):
    """Within the block the suite's `family: independent` cells are drawn by ``variant_name``, and a cell whose photos
    are already on disk must have been drawn by it too: the suite reuses a cell's photos, so photos of the independent
    family or of another variant would otherwise be reported as this variant's. A cell whose weather the variant does
    not draw (`fog` under rain + fog, `rain` under fog) is refused as well."""
    from metegs.bench import data

    original, variant = data.degraded_dataset, VARIANTS[variant_name]

    def degraded_dataset(target, *args, **kwargs):
        condition = inspect.signature(original).bind(target, *args, **kwargs).arguments["condition"]
        missing = sorted(set(condition.kind.split("+")) - set(variant.kinds))
        if condition.family == "independent" and missing:
            raise SystemExit(
                f"condition {condition.name!r} is {condition.kind}, but the {variant_name!r} variant draws no "
                f"{' and no '.join(missing)}: training's θ would expect weather its photos lack; pick its cells with "
                "--only-conditions"
            )
        done = Path(target) / "weather.json"
        if condition.family == "independent" and done.is_file():
            found = drawn_by(json.loads(done.read_text()))
            if found != variant_name:
                what = f"the {found!r} variant" if found else "another generator"
                raise SystemExit(
                    f"{done}: these photos were drawn by {what}, not by {variant_name!r}; "
                    "name the condition after the variant or give the suite another output folder"
                )
        return original(target, *args, **kwargs)

    # the suite imports `degraded_dataset` each time it degrades a cell (`SuiteRunner._degraded`), so this reaches it
    data.degraded_dataset = degraded_dataset
    try:
        with drawing(variant, variant_name):
            yield
    finally:
        data.degraded_dataset = original


def blind_config(output_dir: Path, size: int, steps: int, kinds: str, family: str, conditions, **overrides):
    """Blind MeteGS on the built-in scene as the CI weather-removal test trains it (24 views, every 6th held out, the
    robust mask as a user gets it), ``kinds`` of ``family``'s weather under ``conditions`` -> MeteGSConfig."""
    from metegs.data.config import DatasetConfig, SyntheticSceneConfig
    from metegs.densify.adc import ADCConfig
    from metegs.engine.metegs_config import MeteGSConfig
    from metegs.losses.robust import RobustMaskConfig

    scene = SyntheticSceneConfig(width=size, height=size * 3 // 4, num_views=24, num_points=3000)
    return MeteGSConfig(
        method="metegs-full",
        max_steps=steps,
        output_dir=output_dir,
        experiment_name="run",
        device="cpu",
        progress=False,
        dataset=DatasetConfig(synthetic=scene, auto_max_side=size, test_every=6),
        densify=ADCConfig(),
        checkpoint_every=0,
        save_renders=False,
        degrade=kinds,
        degrade_family=family,
        conditions=conditions,
        clean_supervision=False,
        compare_baseline=False,
        robust=RobustMaskConfig(),
        lpips_download=False,
        **overrides,
    )


def probe_weather(variant: Variant):
    """The weather a probe of ``variant`` degrades with and trains under: 22 mm/h where it draws streaks, 300 m where
    it draws fog -> (kinds, ConditionsConfig)."""
    from metegs.weather.conditions import ConditionsConfig

    rain = "rain" in variant.kinds
    return "+".join(variant.kinds), ConditionsConfig(
        precip_mm_h=22.0 if rain else 0.0, visibility_m=300.0 if variant.fog else None
    )


def probe(variant_name: str, size: int, steps: int) -> dict:
    """Blind MeteGS and 3dgs on the built-in scene under ``variant_name`` -> their metrics and MeteGS's decisions."""
    from metegs.engine.compare import train_baseline

    variant = VARIANTS[variant_name]
    kinds, conditions = probe_weather(variant)
    with tempfile.TemporaryDirectory() as tmp, drawing(variant):
        config = blind_config(Path(tmp), size, steps, kinds, "independent", conditions)
        trainer = config.setup()
        blind = trainer.train()
        plain = train_baseline(trainer)
    keys = ("psnr", "ssim", "streak_energy", "contrast_ratio")
    return {
        "variant": variant_name,
        "size": size,
        "steps": steps,
        "metegs-blind": {k: blind[k] for k in keys} | {"weather": blind.get("weather")},
        "3dgs": {k: plain[k] for k in keys},
        "decisions": trainer.decisions,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("probe", help="built-in scene: blind MeteGS against 3dgs")
    p.add_argument("variant", choices=sorted(VARIANTS))
    p.add_argument("--size", type=int, default=160, help="longer side of the views, px")
    p.add_argument("--steps", type=int, default=700)
    s = sub.add_parser("synth", help="metegs-synth --family independent with this generator")
    s.add_argument("variant", choices=sorted(VARIANTS))
    s.add_argument("synth_args", nargs=argparse.REMAINDER, help="-- then metegs-synth's options")
    b = sub.add_parser("suite", help="metegs-bench suite, this generator drawing the family: independent cells")
    b.add_argument("variant", choices=sorted(VARIANTS))
    b.add_argument("suite_file", type=Path)
    b.add_argument("suite_args", nargs=argparse.REMAINDER, help="-- then metegs-bench suite's options")
    args = parser.parse_args()
    if args.command == "probe":
        print(json.dumps(probe(args.variant, args.size, args.steps), indent=1, default=str))
        return
    if args.command == "suite":
        from metegs.cli.bench import entrypoint as bench

        sys.argv = ["metegs-bench", "suite", str(args.suite_file), *[a for a in args.suite_args if a != "--"]]
        with guarded_cells(args.variant):
            bench()
        return
    from metegs.cli.synth import entrypoint

    rest = [a for a in args.synth_args if a != "--"]
    sys.argv = ["metegs-synth", *rest, "--family", "independent"]
    with drawing(VARIANTS[args.variant], args.variant):
        entrypoint()


if __name__ == "__main__":
    main()
