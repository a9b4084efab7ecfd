"""Sparse points for captures that come with poses but no points (LLFF, nerfstudio, Blender): COLMAP's
point triangulator on the known poses, cached next to the photos.

3DGS starts far better from an SfM cloud than from random points: on the Ethiopian head LLFF capture (poses
only) random initialisation trains slower and varies more between runs. The pipeline is the standard
"triangulate with known poses" one: SIFT features of the training views, exhaustive matching with
geometric verification (sequential matching beyond 200 views; the `metegs-process-images` stages of
`metegs.data.sfm`), then
``pycolmap.triangulate_points`` with the cameras held fixed. Test views are never used. The points are
cached in ``<scene>/.metegs_points/points-<key>.npz``; the key covers the photos (path, size, mtime),
the cameras, the pycolmap version and `PIPELINE_VERSION`, so a changed photo, pose or pipeline triangulates
again. A triangulation that finds too few points is cached as well, so that a second run on the same photos falls
back to random points at once.
"""

from __future__ import annotations

import hashlib
import io
import os
import shutil
import tempfile
import warnings
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from metegs.cameras import Cameras
from metegs.data.sfm import SfmOptions, _extract, _match, _pycolmap, _quiet, hazed_peak_threshold
from metegs.files import atomic_write_bytes

CACHE_DIR = ".metegs_points"
"""Folder, inside the scene folder, of the cached triangulations."""

MIN_POINTS = 100
"""Fewer triangulated points than this is treated as a failure (the caller falls back to random points)."""

MAX_FEATURES = 4096
"""SIFT features per photo that triangulation extracts (at up to 1600 px, as metegs-process-images)."""

PIPELINE_VERSION = "triangulate-2"
"""Part of the cache key beside pycolmap's version: a change to the pipeline that changes its points changes this
(2: photos numbered in file order and a seeded geometric verification, which made the points the same every run)."""


@dataclass
class TriangulatedPoints:
    """What `triangulate_known_poses` found."""

    points: np.ndarray
    """[P, 3] float32 world positions."""
    colors: np.ndarray
    """[P, 3] float32 colours in [0, 1]."""
    num_views: int
    """Views the points were triangulated from."""
    reprojection_error_px: float
    """Mean reprojection error of the points' observations."""
    cache: Path | None = None
    """The cache file read or written (None when it could not be written)."""


def cache_key(image_paths: list[Path], cameras: Cameras, version: str, options: str) -> str:
    """Digest of the photos (path, size, mtime), the cameras, the tool's ``version`` and its ``options``."""
    h = hashlib.sha1(version.encode())
    cameras = cameras.to("cpu")  # one key whatever device the cameras are on
    for path in image_paths:
        stat = Path(path).stat()
        h.update(f"{Path(path).resolve()}|{stat.st_size}|{stat.st_mtime_ns}".encode())
    h.update(np.ascontiguousarray(cameras.camera_to_worlds.double().numpy()).tobytes())
    h.update(np.ascontiguousarray(cameras.intrinsics().double().numpy()).tobytes())
    h.update(np.stack([cameras.width.numpy(), cameras.height.numpy()]).astype(np.int64).tobytes())
    h.update(options.encode())
    return h.hexdigest()[:16]


def load_points(path: Path) -> TriangulatedPoints | None:
    """The points cached in ``path``, or None (with a warning) when the file cannot be read."""
    try:
        with np.load(path, allow_pickle=False) as f:
            return TriangulatedPoints(
                f["points"], f["colors"], int(f["num_views"]), float(f["reprojection_error_px"]), cache=path
            )
    except (OSError, KeyError, ValueError) as exc:
        warnings.warn(f"{path}: ignoring an unreadable cached triangulation ({exc})", stacklevel=3)
        return None


def save_points(path: Path, result: TriangulatedPoints) -> Path | None:
    """Cache ``result`` in ``path``; -> the path, or None (with a warning) when it cannot be written."""
    buf = io.BytesIO()
    np.savez(
        buf,
        points=result.points,
        colors=result.colors,
        num_views=result.num_views,
        reprojection_error_px=result.reprojection_error_px,
    )
    try:
        atomic_write_bytes(path, buf.getvalue())
    except OSError as exc:
        warnings.warn(f"{path}: cannot cache the triangulated points ({exc})", stacklevel=3)
        return None
    return path


def _stage(image_paths: list[Path], folder: Path) -> list[str]:
    """Links (copies where links fail) of the photos under unique names in ``folder``; returns the names."""
    names = []
    for i, src in enumerate(image_paths):
        name = f"{i:05d}{Path(src).suffix.lower()}"
        try:
            os.symlink(Path(src).resolve(), folder / name)
        except OSError:
            shutil.copy2(src, folder / name)
        names.append(name)
    return names


