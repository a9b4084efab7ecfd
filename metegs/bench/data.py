"""The photos each benchmark run trains on, prepared once and cached in the suite folder.

- degraded: `metegs-synth` (the same machinery as the command) writes a rainy / foggy copy of the scene
  with its clean references into ``<suite>/<scene>/<condition>/data/``, from the condition's record and
  time. The built-in synthetic scene has exact depth; a scene from files takes its depth from a clean
  ``3dgs`` run of the suite (``depth_run``).
- restored: every view of the degraded copy, at the resolution training loads it at, through a 2D
  restorer; written as a nerfstudio dataset (clean references alongside) into
  ``<suite>/<scene>/<condition>/restored-<restorer>/`` with ``restore.json`` (restorer, seconds).

A folder that exists complete (``weather.json`` / ``restore.json`` written last) is reused; writing goes
through a temp folder and a rename, so an interrupted suite leaves nothing half-written.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

from metegs.bench.conditions import ResolvedCondition
from metegs.data.config import DatasetConfig, auto_max_side
from metegs.errors import DataError

SYNTH_THETA_FIELDS = ("capture_width_px", "exposure_s", "metres_per_unit")
"""`metegs-synth` options that change θ: runs get the same values in ``--conditions.*``."""


def degraded_dataset(
    target: Path,
    data: Path | None,
    parser: str | None,
    condition: ResolvedCondition,
    dataset: DatasetConfig,
    seed: int,
    depth_run: Path | None = None,
    synth_options: dict[str, Any] | None = None,
    console=None,
) -> tuple[Path, dict]:
    """(folder, weather.json) of the degraded copy of a scene under ``condition`` (written unless cached)."""
    from metegs.synth.pipeline import SynthConfig, synthesise

    target = Path(target)
    done = target / "weather.json"
    if done.is_file():
        return target, json.loads(done.read_text())
    c = condition.conditions
    explicit = c.record is None
    args = SynthConfig(
        output=target,
        data=data,
        parser=parser,
        depth_from=depth_run,
        record=None if explicit else c.record,
        time=() if explicit or c.time is None else (c.time,),
        window=c.window,
        agg=c.agg,
        precip_mm_h=c.precip_mm_h if explicit else None,
        visibility_m=c.visibility_m,
        kinds=condition.kind,
        family=condition.family,
        seed=seed,
        overwrite=True,
        dataset=dataset,
        preview_views=4,
    )
    if synth_options:
        try:
            args = dataclasses.replace(args, **synth_options)
        except TypeError as exc:
            raise DataError(None, f"synth options {sorted(synth_options)}: {exc}") from exc
    synthesise(args, console)
    return target, json.loads(done.read_text())


def run_conditions(condition: ResolvedCondition, weather: dict, synth_options: dict[str, Any] | None = None):
    """The ``--conditions`` of runs on a degraded copy: the condition with the scale, exposure and capture
    width the copy was synthesised with (a file dataset does not carry them), so that θ is the same."""
    views = weather.get("views") or [{}]
    camera = (views[0].get("theta") or {}).get("camera") or {}
    opts = synth_options or {}
    return dataclasses.replace(
        condition.conditions,
        metres_per_unit=float(weather["metres_per_unit"]),
        exposure_s=camera.get("exposure_s", opts.get("exposure_s")),
        capture_width_px=int(opts.get("capture_width_px", condition.conditions.capture_width_px)),
    )


def training_sizes(cameras, dataset: DatasetConfig) -> list[tuple[int, int]]:
    """(width, height) per view as training loads them (the dataset's downscale rule)."""
    from metegs.data.dataset import auto_downscale

    d = dataset.downscale if dataset.downscale is not None else auto_downscale(cameras, auto_max_side(dataset))
    return [
        (max(1, round(int(w) / d)), max(1, round(int(h) / d)))
        for w, h in zip(cameras.width.tolist(), cameras.height.tolist())
    ]


def restored_dataset(
    target: Path, degraded: Path, dataset: DatasetConfig, restorer, progress=None
) -> tuple[Path, dict]:
    """(folder, restore.json) of the degraded copy restored view by view at training resolution.

    Photos another run restored with the same restorer (a pseudo-reference run, an earlier suite) are read from
    `cached_restore`'s cache; their seconds are those their restoring took, so the time reported stays the cost."""
    from metegs.cameras import Cameras
    from metegs.data.images import load_image, resize_image
    from metegs.data.parsers.base import parse_scene
    from metegs.data.scene import SceneData
    from metegs.files import staged_output
    from metegs.restore.cache import cached_restore
    from metegs.synth.writers import DatasetWriter

    target = Path(target)
    done = target / "restore.json"
    if done.is_file():
        return target, json.loads(done.read_text())
    scene = parse_scene(degraded, None, dataset)
    if scene.clean_image_paths is None:
        raise DataError(degraded, "the degraded copy has no clean references")
    sizes = training_sizes(scene.cameras, dataset)
    restored, cleans, seconds, cached = [], [], 0.0, 0
    for i, (w, h) in enumerate(sizes):
        result = cached_restore(restorer, resize_image(load_image(scene.image_paths[i]), w, h))
        restored.append(result.image)
        seconds += result.seconds
        cached += result.cached
        cleans.append(resize_image(load_image(scene.clean_image_paths[i]), w, h))
        if progress is not None:
            progress(i)
    cams = Cameras.cat([scene.cameras[i].resized(w, h) for i, (w, h) in enumerate(sizes)])
    memory = SceneData(
        cameras=cams,
        names=scene.names,
        images=restored,
        clean_images=cleans,
        train_indices=scene.train_indices,
        test_indices=scene.test_indices,
        points=scene.points,
        point_colors=scene.point_colors,
        up=scene.up,
        metric_scale=scene.metric_scale,
        source=None,
        parser="restored",
        image_space=scene.image_space,
        rendered=scene.rendered,
    )
    record = {
        "restorer": restorer.name,
        "removes": sorted(restorer.removes),
        "source": str(Path(degraded).resolve()),
        "views": len(sizes),
        "size": list(sizes[0]),
        "restore_seconds": round(seconds, 3),
        "seconds_per_view": round(seconds / max(len(sizes), 1), 4),
        "views_from_cache": cached,
    }
    with staged_output(target, overwrite=True) as tmp:
        writer = DatasetWriter(memory, tmp)
        for i in range(len(sizes)):
            writer.write_view(i, restored[i], cleans[i])
        writer.finish(None)
        (tmp / "restore.json").write_text(json.dumps(record, indent=1) + "\n")
    return target, record
