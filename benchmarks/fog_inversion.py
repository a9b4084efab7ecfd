"""Where blind fog removal loses on a degraded real capture: the fit of the photos, or the depth the fog was drawn over.

    python benchmarks/fog_inversion.py SUITE/ethiopianhead/fog-200/metegs-blind SUITE/ethiopianhead/clean/_depth-3dgs

metegs's own fog (the physical family) degrades a capture along the depth of a clean 3DGS run: photo I = J·t + A·(1 −
t), t = exp(−β·d), with the exact β and A of each view in the data folder's weather.json. For each run given, on its
training views, this scores against the clean photos J:

- the photo inverted along the run's own rendered depth with the exact medium, (I − A·(1 − t))/t: the best a scene
  of that geometry can do, whatever its colours (the depth run that made the fog gives the photos back to rounding),
  and for a run with a fog model, with the medium it learned;
- the run's clean render, and for a MeteGS run its weather render against the photo (the fit) and that fit's
  residual divided by its medium's t, the error the fit leaves in the clean scene.

Where the inversion along a run's depth stays far under the depth run's, the photos' fog follows a geometry the run
does not have: a 2D restoration, which estimates t per pixel, is not held to any geometry.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import torch


def _stem(name: str) -> str:
    """A view's name without its extension: a degraded copy may store its photos in another format."""
    return str(Path(name).with_suffix(""))


def exact_media(data: Path) -> tuple[dict[str, tuple[torch.Tensor, torch.Tensor]], float]:
    """Per view name without extension (β [3] 1/m, A [3]) of the physical fog in ``data``/weather.json, and its metres per unit."""
    record = json.loads((data / "weather.json").read_text())
    if record.get("family", "physical") != "physical":
        raise SystemExit(f"{data}/weather.json: family {record.get('family')!r}; this needs metegs's own fog")
    media = {}
    for view in record["views"]:
        fog = view.get("fog-analytic")
        if fog:
            media[_stem(view["name"])] = (torch.tensor(fog["beta_per_m"]), torch.tensor(fog["airlight"]))
    if not media:
        raise SystemExit(f"{data}/weather.json: no view has a fog-analytic medium")
    return media, float(record["metres_per_unit"])


def score_run(trainer, degraded, every: int) -> dict:
    """The scores of the module docstring over every ``every``-th training view of ``trainer`` (a loaded run), with
    the photos, clean photos and media of ``degraded`` (a loaded run trained on the physical-fog data folder, maybe
    ``trainer`` itself), averaged as mean squared errors -> {name: dB}."""
    from metegs.weather.fog_analytic import FogAnalytic, ray_lengths

    ds, ref = trainer.dataset, degraded.dataset
    same_names = [_stem(n) for n in ds.names] == [_stem(n) for n in ref.names]
    if not same_names or [im.shape for im in ds.images] != [im.shape for im in ref.images]:
        raise SystemExit(f"{trainer.run_dir}: its views differ from those of {degraded.run_dir}")
    media, mpu = exact_media(Path(degraded.config.data))
    weather = getattr(trainer, "render_weather", None)
    background = trainer.background(training=False)
    sums: dict[str, list[float]] = {}
    for i in ds.train_indices[::every]:
        if _stem(ds.names[i]) not in media:
            continue
        beta, airlight = media[_stem(ds.names[i])]
        photo, clean = ref.images[i], ref.clean_images[i]
        with torch.no_grad():
            out = trainer.render(i)
            h, w = out.depth.shape
            t = torch.exp(-(out.depth * ray_lengths(ds.cameras[i], h, w) * mpu)[..., None] * beta)
            inverted = (photo - airlight * (1.0 - t)) / t.clamp_min(0.05)
            errors = {"inverted along its depth": inverted - clean, "clean render": out.rgb - clean}
            seen = t
            fog = next((m for m in getattr(trainer, "weather_models", []) if isinstance(m, FogAnalytic)), None)
            if fog is not None:
                own_t = torch.exp(-fog.optical_distance(out.depth, out.alpha, i)[..., None] * fog.beta_rgb)
                own = (photo - fog.airlight_toward(i, h, w) * (1.0 - own_t)) / own_t.clamp_min(0.05)
                errors["inverted along its depth, its medium"] = own - clean
                seen = own_t
            if weather is not None and trainer.weather_models:
                fit = weather(i, background, training=False).rgb - photo
                errors["weather render vs photo"] = fit
                errors["that fit's residual / t"] = fit / seen.clamp_min(0.05)
        for name, e in errors.items():
            sums.setdefault(name, []).append(float((e**2).mean()))
    return {name: -10.0 * math.log10(max(sum(v) / len(v), 1e-12)) for name, v in sums.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "runs", type=Path, nargs="+", help="run folders of one capture, one at least trained on its physical fog"
    )
    parser.add_argument("--every", type=int, default=4, help="score every N-th training view")
    parser.add_argument("--output", type=Path, help="write the scores as JSON here")
    args = parser.parse_args()
    from metegs.engine.run import load_run

    trainers = [load_run(run, None, None, "cpu") for run in args.runs]
    degraded = next((t for t in trainers if t.dataset.clean_images is not None), None)
    if degraded is None:
        raise SystemExit("give at least one run trained on the degraded data folder (its clean photos score the rest)")
    results = {}
    for run, trainer in zip(args.runs, trainers):
        results[str(run)] = scores = score_run(trainer, degraded, args.every)
        print(f"{run}: " + ", ".join(f"{k} {v:.2f} dB" for k, v in scores.items()))
    if args.output is not None:
        args.output.write_text(json.dumps(results, indent=1) + "\n")


if __name__ == "__main__":
    main()
