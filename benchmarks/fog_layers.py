"""Blind MeteGS on the built-in scene in fog, with the height profile learnt from uniform against a uniform fog.

    python benchmarks/fog_layers.py [physical] [fog] [smog] … [--steps 700]

`physical` is metegs's own fog of 200 m (uniform); the others are the third generator's variants with fog, under
`benchmarks/other_generator.py probe`'s weather (300 m, and 22 mm/h where the variant draws streaks). Each variant
trains twice as the CI weather-removal test does (24 views at 160×120, every 6th held out): once with the profile
learnt from uniform even where the points read the fog denser upwards (`profile_from_uniform`: there the decision
`fog-analytic layers` keeps β uniform) and once with `--fog-analytic.no-layered`, and prints one JSON line per run:
PSNR / SSIM on the clean test views, the learnt β and scale height, and the layers decision.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager, nullcontext
from pathlib import Path

from other_generator import VARIANTS, blind_config, drawing, probe_weather


@contextmanager
def profile_from_uniform() -> Iterator[None]:
    """Within the block blind MeteGS learns the fog's height profile from uniform where the points read the fog
    denser upwards, where it otherwise keeps β uniform (`MeteGSTrainer._points_layers` read as uniform there)."""
    from metegs.engine.metegs_trainer import MeteGSTrainer

    measure = MeteGSTrainer._points_layers

    def thinning_or_uniform(self, fog):
        fit = measure(self, fog)
        return fit if fit is None or fit.height_rate >= 0.0 else dataclasses.replace(fit, height_rate=0.0)

    MeteGSTrainer._points_layers = thinning_or_uniform
    try:
        yield
    finally:
        MeteGSTrainer._points_layers = measure


def run(variant: str, layered: bool, steps: int) -> dict:
    """Blind MeteGS in ``variant``'s fog, the fog's profile learnt (`profile_from_uniform`) or off -> its metrics and
    medium."""
    from metegs.weather.conditions import ConditionsConfig
    from metegs.weather.fog_analytic import FogAnalyticConfig

    other = None if variant == "physical" else VARIANTS[variant]  # the third generator's, or metegs's own fog
    if other is None:
        family, kinds, conditions = "physical", "fog", ConditionsConfig(precip_mm_h=0.0, visibility_m=200.0)
    else:
        family, (kinds, conditions) = "independent", probe_weather(other)
    with (
        tempfile.TemporaryDirectory() as tmp,
        nullcontext() if other is None else drawing(other),
        profile_from_uniform() if layered else nullcontext(),
    ):
        fog = FogAnalyticConfig(layered=layered)
        trainer = blind_config(Path(tmp), 160, steps, kinds, family, conditions, fog_analytic=fog).setup()
        metrics = trainer.train()
    medium = (metrics.get("weather") or {}).get("fog-analytic", {})
    return {
        "variant": variant,
        "layered": layered,
        "psnr": round(metrics["psnr"], 2),
        "ssim": round(metrics["ssim"], 3),
        "beta_per_m": medium.get("beta_per_m"),
        "scale_height_m": medium.get("scale_height_m"),
        "layers": trainer.decisions.get("fog-analytic layers"),
    }


def main() -> None:
    fogs = ["physical", *sorted(name for name, v in VARIANTS.items() if v.fog)]
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "variants", nargs="*", metavar="VARIANT", help=f"fogs to run, of {', '.join(fogs)} (default: all)"
    )
    parser.add_argument("--steps", type=int, default=700)
    args = parser.parse_args()
    unknown = sorted(set(args.variants) - set(fogs))
    if unknown:
        parser.error(f"unknown fog {', '.join(unknown)}; choose from {', '.join(fogs)}")
    for variant in args.variants or fogs:
        for layered in (True, False):
            print(json.dumps(run(variant, layered, args.steps), default=str), flush=True)


if __name__ == "__main__":
    main()
