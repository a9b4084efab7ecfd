"""Structure from motion with pycolmap: a folder of photos -> a COLMAP dataset metegs trains on.

The pipeline is COLMAP's standard one: SIFT feature extraction, exhaustive or sequential matching with
geometric verification, incremental mapping. The result is written in the layout the ``colmap`` parser
reads (``<output>/images/``, ``<output>/sparse/0/``) plus ``<output>/process_images.json`` (options,
registered and unregistered views, reprojection error, timings). Everything is built in a hidden
folder next to ``<output>`` and renamed into place at the end, so an interrupted run leaves nothing
half-written.
"""

from __future__ import annotations

import json
import shutil
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Annotated, Literal, TypeVar

import cv2
import numpy as np

from metegs.data.images import LUMA, load_image, load_mask, read_image_bytes
from metegs.errors import ConfigError, DataError
from metegs.files import staged_output
from metegs.validate import NON_NEGATIVE, check_config

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp")
"""File types taken from the photo folder (case-insensitive)."""

EXHAUSTIVE_LIMIT = 200
"""With ``matcher="auto"``, folders up to this many photos are matched exhaustively, larger ones sequentially."""


@dataclass
class SfmOptions:
    """Options of `run_sfm` (the CLI flags of ``metegs-process-images``)."""

    matcher: Literal["auto", "exhaustive", "sequential"] = "auto"
    """Pairs to match: every pair, or neighbours in file-name order (video frames); auto picks by count."""
    max_image_size: int = 1600
    """Longest side (px) at which features are extracted; 0 keeps the photos' size."""
    max_features: int = 8192
    """SIFT features kept per photo."""
    peak_threshold: Annotated[float, NON_NEGATIVE] = 0.0
    """SIFT's contrast threshold on the difference of Gaussians; 0: COLMAP's 0.02/3, lowered for hazed photos
    (brightness spanning under 0.5 between its 0.5 % and 99.5 % quantiles) by their span over a clear photo's 0.8."""
    accurate_features: bool = False
    """SIFT with affine shape and domain-size pooling plus guided matching: 2-3x slower, registers more
    views of weakly textured or turning objects."""
    min_inliers: int = 30
    """Verified matches needed to register a view (COLMAP's abs_pose_min_num_inliers; the other mapper
    thresholds scale with it). Lower it (e.g. 15) for hard scenes: more views, more risk of a wrong pose."""
    camera_model: str = "SIMPLE_RADIAL"
    """COLMAP camera model (e.g. PINHOLE, SIMPLE_RADIAL, OPENCV); the colmap parser undistorts the others."""
    undistort: bool = True
    """Write undistorted photos with a PINHOLE model (COLMAP's image undistorter) so that every tool,
    metegs-synth included, takes them as they are; off keeps the photos and the fitted distortion."""
    single_camera: bool = True
    """All photos share one camera (same lens and zoom); turn off for mixed cameras."""
    sequential_overlap: int = 10
    """With the sequential matcher, each photo is matched with this many following ones."""
    min_registered: int = 3
    """Fewer registered views than this is an error."""
    num_threads: int = -1
    """CPU threads for COLMAP's feature extraction and matching (-1: all; poses are mapped on one). Only 1 gives the
    same poses every run: on several the matcher's approximate search differs now and then (Lund: 1 run in 7)."""
    seed: int = 0
    """Random seed of the matching's and the mapper's RANSAC and of the mapper's initial pair."""


@dataclass
class SfmResult:
    """What `run_sfm` produced (also written to ``process_images.json``)."""

    output: str
    num_images: int
    registered: list[str]
    unregistered: list[str]
    num_points: int
    mean_reprojection_error_px: float
    other_models: list[int] = field(default_factory=list)
    """Registered-view counts of the smaller models COLMAP also built (not written)."""
    initial_pair: str = "default"
    """How the kept model's first two views were chosen: "default" (COLMAP's checks) or "forward" (mapping stalled,
    `RETRY_BELOW`; mapped again allowing a pair that moves along its view, `FORWARD_INIT_TRI_ANGLE_DEG`)."""
    focal_prior: str = "exif"
    """Where the kept model's focal length started: "exif" (the photos' EXIF, else COLMAP's guess), or "dropped"
    (mapping stalled both ways from EXIF; mapping with the focal length unknown registered more)."""
    timings_s: dict[str, float] = field(default_factory=dict)
    options: dict = field(default_factory=dict)


