"""nerfstudio ``transforms.json`` scenes.

Intrinsics ``fl_x, fl_y, cx, cy, w, h`` are read at the top level and may be overridden per frame.
``transform_matrix`` is camera-to-world in OpenGL camera axes and is converted to OpenCV axes; the
world frame is kept as is (nerfstudio's world is +Z up). Frames whose image file is missing are
skipped with one warning. The split comes from ``train_filenames`` / ``test_filenames`` (``val_filenames``
when there is no test list) when present, else every n-th view is held out. ``ply_file_path`` points
(x, y, z and optional red, green, blue) are read with a small numpy PLY reader. Clean references (as
`metegs-synth` writes them) come from the sibling folder of the image folder (``images_clean/``), and a
per-frame ``depth_file_path`` naming a ``.npy`` file (float32 [H, W] z-depth in scene units, as
`metegs-synth` writes them) gives the scene's depth maps when every frame has one.

Lens distortion (``k1, k2, k3, k4, p1, p2`` or nerfstudio's ``distortion_params`` [k1, k2, k3, k4, p1, p2],
per frame or at the top level, as ``ns-process-data`` and instant-ngp write them) is undistorted once and
cached when ``--dataset.undistort`` is on (the default), as for COLMAP (`metegs.data.undistort`):
``OPENCV`` (and the other pinhole models) with k1, k2, k3, p1, p2, and ``OPENCV_FISHEYE`` with k1..k4; clean
references and masks are undistorted with their view. A per-frame ``mask_path`` (white = keep) gives the
scene's masks when every frame has one (``--dataset.use-masks``). A radial k4 outside the fisheye model, distortion beside
depth maps, and other camera models (equirectangular, ...) raise a DataError naming the frame.
"""

from __future__ import annotations

import json
import os
import warnings
from pathlib import Path
from typing import ClassVar

import numpy as np
import torch

from metegs.cameras import Cameras, opengl_to_opencv
from metegs.data.config import DatasetConfig
from metegs.data.exif import exposure_times_s
from metegs.data.parsers.clean import find_clean_paths
from metegs.data.scene import SceneData, split_every_nth
from metegs.data.undistort import Distortion, cache_folder, undistorted_copy
from metegs.errors import DataError
from metegs.gaussians.ply import check_finite, read_ply_vertices

_INTRINSICS = ("fl_x", "fl_y", "cx", "cy", "w", "h")
_DISTORTION = ("k1", "k2", "k3", "k4", "p1", "p2")
_PERSPECTIVE = ("PINHOLE", "SIMPLE_PINHOLE", "OPENCV", "SIMPLE_RADIAL", "RADIAL")
_FISHEYE = "OPENCV_FISHEYE"


def read_json(path: Path) -> dict:
    """Parse a JSON object file; DataError naming the file if it is missing, malformed or not an object."""
    try:
        with open(path, encoding="utf-8") as f:
            meta = json.load(f)
    except FileNotFoundError as exc:
        raise DataError(path, "file does not exist") from exc
    except (OSError, ValueError) as exc:
        raise DataError(path, f"cannot parse JSON: {exc}") from exc
    if not isinstance(meta, dict):
        raise DataError(path, "expected a JSON object at the top level")
    return meta


def number(value, source: Path, what: str) -> float:
    """``value`` as a finite float; DataError naming the file and ``what`` otherwise."""
    try:
        out = float(value)
    except (TypeError, ValueError):
        out = None
    if out is None or not np.isfinite(out):
        raise DataError(source, f"{what} must be a finite number, got {value!r}")
    return out


def read_npy(path: Path, what: str) -> np.ndarray:
    """A numeric ``.npy`` array; DataError naming the file when it is missing, not a .npy file or truncated.

    The file is memory-mapped, so a header that claims more data than the file holds allocates nothing.
    """
    try:
        with open(path, "rb") as f:
            if f.read(6) != b"\x93NUMPY":
                raise DataError(path, f"the {what} file is not a .npy array (no NUMPY magic bytes)")
        data = np.load(path, mmap_mode="r", allow_pickle=False)
    except FileNotFoundError as exc:
        raise DataError(path, f"{what}: file does not exist") from exc
    except (OSError, ValueError, EOFError) as exc:
        raise DataError(path, f"cannot read the {what} (truncated, or not a plain numeric array): {exc}") from exc
    if data.dtype.kind not in "biuf":
        raise DataError(path, f"the {what} must be a numeric array, got dtype {data.dtype}")
    return np.array(data)


