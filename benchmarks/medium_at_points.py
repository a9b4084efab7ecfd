"""The fog medium measured at a degraded scene's SfM points, against the one its generator drew.

    python benchmarks/medium_at_points.py outputs/bench/real/lund/rain+fog-ind/data   # a metegs-bench data folder

A scene point of colour J seen through fog at distance d shows I = J·t + A·(1 − t), t = exp(−τ(d)). Where the views
see the points from distances far apart (a street walked down), I changes from view to view by the medium alone, so
the photos' colours at the points' projections measure β, its fall with height and the airlight A with one unknown
J per point. Training measures the same through the scene's Gaussians, which can take the haze in themselves
(Gaussians near the cameras, colours that change with the view): on OpenSfM's Lund street under independent height
fog, blind training let β fall to a third of the generator's while this fit comes within 10 %. Views in which another
point hides a point are left out (`unoccluded`), rain streaks over it are outliers of a robust loss. Blind training
measures a uniform medium the same way at its starting points under the photos' airlight (`fit_uniform_medium`,
decision `fog-analytic prior`); this diagnostic also fits the airlight and how β falls with height, by gradient steps,
and compares them with the generator's.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
import torch

from metegs.weather.airlight import typical_airlight
from metegs.weather.medium_fit import fit_medium, fit_uniform_medium, point_observations


def generator_medium(data: Path, scene) -> dict | None:
    """The independent generator's β at the cameras' mean height (green channel), scale height and airlight, from
    ``data``/weather.json (None for other families)."""
    from metegs.weather.independent import ground_height

    record = json.loads((data / "weather.json").read_text())
    fog = next((v["fog"] for v in record.get("views", []) if isinstance(v.get("fog"), dict)), None)
    if fog is None:
        return None
    up = np.asarray(scene.up, np.float64) / np.linalg.norm(scene.up)
    centres = scene.cameras.camera_to_worlds[:, :3, 3].double().numpy()
    height_m = ((centres @ up).mean() - ground_height(scene, up)) * record["metres_per_unit"]
    beta = fog["beta_per_m"] * fog["channel_scale"][1] * math.exp(-max(height_m, 0.0) / fog["scale_height_m"])
    return {"beta_per_m": beta, "scale_height_m": fog["scale_height_m"], "airlight": fog["airlight"]}


def main() -> None:
    from metegs.data.config import DatasetConfig
    from metegs.data.images import load_image
    from metegs.data.parsers.base import parse_scene

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "data", type=Path, help="a degraded scene folder with weather.json (metegs-synth, metegs-bench)"
    )
    args = parser.parse_args()
    scene = parse_scene(args.data, None, DatasetConfig())
    if scene.points is None:
        raise SystemExit(f"{args.data}: the scene has no points to measure the medium at")
    mpu = json.loads((args.data / "weather.json").read_text())["metres_per_unit"]
    views = scene.train_indices
    images = [torch.from_numpy(load_image(scene.image_paths[i])) for i in views]
    obs = point_observations(
        scene.cameras[views], images, torch.as_tensor(scene.points), torch.as_tensor(scene.up), mpu
    )
    for layered in (False, True):
        print(("layered: " if layered else "uniform: ") + fit_medium(obs, 0.01, layered=layered).describe())
    held = fit_uniform_medium(obs, airlight=typical_airlight(images))
    print("uniform under the photos' airlight (as blind training measures it): " + held.describe())
    truth = generator_medium(args.data, scene)
    if truth is not None:
        a = ", ".join(f"{v:.2f}" for v in truth["airlight"])
        print(
            f"generator: β {truth['beta_per_m']:.2e}/m at the cameras' mean height (green), scale height "
            f"{truth['scale_height_m']:.0f} m, airlight ({a}) before its view-dependent factor 0.85-1"
        )


if __name__ == "__main__":
    main()
