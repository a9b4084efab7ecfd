"""`metegs-process-images`: a folder of photos -> COLMAP poses with pycolmap -> a dataset metegs trains on.

    metegs-process-images photos/ datasets/my-scene
    metegs-train 3dgs --data datasets/my-scene

Writes ``images/`` (the photos, undistorted unless --no-undistort), ``sparse/0/`` (the largest model COLMAP built) and
``process_images.json`` (registered views, reprojection error, timings, options).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import tyro
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from metegs.cli import run_cli
from metegs.data.sfm import SfmOptions, SfmResult, run_sfm

STAGE_NAMES = {"extract": "features (SIFT)", "match": "matching", "map": "mapping (views registered)"}


@dataclass
class ProcessImagesArgs:
    """Estimate camera poses of a folder of photos with COLMAP (pycolmap) and write a COLMAP dataset."""

    images: Annotated[tyro.conf.Positional[Path], tyro.conf.arg(metavar="IMAGES_DIR")]
    """Folder of photos (jpg, png, tif) of one static scene."""
    output: Annotated[tyro.conf.Positional[Path], tyro.conf.arg(metavar="OUTPUT_DIR")]
    """Dataset folder to write (must not exist unless --overwrite)."""
    masks: Path | None = None
    """Folder of masks matched to the photos by file stem (white = use, black = ignore): keeps SfM on an
    object that turns in front of a static background, or off people and sky."""
    sfm: SfmOptions = field(default_factory=SfmOptions)
    """Structure-from-motion options."""
    overwrite: bool = False
    """Replace an existing output folder (only once the new one is complete)."""


def main(args: ProcessImagesArgs, console: Console | None = None) -> SfmResult:
    console = console or Console(stderr=True)
    columns = (TextColumn("{task.description:<28}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn())
    with Progress(*columns, console=console, transient=False) as progress:
        tasks: dict[str, int] = {}

        def report(stage: str, done: int, total: int) -> None:
            if stage not in tasks:
                tasks[stage] = progress.add_task(STAGE_NAMES[stage], total=total)
            progress.update(tasks[stage], completed=done, total=total)

        result = run_sfm(
            args.images, args.output, args.sfm, overwrite=args.overwrite, progress=report, masks=args.masks
        )
    registered, total = len(result.registered), result.num_images
    console.print(
        f"registered {registered} of {total} photos, {result.num_points} points, "
        f"mean reprojection error {result.mean_reprojection_error_px:.2f} px -> {result.output}",
        highlight=False,
    )
    if result.initial_pair == "forward":
        unknown = " and the focal length unknown" if result.focal_prior == "dropped" else ""
        console.print(
            f"mapping left photos out: mapped again from an initial pair that may move along its view{unknown}"
        )
    if result.unregistered:
        console.print(f"[yellow]not registered:[/] {', '.join(result.unregistered)}", highlight=False)
    if result.other_models:
        console.print(f"[yellow]COLMAP also built smaller models of {result.other_models} views (not written)[/]")
    console.print(f"next: metegs-train 3dgs --data {result.output}", highlight=False)
    return result


def entrypoint() -> None:
    run_cli(
        lambda: main(tyro.cli(ProcessImagesArgs, prog="metegs-process-images", config=(tyro.conf.OmitArgPrefixes,)))
    )