def gl_matrix(value, source: Path, where: str) -> np.ndarray:
    """A 4x4 (or 3x4) camera-to-world list from JSON -> float64 [4, 4]; DataError naming ``where`` if malformed."""
    try:
        m = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise DataError(source, f"{where} has a non-numeric 'transform_matrix'") from exc
    if m.shape == (3, 4):
        m = np.concatenate([m, [[0.0, 0.0, 0.0, 1.0]]])
    if m.shape != (4, 4) or not np.isfinite(m).all():
        raise DataError(source, f"{where} has a malformed 'transform_matrix' (expected 4x4 finite numbers)")
    return m


def gl_to_cv(c2w_gl: np.ndarray) -> np.ndarray:
    """[N, 4, 4] OpenGL camera-to-worlds -> [N, 4, 4] float32 OpenCV camera-to-worlds."""
    return opengl_to_opencv(torch.from_numpy(np.asarray(c2w_gl, dtype=np.float64))).float().numpy()


def warn_missing(source: Path, missing: list[str]) -> None:
    """One warning listing skipped frames (first 10 names and a count)."""
    shown = ", ".join(missing[:10]) + (f" and {len(missing) - 10} more" if len(missing) > 10 else "")
    warnings.warn(f"{source}: skipping {len(missing)} frame(s) whose image file is missing: {shown}", stacklevel=3)


class NerfstudioParser:
    """nerfstudio ``transforms.json`` -> SceneData (see the module docstring)."""

    priority: ClassVar[int] = 20

    @staticmethod
    def can_parse(path: Path) -> bool:
        path = Path(path)
        return (path.is_dir() and (path / "transforms.json").is_file()) or (path.is_file() and path.suffix == ".json")

    def parse(self, path: Path | None, options: DatasetConfig) -> SceneData:
        if path is None:
            raise DataError(None, "the nerfstudio parser needs a transforms.json file or its folder")
        path = Path(path)
        source = path / "transforms.json" if path.is_dir() else path
        meta = read_json(source)
        frames = meta.get("frames")
        if not isinstance(frames, list) or not frames:
            raise DataError(source, "missing or empty 'frames' list")
        views = [self._frame(meta, fr, i, source) for i, fr in enumerate(frames)]
        extra = _metegs_block(meta, len(frames), source)
        for v, exposure in zip(views, extra["exposure"]):
            v["exposure"] = exposure
        views.sort(key=lambda v: v["name"])
        present = [v for v in views if v["path"].is_file()]
        missing = [v["name"] for v in views if not v["path"].is_file()]
        if not present:
            raise DataError(source, f"no images found: none of the {len(views)} frame image files exist")
        if missing:
            warn_missing(source, missing)
        clean = find_clean_paths(source.parent, [v["path"] for v in present])
        masks = _masks(present, source)
        exposures = [v["exposure"] for v in present]
        if any(e is None for e in exposures):  # else the photos' EXIF (read before undistorted copies drop it)
            exposures = exposure_times_s([v["path"] for v in present])
        if any(v["distortion"].distorted for v in present):
            clean, masks = _undistort(present, clean, masks, source, options)
        cams = Cameras.create(
            gl_to_cv(np.stack([v["c2w"] for v in present])),
            *([v[k] for v in present] for k in _INTRINSICS),
            exposure_time_s=exposures,
        )
        names = [v["name"] for v in present]
        train, test = _split(meta, names, source, options.test_every)
        points, colors = self._points(meta, source)
        paths = [v["path"] for v in present]
        return SceneData(
            cameras=cams,
            names=names,
            image_paths=paths,
            clean_image_paths=clean,
            mask_paths=masks,
            depths=_npy_depths(present, source),
            train_indices=train,
            test_indices=test,
            points=points,
            point_colors=colors,
            source=path,
            **extra["scene"],
        )

    @staticmethod
    def _frame(meta: dict, frame, index: int, source: Path) -> dict:
        """One frame -> {name, path, c2w (GL [4, 4]), fl_x, fl_y, cx, cy, w, h}."""
        where = f"frame {index}"
        if not isinstance(frame, dict):
            raise DataError(source, f"{where} is not a JSON object")
        if "file_path" not in frame:
            raise DataError(source, f"{where} has no 'file_path'")
        if "transform_matrix" not in frame:
            raise DataError(source, f"{where} has no 'transform_matrix'")
        view = {"name": os.path.normpath(str(frame["file_path"])), "path": source.parent / str(frame["file_path"])}
        depth = frame.get("depth_file_path")
        view["depth"] = source.parent / str(depth) if isinstance(depth, str) and depth.endswith(".npy") else None
        mask = frame.get("mask_path")
        view["mask"] = source.parent / mask if isinstance(mask, str) and mask else None
        view["c2w"] = gl_matrix(frame["transform_matrix"], source, where)
        for key in _INTRINSICS:
            value = frame.get(key, meta.get(key))
            if value is None:
                raise DataError(source, f"{where} has no intrinsic '{key}' (neither per frame nor at the top level)")
            view[key] = number(value, source, f"{where}: intrinsic '{key}'")
        view["distortion"] = _distortion(meta, frame, view, source, where)
        return view

    @staticmethod
    def _points(meta: dict, source: Path) -> tuple[np.ndarray | None, np.ndarray | None]:
        ply = meta.get("ply_file_path")
        if not ply:
            return None, None
        return read_ply_points(source.parent / str(ply))