SIFT_PEAK_THRESHOLD = 0.02 / 3
"""COLMAP's SIFT contrast threshold (its peak threshold over its 3 scales per octave)."""

CLEAR_CONTRAST = 0.8
"""The span of a clear photo's brightness between its 0.5 % and 99.5 % quantiles: 0.79-0.93 in the clean views of
the Ethiopian head, the instant-ngp fox and the Lund street; their 200 m fog leaves 0.23-0.31 of it."""

HAZY_CONTRAST = 0.5
"""Photos whose brightness spans less than this are taken as hazed (fog, dense haze); dimmer clear scenes span
0.6-0.8 (the built-in scene 0.65), heavy rain 0.66-0.82."""


T = TypeVar("T")

CONTRAST_SAMPLE = 16
"""The most photos `photo_contrast` reads, evenly spread over a capture (`contrast_sample`)."""


def contrast_sample(items: Sequence[T]) -> Sequence[T]:
    """Up to `CONTRAST_SAMPLE` of ``items``, evenly spread over them: the photos `photo_contrast` reads."""
    return items[:: max(1, len(items) // CONTRAST_SAMPLE)][:CONTRAST_SAMPLE]


def photo_contrast(images) -> float:
    """Median over ``images`` ([H, W, 3] arrays or tensors in [0, 1]; `contrast_sample` of them) of the span of their
    luminance between its 0.5 % and 99.5 % quantiles (every 4th pixel of each side)."""
    spans = []
    for image in contrast_sample(images):
        if hasattr(image, "detach"):  # a tensor, maybe on the GPU
            image = image[::4, ::4].detach().cpu().numpy()
        else:
            image = np.asarray(image)[::4, ::4]
        luma = image[..., :3].astype(np.float32) @ np.asarray(LUMA, dtype=np.float32)
        lo, hi = np.quantile(luma, [0.005, 0.995])
        spans.append(float(hi - lo))
    return float(np.median(spans))


def hazed_peak_threshold(contrast: float) -> float:
    """SIFT's contrast threshold for photos whose brightness spans ``contrast`` (`photo_contrast`): where that is
    under `HAZY_CONTRAST`, COLMAP's scaled by it against a clear photo's `CLEAR_CONTRAST` (at least 0.2 of it), as
    stretching the photos to a clear one's span would (SIFT's responses scale with the contrast); else 0 (COLMAP's)."""
    if contrast >= HAZY_CONTRAST:
        return 0.0
    return SIFT_PEAK_THRESHOLD * max(0.2, contrast / CLEAR_CONTRAST)


StageCallback = Callable[[str, int, int], None]
"""``callback(stage, done, total)``: progress of "extract", "match" and "map"."""


def list_photos(folder: Path) -> list[str]:
    """Sorted names of the readable photos directly in ``folder``; a clear error when there are none."""
    folder = Path(folder)
    if not folder.is_dir():
        raise DataError(folder, "photo folder does not exist")
    names = sorted(p.name for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)
    if not names:
        raise DataError(folder, f"no photos found (looked for {', '.join(IMAGE_SUFFIXES)})")
    unreadable = [n for n in names if not cv2.haveImageReader(str(folder / n))]
    if unreadable:
        raise DataError(folder / unreadable[0], f"not a readable image ({len(unreadable)} unreadable in the folder)")
    for name in names:
        read_image_bytes(folder / name)  # refuses empty and truncated JPEG/PNG files, naming them
    return names


def stage_masks(masks: Path, names: list[str], dst: Path) -> None:
    """Masks (white = keep) matched to ``names`` by file stem -> COLMAP's ``dst/<name>.png`` (0 = ignore)."""
    masks = Path(masks)
    if not masks.is_dir():
        raise DataError(masks, "mask folder does not exist")
    by_stem = {p.stem: p for p in masks.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES}
    missing = [n for n in names if Path(n).stem not in by_stem]
    if missing:
        raise DataError(
            masks, f"no mask for {len(missing)} photo(s), e.g. {missing[0]} (masks are matched by file stem)"
        )
    dst.mkdir(parents=True)
    for name in names:
        mask = load_mask(by_stem[Path(name).stem])  # DataError naming a missing, truncated or unreadable mask
        cv2.imwrite(str(dst / f"{name}.png"), np.where(mask > 0.5, 255, 0).astype(np.uint8))


def _pycolmap():
    try:
        import pycolmap
    except ImportError as exc:  # pragma: no cover - pycolmap is a dependency
        raise ConfigError("metegs-process-images needs pycolmap (pip install pycolmap)") from exc
    return pycolmap


def _quiet(pycolmap) -> None:
    """Keep COLMAP's own log to warnings and errors: progress is shown by the caller."""
    pycolmap.logging.minloglevel = 1


def _extract(
    pycolmap, db: Path, images: Path, names: list[str], masks: Path | None, opts: SfmOptions, progress: StageCallback
) -> None:
    """SIFT features of every photo into ``db`` (none where ``masks`` are black), the photos numbered in the order of
    ``names``. COLMAP numbers the photos of one call as its threads finish them, and that numbering steers matching
    and mapping, so that the same photos posed differently from run to run (the Lund street's 29: 27, 28 or 29
    registered). With one camera the first photo makes it and the others are entered in order beforehand
    (`_enter_in_order`), then extracted on every thread; with a camera per photo they are extracted one by one."""
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = opts.camera_model
    if masks is not None:
        reader.mask_path = str(masks)
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size = opts.max_image_size if opts.max_image_size > 0 else -1
    extraction.num_threads = opts.num_threads
    extraction.sift.max_num_features = opts.max_features
    if opts.peak_threshold > 0:
        extraction.sift.peak_threshold = opts.peak_threshold
    extraction.sift.estimate_affine_shape = opts.accurate_features
    extraction.sift.domain_size_pooling = opts.accurate_features
    mode = pycolmap.CameraMode.SINGLE if opts.single_camera else pycolmap.CameraMode.PER_IMAGE

    def extract(batch: list[str]) -> None:
        pycolmap.extract_features(
            db,
            images,
            image_names=batch,
            camera_mode=mode,
            reader_options=reader,
            extraction_options=extraction,
            device=pycolmap.Device.cpu,
        )

    extract(names[:1])
    progress("extract", 1, len(names))
    if opts.single_camera:
        reader.existing_camera_id = _enter_in_order(pycolmap, db, names[1:])
        chunk = 8  # the photos are numbered already: a chunk shows progress
    else:
        chunk = 1
    for start in range(1, len(names), chunk):
        extract(names[start : start + chunk])
        progress("extract", min(start + chunk, len(names)), len(names))


def _enter_in_order(pycolmap, db: Path, names: list[str]) -> int:
    """Enter ``names`` into ``db`` in that order, each a frame of the rig of the camera that ``db``'s one photo made,
    as COLMAP's extraction enters a photo of that camera; returns the camera's id."""
    database = pycolmap.Database.open(db)
    try:
        (camera,) = database.read_all_cameras()
        (rig,) = database.read_all_rigs()
        sensor = pycolmap.sensor_t(type=pycolmap.SensorType.CAMERA, id=camera.camera_id)
        for name in names:
            image_id = database.write_image(pycolmap.Image(name=name, camera_id=camera.camera_id))
            frame = pycolmap.Frame(rig_id=rig.rig_id)
            frame.add_data_id(pycolmap.data_t(sensor_id=sensor, id=image_id))
            database.write_frame(frame)
    finally:
        database.close()
    return camera.camera_id


def _match(pycolmap, db: Path, count: int, opts: SfmOptions, progress: StageCallback) -> str:
    """Match feature pairs with geometric verification (its RANSAC seeded with ``opts.seed``, so that the same matches
    verify the same on any number of threads); returns the matcher used."""
    matcher = opts.matcher
    if matcher == "auto":
        matcher = "exhaustive" if count <= EXHAUSTIVE_LIMIT else "sequential"
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = opts.num_threads
    matching.guided_matching = opts.accurate_features
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = opts.seed
    progress("match", 0, 1)
    if matcher == "exhaustive":
        pycolmap.match_exhaustive(
            db, matching_options=matching, verification_options=verification, device=pycolmap.Device.cpu
        )
    else:
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = opts.sequential_overlap
        pycolmap.match_sequential(
            db,
            matching_options=matching,
            pairing_options=pairing,
            verification_options=verification,
            device=pycolmap.Device.cpu,
        )
    progress("match", 1, 1)
    return matcher


def _map(
    pycolmap,
    db: Path,
    images: Path,
    sparse: Path,
    count: int,
    opts: SfmOptions,
    progress: StageCallback,
    forward: bool = False,
):
    """Incremental mapping; returns the reconstructions COLMAP built, largest first. ``forward``: the initial pair
    may move along its viewing direction, with a small triangulation angle (`FORWARD_INIT_TRI_ANGLE_DEG`)."""
    mapping = pycolmap.IncrementalPipelineOptions()
    if forward:
        mapping.mapper.init_max_forward_motion = 1.0
        mapping.mapper.init_min_tri_angle = FORWARD_INIT_TRI_ANGLE_DEG
    mapping.num_threads = 1  # on several threads the same matches mapped to different poses from run to run
    mapping.random_seed = opts.seed
    relax = opts.min_inliers / 30.0  # relative to COLMAP's defaults
    mapping.min_num_matches = min(15, opts.min_inliers)
    mapping.mapper.abs_pose_min_num_inliers = opts.min_inliers
    mapping.mapper.abs_pose_min_inlier_ratio = min(0.25, 0.25 * relax)
    mapping.mapper.init_min_num_inliers = max(30, min(100, round(100 * relax)))
    registered = [0]

    def initial_pair() -> None:
        registered[0] = 2
        progress("map", 2, count)

    def next_image() -> None:
        registered[0] += 1
        progress("map", min(registered[0], count), count)

    sparse.mkdir(parents=True, exist_ok=True)
    models = pycolmap.incremental_mapping(
        db, images, sparse, options=mapping, initial_image_pair_callback=initial_pair, next_image_callback=next_image
    )
    return sorted(models.values(), key=lambda rec: rec.num_reg_images(), reverse=True)


RETRY_SEEDS = 4
"""Mapping attempts (initial seeds) of each retry when mapping stalls."""
RETRY_BELOW = 0.9
"""Mapping counts as stalled below this share of the photos registered (a few photos that match nothing do not make
a large capture map again)."""
FORWARD_INIT_TRI_ANGLE_DEG = 4.0
"""Smallest triangulation angle of a retry's initial pair (COLMAP: 16°). Photos taken walking along a street or
corridor look where they move: COLMAP's initial pair must not (``init_max_forward_motion`` 0.95) and needs 16°,
so OpenSfM's 29-photo Lund street started from a pair whose focal length diverged (2 of 29 registered, 3 of 3
seeds); allowed both, 27 of 29 from EXIF. With the focal length unknown instead it registered 29 of 29 as a
broken model (the cameras turned 40° between two photos a step apart), so that retry comes last."""


def _drop_focal_priors(pycolmap, db: Path) -> bool:
    """Mark every camera's focal length in ``db`` as unknown; returns whether any had a prior (from EXIF)."""
    database = pycolmap.Database.open(db)
    try:
        cameras = [cam for cam in database.read_all_cameras() if cam.has_prior_focal_length]
        for cam in cameras:
            cam.has_prior_focal_length = False
            database.update_camera(cam)
    finally:
        database.close()
    return bool(cameras)


def _num_registered(models: list) -> int:
    return models[0].num_reg_images() if models else 0


def _is_pinhole(rec) -> bool:
    return all(cam.model.name in ("PINHOLE", "SIMPLE_PINHOLE") for cam in rec.cameras.values())


def _undistort(pycolmap, rec, model: Path, images: Path, scratch: Path, final: Path) -> None:
    """COLMAP's image undistorter: ``images`` are replaced by undistorted copies and ``final`` gets the
    PINHOLE model that goes with them."""
    model.mkdir(parents=True)
    rec.write(model)
    pycolmap.undistort_images(scratch, model, images)
    shutil.rmtree(images)
    (scratch / "images").rename(images)
    for file in (scratch / "sparse").iterdir():
        file.rename(final / file.name)
    shutil.rmtree(scratch)


def run_sfm(
    images: Path,
    output: Path,
    opts: SfmOptions | None = None,
    overwrite: bool = False,
    progress: StageCallback | None = None,
    masks: Path | None = None,
) -> SfmResult:
    """Photos in ``images`` -> COLMAP dataset at ``output`` (``images/``, ``sparse/0/``, ``process_images.json``).

    ``masks``: a folder of masks matched to the photos by file stem (white = use, black = ignore), e.g. to
    keep SfM on an object that turns on a turntable in front of a static background.
    """
    opts = opts or SfmOptions()
    check_config(opts)
    progress = progress or (lambda stage, done, total: None)
    pycolmap = _pycolmap()
    _quiet(pycolmap)
    images = Path(images)
    output = Path(output)
    if images.resolve() == output.resolve() or output.resolve() in images.resolve().parents:
        raise ConfigError(f"{output}: the output must not contain the photo folder {images}")
    if output.exists() and not overwrite:
        raise ConfigError(f"{output} exists; choose another output folder or pass --overwrite")
    names = list_photos(images)
    if opts.peak_threshold == 0:  # hazed photos: as many features as their contrast allows (recorded in the options)
        sample = [load_image(images / n) for n in contrast_sample(names)]
        opts = replace(opts, peak_threshold=hazed_peak_threshold(photo_contrast(sample)))
    timings: dict[str, float] = {}
    with staged_output(output, overwrite=overwrite) as tmp:
        staged_images = tmp / "images"
        staged_images.mkdir()
        for name in names:
            shutil.copy2(images / name, staged_images / name)
        staged_masks = None
        if masks is not None:
            staged_masks = tmp / "colmap_masks"
            stage_masks(masks, names, staged_masks)
        db = tmp / "database.db"
        t0 = time.perf_counter()
        _extract(pycolmap, db, staged_images, names, staged_masks, opts, progress)
        timings["extract"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        matcher = _match(pycolmap, db, len(names), opts, progress)
        timings["match"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        work = tmp / "mapper"
        models = _map(pycolmap, db, staged_images, work, len(names), opts, progress)
        how = {"initial_pair": "default", "focal_prior": "exif"}
        # stalled: map again from a few seeds with a forward-moving initial pair allowed (a street walk), then with
        # the focal length unknown as well (a wrong EXIF focal length, as a phone's crop or zoom writes, marks true
        # pairs uncalibrated); keep the model that registers the most photos
        for focal in ("exif", "dropped"):
            if _num_registered(models) >= RETRY_BELOW * len(names):
                break
            if focal == "dropped" and not _drop_focal_priors(pycolmap, db):
                break
            for attempt in range(RETRY_SEEDS):
                retry_dir = tmp / f"mapper-forward-{focal}-{attempt}"
                retry_opts = replace(opts, seed=opts.seed + attempt)
                retry = _map(pycolmap, db, staged_images, retry_dir, len(names), retry_opts, progress, forward=True)
                if _num_registered(retry) > _num_registered(models):
                    shutil.rmtree(work, ignore_errors=True)
                    models, work, how = retry, retry_dir, {"initial_pair": "forward", "focal_prior": focal}
                else:
                    shutil.rmtree(retry_dir, ignore_errors=True)
                if _num_registered(models) == len(names):
                    break
        timings["map"] = time.perf_counter() - t0
        best = models[0] if models else None
        registered = sorted(best.images[i].name for i in best.reg_image_ids()) if best else []
        progress("map", len(registered), len(names))
        if len(registered) < opts.min_registered:
            raise DataError(
                images,
                f"only {len(registered)} of {len(names)} photos could be registered "
                f"(need {opts.min_registered}); photos need more overlap and texture — try "
                "--accurate-features, --min-inliers 15, --masks for a turning object, "
                "or --no-single-camera for mixed cameras",
            )
        final = tmp / "sparse" / "0"
        final.mkdir(parents=True)
        if opts.undistort and not _is_pinhole(best):
            t0 = time.perf_counter()
            _undistort(pycolmap, best, work / "best", staged_images, tmp / "undistorted", final)
            timings["undistort"] = time.perf_counter() - t0
        else:
            best.write(final)
        shutil.rmtree(work)
        if staged_masks is not None:
            shutil.rmtree(staged_masks)
        db.unlink()
        result = SfmResult(
            output=str(output),
            num_images=len(names),
            registered=registered,
            unregistered=sorted(set(names) - set(registered)),
            num_points=best.num_points3D(),
            mean_reprojection_error_px=float(best.compute_mean_reprojection_error()),
            other_models=[rec.num_reg_images() for rec in models[1:]],
            **how,
            timings_s={k: round(v, 2) for k, v in timings.items()},
            options={**asdict(opts), "matcher": matcher, "masks": None if masks is None else str(masks)},
        )
        (tmp / "process_images.json").write_text(json.dumps(asdict(result), indent=2) + "\n")
    return result
