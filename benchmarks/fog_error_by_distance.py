"""Where blind MeteGS's clean renders err in fog: the built-in scene's test views against their exact depth.

    python benchmarks/fog_error_by_distance.py [--family physical|independent] [--visibility 200] [--steps 700]

Trains blind MeteGS on the built-in scene (24 views at 160×120, every 6th held out, as the CI weather-removal test)
in fog of one family, once as the decisions choose (`auto`) and once with the dark-channel prior forced on
(`--dark-channel.mode on`), and prints as JSON, per run, the metrics, the learned medium and, by each test pixel's
true distance, the share of pixels, the clean render's mean signed error (render − clean reference) and the median
ratio of the rendered to the true distance. Past a fog's reach (t = e^{−βd} of a few %) a surface's colour hardly
reaches the photos, and the error there is the colour the Gaussians start from and keep; a ratio under 1 says the
Gaussians moved in towards the cameras.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import torch

DISTANCE_BINS_M = (0.0, 100.0, 150.0, 200.0, 260.0, float("inf"))
"""Edges of the true-distance bins (metres along the pixel's ray)."""


def errors_by_distance(trainer) -> list[dict]:
    """Per `DISTANCE_BINS_M` bin over ``trainer``'s test views: pixel share, mean signed clean error (render −
    reference, over R, G, B), median rendered/true distance."""
    from metegs.weather.fog_analytic import ray_lengths

    ds = trainer.dataset
    metres = trainer.scene.metric_scale
    errors, ratios, distances = [], [], []
    with torch.no_grad():
        background = trainer.background(training=False)
        for i in ds.test_indices:
            out = trainer.render(i)
            clean = trainer.as_photographed(out.rgb, i).clamp(0, 1)
            rays = ray_lengths(ds.cameras[i], *ds.depths[i].shape)
            true_m = ds.depths[i] * rays * metres
            errors.append((clean - trainer.reference(i, background)).mean(-1).flatten())
            ratios.append((out.depth * rays * metres / true_m).flatten())
            distances.append(true_m.flatten())
    error, ratio, distance = torch.cat(errors), torch.cat(ratios), torch.cat(distances)
    rows = []
    for lo, hi in zip(DISTANCE_BINS_M[:-1], DISTANCE_BINS_M[1:]):
        inside = (distance >= lo) & (distance < hi)
        if inside.any():
            rows.append(
                {
                    "distance_m": [lo, None if hi == float("inf") else hi],
                    "pixels": round(float(inside.float().mean()), 4),
                    "signed_error": round(float(error[inside].mean()), 4),
                    "depth_ratio": round(float(ratio[inside].median()), 3),
                }
            )
    return rows


def run(family: str, visibility_m: float, steps: int, dark_channel: str) -> dict:
    """Blind MeteGS on the built-in scene in ``family``'s fog with the dark-channel prior ``dark_channel``
    (auto | on) -> its metrics, medium, two decisions and `errors_by_distance`."""
    from other_generator import blind_config

    from metegs.losses.dark_channel import DarkChannelPriorConfig
    from metegs.weather.conditions import ConditionsConfig

    conditions = ConditionsConfig(precip_mm_h=0.0, visibility_m=visibility_m)
    with tempfile.TemporaryDirectory() as tmp:
        config = blind_config(
            Path(tmp), 160, steps, "fog", family, conditions, dark_channel=DarkChannelPriorConfig(mode=dark_channel)
        )
        trainer = config.setup()
        metrics = trainer.train()
        return {
            "dark_channel": dark_channel,
            "psnr": round(metrics["psnr"], 2),
            "ssim": round(metrics["ssim"], 3),
            "weather": metrics.get("weather"),
            "decisions": {k: trainer.decisions.get(k) for k in ("dark channel prior", "fog-analytic prior")},
            "by_distance": errors_by_distance(trainer),
        }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--family", choices=("physical", "independent"), default="physical")
    parser.add_argument("--visibility", type=float, default=200.0, help="the fog's visibility, m")
    parser.add_argument("--steps", type=int, default=700)
    args = parser.parse_args()
    runs = [run(args.family, args.visibility, args.steps, mode) for mode in ("auto", "on")]
    print(json.dumps({"family": args.family, "visibility_m": args.visibility, "runs": runs}, indent=1, default=str))


if __name__ == "__main__":
    main()