def _npy_depths(views: list[dict], source: Path) -> list[np.ndarray] | None:
    """Depth maps [H, W] float32 of every view from ``.npy`` depth files, or None when a view has none."""
    if not views or any(v["depth"] is None for v in views):
        return None
    depths = []
    for v in views:
        d = read_npy(v["depth"], "depth map")
        if d.shape != (int(v["h"]), int(v["w"])):
            raise DataError(v["depth"], f"depth map has shape {list(d.shape)}, expected [{int(v['h'])}, {int(v['w'])}]")
        depths.append(d.astype(np.float32))
    return depths


def _distortion(meta: dict, frame: dict, view: dict, source: Path, where: str) -> Distortion:
    """The frame's camera (its own keys over the top level's); DataError for what cannot be undistorted."""
    model = frame.get("camera_model", meta.get("camera_model"))
    if model is not None and model not in (*_PERSPECTIVE, _FISHEYE):
        said = where if "camera_model" in frame else "the top level"
        raise DataError(source, f"{said}: camera_model {model} is unsupported (pinhole and {_FISHEYE} are)")
    coeffs = {}
    for obj, what in ((meta, "the top level"), (frame, where)):
        params = obj.get("distortion_params")
        if params is not None:
            if not isinstance(params, list) or len(params) > 6:
                raise DataError(source, f"{what}: 'distortion_params' must be a list [k1, k2, k3, k4, p1, p2]")
            coeffs.update(zip(_DISTORTION, (number(d, source, f"{what}: 'distortion_params'") for d in params)))
        coeffs.update({k: number(obj[k], source, f"{what}: '{k}'") for k in _DISTORTION if obj.get(k) is not None})
    k = {name: coeffs.get(name, 0.0) for name in _DISTORTION}
    pinhole = (view["fl_x"], view["fl_y"], view["cx"], view["cy"])
    if model == _FISHEYE:
        return Distortion(*pinhole, (k["k1"], k["k2"], k["k3"], k["k4"]), fisheye=True)
    if k["k4"] != 0.0:
        raise DataError(source, f"{where}: a radial k4 is only supported with camera_model {_FISHEYE}")
    return Distortion(*pinhole, (k["k1"], k["k2"], k["p1"], k["p2"], k["k3"]))


def _masks(views: list[dict], source: Path) -> list[Path] | None:
    """Every view's ``mask_path`` file (white = keep), or None when a view has none (with a warning if some do)."""
    named = [v["mask"] for v in views if v["mask"] is not None]
    if not named:
        return None
    missing = [v["name"] for v in views if v["mask"] is None or not v["mask"].is_file()]
    if missing:
        warnings.warn(
            f"{source}: ignoring the masks, {len(missing)} frame(s) have no mask file (e.g. {missing[0]})", stacklevel=3
        )
        return None
    return [v["mask"] for v in views]


def _undistort(
    views: list[dict], clean: list[Path] | None, masks: list[Path] | None, source: Path, options: DatasetConfig
) -> tuple[list[Path] | None, list[Path] | None]:
    """Point distorted views (and their clean references and masks) at undistorted copies with pinhole intrinsics."""
    first = next(v for v in views if v["distortion"].distorted)
    if not options.undistort:
        raise DataError(source, f"{first['name']}: the camera is distorted; rerun with --dataset.undistort")
    if any(v["depth"] is not None for v in views):
        raise DataError(source, f"{first['name']}: depth maps beside lens distortion are unsupported")
    cache = cache_folder(source.parent)
    extra = {"clean": None if clean is None else list(clean), "masks": None if masks is None else list(masks)}
    for i, v in enumerate(views):
        camera = v["distortion"]
        if not camera.distorted:
            continue
        v["fl_x"], v["fl_y"], v["cx"], v["cy"] = camera.pinhole(int(v["w"]), int(v["h"]))
        v["path"] = undistorted_copy(v["path"], cache, v["name"], camera)
        for kind, paths in extra.items():
            if paths is not None:
                paths[i] = undistorted_copy(paths[i], cache, os.path.join(kind, v["name"]), camera)
    return extra["clean"], extra["masks"]