def _triangulate(image_paths: list[Path], cameras: Cameras, opts: SfmOptions) -> TriangulatedPoints:
    pycolmap = _pycolmap()
    _quiet(pycolmap)
    pycolmap.logging.minloglevel = 2  # not even the 'all threads' memory warning of every extraction chunk
    cameras = cameras.to("cpu")
    K = cameras.intrinsics().double().numpy()
    w2c = cameras.world_to_cameras().double().numpy()
    shared = bool(
        np.allclose(K, K[:1])
        and (cameras.width == cameras.width[0]).all()
        and (cameras.height == cameras.height[0]).all()
    )
    opts = replace(opts, camera_model="PINHOLE", single_camera=shared)
    with tempfile.TemporaryDirectory(prefix="metegs-triangulate-") as tmp:
        images = Path(tmp) / "images"
        images.mkdir()
        names = _stage(image_paths, images)
        db_path = Path(tmp) / "database.db"
        _extract(pycolmap, db_path, images, names, None, opts, lambda *a: None)
        _match(pycolmap, db_path, len(names), opts, lambda *a: None)
        rec = pycolmap.Reconstruction()
        db = pycolmap.Database.open(db_path)
        try:
            view_of = {name: i for i, name in enumerate(names)}
            db_images = db.read_all_images()
            for cam in db.read_all_cameras():  # the known intrinsics of the first view using each camera
                i = next(view_of[im.name] for im in db_images if im.camera_id == cam.camera_id)
                cam.model = pycolmap.CameraModelId.PINHOLE
                cam.params = [K[i, 0, 0], K[i, 1, 1], K[i, 0, 2], K[i, 1, 2]]
                db.update_camera(cam)
                rec.add_camera_with_trivial_rig(cam)
            for im in db_images:
                i = view_of[im.name]
                pose = pycolmap.Rigid3d(pycolmap.Rotation3d(w2c[i, :3, :3]), w2c[i, :3, 3])
                image = pycolmap.Image(name=im.name, camera_id=im.camera_id, image_id=im.image_id)
                rec.add_image_with_trivial_frame(image, pose)
        finally:
            db.close()
        out = Path(tmp) / "sparse"
        out.mkdir()
        rec = pycolmap.triangulate_points(rec, db_path, images, out)
        rec.extract_colors_for_all_images(str(images))
        pts = list(rec.points3D.values())
        points = np.array([p.xyz for p in pts], dtype=np.float32).reshape(-1, 3)
        colors = np.array([p.color for p in pts], dtype=np.float32).reshape(-1, 3) / 255.0
        error = float(rec.compute_mean_reprojection_error()) if pts else float("nan")
    return TriangulatedPoints(points, colors, len(names), error)


def contrast_options(contrast: float) -> SfmOptions:
    """Triangulation's options for photos whose brightness spans ``contrast`` (`photo_contrast`): SIFT's contrast
    threshold lowered where they are hazed (`hazed_peak_threshold`)."""
    return SfmOptions(max_features=MAX_FEATURES, peak_threshold=hazed_peak_threshold(contrast))


def triangulate_known_poses(
    image_paths: list[Path],
    cameras: Cameras,
    cache_dir: Path | None,
    opts: SfmOptions | None = None,
) -> TriangulatedPoints:
    """Sparse points of the scene seen by ``image_paths`` from their known ``cameras`` (one per photo).

    Reads the cached result from ``cache_dir`` when the photos and cameras are unchanged, else runs the
    pipeline of the module docstring and caches it there (``cache_dir`` None: no cache). Raises
    ``RuntimeError`` when fewer than `MIN_POINTS` points could be triangulated (a failure is cached too).
    """
    opts = opts or SfmOptions(max_features=MAX_FEATURES)
    if len(image_paths) != len(cameras):
        raise ValueError(f"{len(image_paths)} photos but {len(cameras)} cameras")
    pycolmap = _pycolmap()
    cache = None
    found = None
    if cache_dir is not None:
        options = f"{opts.max_image_size}|{opts.max_features}"
        if opts.peak_threshold > 0:  # the caches of the default threshold keep their keys
            options += f"|{opts.peak_threshold:.6g}"
        key = cache_key(image_paths, cameras, f"{pycolmap.__version__}|{PIPELINE_VERSION}", options)
        cache = Path(cache_dir) / f"points-{key}.npz"
        if cache.is_file():
            found = load_points(cache)
    if found is None:
        found = _triangulate(image_paths, cameras, opts)
        if cache is not None:  # a failure too: the same photos and poses would fail the same way, minutes later
            found.cache = save_points(cache, found)
    if len(found.points) < MIN_POINTS:
        where = f"; remembered in {found.cache} (delete it to try again)" if found.cache is not None else ""
        raise RuntimeError(
            f"only {len(found.points)} points could be triangulated from {found.num_views} views "
            f"(need {MIN_POINTS}): the photos have too little texture or overlap{where}"
        )
    return found
