"""The synthesis pipeline of `metegs-synth`: a rainy / foggy copy of a dataset from a real met record (or explicit
numbers), written atomically and reproducible from its seed.

The output holds a degraded copy of the dataset in its own format (the synthetic scene becomes a
nerfstudio dataset with its exact depth), the clean images in sibling ``*_clean/`` folders (parsers
expose them as clean references), ``weather.json`` (θ per view, the record, kinds, seed, scale) and
``preview.png`` (clean vs degraded for a few views).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from metegs.data.config import DatasetConfig
from metegs.errors import ConfigError, DataError
from metegs.meteo import limits
from metegs.validate import NON_NEGATIVE, POSITIVE, Range, check_config


@dataclass
class SynthConfig:
    """Degrade a dataset with weather from a met record (rain streaks, fog, lens drops, a plugin's weather)."""

    output: Path
    """Folder to write (must not exist unless --overwrite)."""
    data: Path | None = None
    """Scene folder (any format); none: the built-in synthetic scene, or the data of --depth-from's run."""
    parser: str | None = None
    """Force a data format (colmap, llff, nerfstudio, blender); none: detected."""
    depth_from: Path | None = None
    """A trained clean run (e.g. 3dgs) of this dataset: its depth is rendered for every view.
    Not needed for the synthetic scene (exact depth) or datasets that ship depth maps."""
    checkpoint: Path | None = None
    """Checkpoint of --depth-from to render (default: its latest)."""
    record: Path | None = None
    """Met record (csv, METAR, GHCNh, ISD, Open-Meteo; reader detected, PRSA csv options automatic);
    none and no explicit values: the storm excerpt shipped with metegs at its default time."""
    time: tuple[str, ...] = ()
    """Capture time(s), ISO 8601 (UTC unless an offset is given); several are spread over the views in order."""
    window: str = "1h"
    """Aggregation window around each capture time."""
    agg: str = "max"
    """Aggregation of the window (max, mean, min)."""
    reader: str | None = None
    """Reader of --record; none: detected from the file."""
    set: tuple[str, ...] = ()
    """Reader options as KEY=VALUE (e.g. precip_column=RAIN)."""
    station: str | None = None
    """Station, for records holding several."""
    precip_mm_h: Annotated[float | None, Range(0, limits.MAX_PRECIP_RATE_MM_H)] = None
    """Explicit precipitation rate, mm/h (instead of a record)."""
    visibility_m: Annotated[float | None, Range(limits.MIN_VISIBILITY_M)] = None
    """Visibility, m: explicit, or replacing the record's (PRSA records have none)."""
    wind_speed_m_per_s: Annotated[float | None, Range(0, limits.MAX_WIND_M_S)] = None
    """Explicit 10-m wind speed, m/s."""
    wind_dir_deg: Annotated[float | None, Range(0, 360)] = None
    """Explicit direction the wind blows from, degrees true."""
    family: Literal["physical", "independent"] = "physical"
    """Weather generator: metegs's own weather models from θ (physical), or 2D streak layers, heterogeneous fog
    and blurred lens drops made without them (independent: a benchmark a method cannot fit with its own model)."""
    kinds: str = "rain+fog"
    """Weather to add: registered weather kinds joined with + (rain, fog, rain+fog; a plugin's, e.g. snow or
    snow+fog); append +drops for lens drops when it rains (θ's count, else a default); the fog of rain+fog
    includes the rain's own veil."""
    seed: int = 0
    """Seed of the rain and lens drops (view v draws from (seed, v))."""
    metres_per_unit: Annotated[float | None, POSITIVE] = None
    """Metres per scene unit; none: the scene's metric scale, else a guess that puts the median depth at
    --assumed-depth-m (printed)."""
    assumed_depth_m: Annotated[float, POSITIVE] = 4.0
    """Median scene depth assumed for scenes without a metric scale, m (LLFF, COLMAP)."""
    exposure_s: Annotated[float | None, POSITIVE] = None
    """Exposure time of the views, s (sets streak length); none: the cameras', else 1/60."""
    capture_width_px: Annotated[int, NON_NEGATIVE] = 1920
    """Width of the photos as the camera took them (streak visibility depends on the sensor's resolution, not
    the dataset's); 0: the dataset's stored width."""
    rain_far_m: Annotated[float | None, POSITIVE] = None
    """Fixed far depth of rain streaks, m; none: where a streak's contrast falls below two 8-bit levels
    (small images see few streaks by that rule)."""
    preview_views: Annotated[int, NON_NEGATIVE] = 4
    """Number of views on the contact sheet."""
    overwrite: bool = False
    """Replace an existing output folder."""
    device: str | None = None
    """Torch device to render depth from --depth-from on (default: the run's)."""
    dataset: DatasetConfig = field(default_factory=DatasetConfig)
    """Options of the data parsers (the synthetic scene's size, the split); with --depth-from and no --data,
    the run's."""

    def __post_init__(self) -> None:
        check_config(self)


def synthesise(args: SynthConfig, console: Console | None = None) -> Path:
    """Write the degraded dataset ``args`` describe; returns its folder."""
    from metegs.data.parsers.base import parse_scene
    from metegs.engine.run import depths_from_run, load_run_config
    from metegs.files import staged_output
    from metegs.meteo.theta_plan import plan_from_record, plan_from_values
    from metegs.synth.contact_sheet import contact_sheet, encode_png, pick_views, record_label
    from metegs.synth.depth import guess_metres_per_unit
    from metegs.synth.writers import DatasetWriter
    from metegs.weather.conditions import theta_camera
    from metegs.weather.degrade import iter_degraded_views
    from metegs.weather.kinds import join_kinds, parse_kinds

    console = console or Console(stderr=True)
    t0 = time.perf_counter()
    kinds = join_kinds(parse_kinds(args.kinds, "--kinds"))
    if args.output.exists() and not args.overwrite:
        raise ConfigError(f"{args.output} exists; choose another --output or pass --overwrite")
    explicit = any(v is not None for v in (args.precip_mm_h, args.wind_speed_m_per_s, args.wind_dir_deg))
    if explicit and (args.record is not None or args.time):
        raise ConfigError("give either --record/--time or explicit --precip-mm-h/--wind-*, not both")
    data, parser, options = args.data, args.parser, args.dataset
    if data is None and args.depth_from is not None:  # the run's own dataset
        run_config = load_run_config(args.depth_from)
        data, parser, options = run_config.data, parser or run_config.parser, run_config.dataset
    scene = parse_scene(data, parser, options)
    n = len(scene)
    console.print(f"scene: {scene.source or 'synthetic'} ({scene.parser}, {n} views)", highlight=False)

    # depth
    depth_note = "exact (synthetic scene)" if scene.parser == "synthetic" else "shipped with the dataset"
    depths = scene.depths
    if args.depth_from is not None:
        with _progress(console) as progress:
            task = progress.add_task("render depth", total=n)
            depths, depth_note = depths_from_run(
                args.depth_from, scene, args.checkpoint, progress=lambda i: progress.advance(task), device=args.device
            )
    if depths is None:
        raise DataError(
            scene.source,
            "no depth for this dataset: train a clean run first (metegs-train 3dgs --data ...) and pass "
            "--depth-from RUN_DIR",
        )

    # scale
    if args.metres_per_unit is not None:
        mpu, mpu_note = float(args.metres_per_unit), "given (--metres-per-unit)"
    elif scene.metric_scale is not None:
        mpu, mpu_note = float(scene.metric_scale), "the scene's metric scale"
    else:
        mpu = guess_metres_per_unit(depths, args.assumed_depth_m)
        mpu_note = f"guess: median depth taken as {args.assumed_depth_m:g} m (--assumed-depth-m)"
    console.print(f"metres per unit: {mpu:.4g} ({mpu_note})", highlight=False)

    # θ
    camera = theta_camera(scene.cameras, mpu, args.exposure_s, args.capture_width_px, far_m=args.rain_far_m)
    if explicit:
        plan = plan_from_values(
            n, camera, args.precip_mm_h or 0.0, args.visibility_m, args.wind_speed_m_per_s or 0.0, args.wind_dir_deg
        )
    else:
        from metegs.meteo import parse_options

        plan = plan_from_record(
            n,
            camera,
            args.record,
            list(args.time) or None,
            reader=args.reader,
            options=parse_options(args.set),
            window=args.window,
            agg=args.agg,
            station=args.station,
            visibility_m=args.visibility_m,
        )
    for t, th in zip(plan.times, plan.distinct):
        r, f = th.rain, th.fog
        streaks = (
            f"{r.count} streaks/view (near {r.near_m:.2f} m, far {r.far_m:.2f} m), "
            if "rain" in kinds.split("+")
            else ""
        )
        console.print(
            f"θ{' at ' + t if t else ''}: P {r.precip_mm_per_h:.2f} mm/h ({r.intensity_class}), {streaks}"
            f"exposure {r.exposure_s:.4g} s, "
            f"visibility {_vis(f.visibility_m)}, fog {'on' if f.active else 'off'}, "
            f"lens drops {th.drops.count}",
            highlight=False,
        )

    # degrade and write
    picks = set(pick_views(n, args.preview_views))
    preview: dict[int, tuple[np.ndarray, np.ndarray, dict]] = {}
    records = []
    with staged_output(args.output, args.overwrite) as tmp:
        writer = DatasetWriter(scene, tmp)
        with _progress(console) as progress:
            task = progress.add_task(f"degrade ({kinds}, {args.family})", total=n)
            for view in iter_degraded_views(
                scene, plan.thetas, kinds=kinds, seed=args.seed, metres_per_unit=mpu, depths=depths, family=args.family
            ):
                writer.write_view(view.index, view.image, view.clean)
                record = dict(view.record)
                record["time"] = plan.times[plan.view_time_index[view.index]]
                record["image"], record["clean_image"] = writer.image_rel[view.index], writer.clean_rel[view.index]
                records.append(record)
                if view.index in picks:
                    preview[view.index] = (view.clean, view.image, record_label(record))
                progress.advance(task)
        writer.finish(depths if writer.format == "nerfstudio" and scene.source is None else None)
        weather = {
            "created_by": "metegs-synth",
            "format": writer.format,
            "source": str(scene.source) if scene.source is not None else "synthetic scene",
            "kinds": kinds,
            "family": args.family,
            "seed": args.seed,
            "metres_per_unit": mpu,
            "metres_per_unit_source": mpu_note,
            "depth": depth_note,
            "record": {**plan.source, "times": plan.times},
            "views": records,
        }
        (tmp / "weather.json").write_text(json.dumps(weather, indent=1) + "\n")
        order = sorted(preview)
        title = f"metegs-synth {kinds} ({args.family}), seed {args.seed}: " + (
            f"{Path(plan.source['file']).name} {', '.join(t for t in plan.times if t)}"
            if "file" in plan.source
            else "explicit values"
        )
        sheet = contact_sheet(
            [preview[i][0] for i in order],
            [preview[i][1] for i in order],
            [preview[i][2] for i in order],
            [Path(scene.names[i]).stem for i in order],
            title=title,
        )
        (tmp / "preview.png").write_bytes(encode_png(sheet))
    console.print(
        f"wrote {args.output} ({writer.format}, {n} views, clean images alongside, weather.json, "
        f"preview.png) in {time.perf_counter() - t0:.1f} s",
        highlight=False,
    )
    return args.output


def _vis(v: float | None) -> str:
    return "n/a" if v is None else f"{v:.0f} m"


def _progress(console: Console) -> Progress:
    return Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=console,
        transient=True,
    )