def _split(meta: dict, names: list[str], source: Path, every: int) -> tuple[list[int], list[int]]:
    """Train/test indices from ``train_filenames``/``test_filenames`` (or ``val_filenames``), else every n-th."""
    lists = {k: meta.get(f"{k}_filenames") for k in ("train", "val", "test")}
    for k, items in lists.items():
        if items is not None and not isinstance(items, list):
            raise DataError(source, f"'{k}_filenames' must be a list of image paths, got {items!r}")
    test_list = lists["test"] if lists["test"] is not None else lists["val"]
    if lists["train"] is None and test_list is None:
        return split_every_nth(len(names), every)
    norm = lambda items: {os.path.normpath(str(x)) for x in items}  # noqa: E731
    if lists["train"] is not None:
        train_set = norm(lists["train"])
        train = [i for i, n in enumerate(names) if n in train_set]
        test_set = norm(test_list) if test_list is not None else set(names) - train_set
    else:
        test_set = norm(test_list)
        train = [i for i, n in enumerate(names) if n not in test_set]
    test = [i for i, n in enumerate(names) if n in test_set]
    if lists["train"] and not train:
        raise DataError(source, "none of the 'train_filenames' is the file_path of a frame with an image")
    return train, test


def read_ply_points(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Vertices of a PLY file: [P, 3] float32 xyz and [P, 3] float32 colours in [0, 1] (None without colours).

    Read with `metegs.gaussians.ply.read_ply_vertices` (ascii or binary of either byte order).
    """
    path = Path(path)
    vertex = read_ply_vertices(path)
    fields = vertex.dtype.names
    if not all(k in fields for k in ("x", "y", "z")):
        raise DataError(path, "PLY vertices have no x, y, z properties")
    check_finite(path, vertex, [k for k in ("x", "y", "z", "red", "green", "blue") if k in fields])
    xyz = np.stack([vertex[k] for k in ("x", "y", "z")], axis=1).astype(np.float32)
    if not all(k in fields for k in ("red", "green", "blue")):
        return xyz, None
    rgb = np.stack([vertex[k] for k in ("red", "green", "blue")], axis=1).astype(np.float32)
    kind = vertex.dtype["red"]
    if kind.kind == "f":
        scale = 255.0 if rgb.size and rgb.max() > 1.0 else 1.0  # float colours in [0, 1] (or 0..255)
    else:
        scale = float(np.iinfo(kind).max)
    return xyz, np.clip(rgb / scale, 0.0, 1.0)


def _metegs_block(meta: dict, n_frames: int, source: Path) -> dict:
    """What metegs-synth adds under "metegs": per-frame exposure times; the scene's scale, up, colour space, rendering."""
    block = meta.get("metegs")
    out = {"exposure": [None] * n_frames, "scene": {}}
    if not isinstance(block, dict):
        return out
    exposure = block.get("exposure_time_s")
    if exposure is not None:
        if not isinstance(exposure, list) or len(exposure) != n_frames:
            raise DataError(source, f"metegs.exposure_time_s must list one value per frame ({n_frames})")
        out["exposure"] = [number(e, source, "metegs.exposure_time_s") for e in exposure]
    if block.get("metric_scale") is not None:
        out["scene"]["metric_scale"] = number(block["metric_scale"], source, "metegs.metric_scale")
    if block.get("up") is not None:
        values = block["up"] if isinstance(block["up"], list) else [block["up"]]
        up = np.asarray([number(u, source, "metegs.up") for u in values], dtype=np.float32)
        if up.shape != (3,) or np.linalg.norm(up) == 0:
            raise DataError(source, f"metegs.up must be a non-zero 3-vector, got {block['up']!r}")
        out["scene"]["up"] = up / np.linalg.norm(up)
    if block.get("image_space") in ("srgb", "linear"):
        out["scene"]["image_space"] = block["image_space"]
    if block.get("rendered") is not None:
        if not isinstance(block["rendered"], bool):
            raise DataError(source, f"metegs.rendered must be true or false, got {block['rendered']!r}")
        out["scene"]["rendered"] = block["rendered"]
    return out
