"""Cheap structural checks of a COLMAP model's files, run before pycolmap reads them.

pycolmap trusts the counts stored in a binary model: a truncated ``points3D.bin`` makes it reserve
gigabytes before it fails. `check_model` walks the layout of each binary file (counts and per-record
lengths, read with `struct` from a memory map, so nothing bigger than the file is allocated) and parses
every line of a text model, so that a corrupt model is refused with a DataError naming the file, the
record and the field (or the line) that is wrong.
"""

from __future__ import annotations

import math
import mmap
import os
import struct
from pathlib import Path

from metegs.errors import DataError

MODEL_FILES = ("cameras", "images", "points3D")
"""The files every COLMAP model has (``.bin`` or ``.txt``); ``rigs`` and ``frames`` are optional."""

CAMERA_MODELS = {
    0: ("SIMPLE_PINHOLE", 3), 1: ("PINHOLE", 4), 2: ("SIMPLE_RADIAL", 4), 3: ("RADIAL", 5), 4: ("OPENCV", 8),
    5: ("OPENCV_FISHEYE", 8), 6: ("FULL_OPENCV", 12), 7: ("FOV", 5), 8: ("SIMPLE_RADIAL_FISHEYE", 4),
    9: ("RADIAL_FISHEYE", 5), 10: ("THIN_PRISM_FISHEYE", 12), 11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16),
    12: ("SIMPLE_DIVISION", 4), 13: ("DIVISION", 5), 14: ("SIMPLE_FISHEYE", 3), 15: ("FISHEYE", 4),
    16: ("EUCM", 6), 17: ("EQUIRECTANGULAR", 2),
}  # fmt: skip
"""COLMAP camera model id -> (name, number of parameters), as stored in ``cameras.bin``."""
_PARAMS_BY_NAME = dict(CAMERA_MODELS.values())


def model_format(folder: Path) -> str | None:
    """The extension pycolmap reads in ``folder``: "bin" when all the binary files exist, else "txt", else None."""
    for ext in ("bin", "txt"):
        if all((Path(folder) / f"{name}.{ext}").is_file() for name in MODEL_FILES):
            return ext
    return None


def model_file(folder: Path, name: str) -> Path:
    """The file ``name`` (e.g. "points3D") of the model in ``folder`` that pycolmap reads."""
    return Path(folder) / f"{name}.{model_format(folder) or 'bin'}"


def check_model(folder: Path) -> None:
    """DataError naming the file and the record/field or line when a model file in ``folder`` is malformed."""
    folder = Path(folder)
    ext = model_format(folder)
    if ext is None:
        present = sorted(p.name for p in folder.iterdir() if p.stem in MODEL_FILES)
        raise DataError(
            folder,
            f"incomplete COLMAP model: found {', '.join(present) or 'nothing'}, expected "
            "cameras, images and points3D all .bin or all .txt",
        )
    for name, check in (_BINARY if ext == "bin" else _TEXT).items():
        if (folder / f"{name}.{ext}").is_file():
            check(folder / f"{name}.{ext}")


# --- binary ------------------------------------------------------------------------------------------

_U64 = struct.Struct("<Q")


class _Walk:
    """A cursor over a binary model file; every read is checked against the file's size."""

    def __init__(self, path: Path, data):
        self.path, self.data, self.pos, self.size = path, data, 0, len(data)

    def fail(self, problem: str):
        raise DataError(self.path, f"{problem} (the file has {self.size} bytes: truncated or corrupt)")

    def take(self, fmt: str, what: str) -> tuple:
        """Unpack little-endian ``fmt`` at the cursor; ``what`` names the field in the error."""
        size = struct.calcsize("<" + fmt)
        if self.pos + size > self.size:
            self.fail(f"{what} runs past the end of the file (byte {self.pos})")
        values = struct.unpack_from("<" + fmt, self.data, self.pos)
        self.pos += size
        return values

    def skip(self, count: int, size: int, what: str) -> None:
        """Step over ``count`` items of ``size`` bytes."""
        if count * size > self.size - self.pos:
            self.fail(f"{what}: {count} x {size} bytes run past the end of the file (byte {self.pos})")
        self.pos += count * size

    def count(self, what: str, min_record: int) -> int:
        """The leading uint64 record count, refused when the rest of the file cannot hold that many records."""
        (n,) = self.take("Q", f"the number of {what}")
        if n * min_record > self.size - self.pos:
            self.fail(f"the number of {what} is {n}, impossible: each needs at least {min_record} bytes")
        return n

    def name(self, what: str) -> str:
        """A NUL-terminated string."""
        end = self.data.find(b"\0", self.pos)
        if end < 0:
            self.fail(f"{what} has no terminating NUL byte")
        raw = self.data[self.pos : end]
        self.pos = end + 1
        return raw.decode("utf-8", errors="replace")

    def end(self, records: str) -> None:
        if self.pos != self.size:
            self.fail(f"{self.size - self.pos} bytes follow the last of the {records} (wrong count?)")


def _walk(path: Path, body) -> None:
    """Run ``body(walk)`` over the file, memory-mapped."""
    with open(path, "rb") as f:
        if os.fstat(f.fileno()).st_size == 0:
            raise DataError(path, "empty file (a COLMAP binary model file starts with its record count)")
        with mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as data:
            body(_Walk(path, data))


def _cameras_bin(w: _Walk) -> None:
    n = w.count("cameras", 24)
    for i in range(n):
        cam_id, model, _, _ = w.take("iiQQ", f"camera {i + 1} of {n}")
        if model not in CAMERA_MODELS:
            w.fail(f"camera {cam_id}: unknown camera model id {model}")
        name, n_params = CAMERA_MODELS[model]
        w.skip(n_params, 8, f"camera {cam_id}: the {name} parameters")
    w.end(f"{n} cameras")


def _images_bin(w: _Walk) -> None:
    n = w.count("images", 73)
    for i in range(n):
        image_id, *pose, _ = w.take("I7dI", f"image {i + 1} of {n}")
        if not all(map(math.isfinite, pose)):
            w.fail(f"image {image_id}: the pose (qvec, tvec) is not finite: {pose}")
        name = w.name(f"image {image_id}: the name")
        (n_points,) = w.take("Q", f"image {image_id} ({name}): the number of 2D points")
        w.skip(n_points, 24, f"image {image_id} ({name}): the 2D points")
    w.end(f"{n} images")


def _points3d_bin(w: _Walk) -> None:
    n = w.count("points", 51)
    data, pos, size = w.data, w.pos, w.size
    for i in range(n):  # id, xyz, rgb, error (43 bytes), track length, track: the hot loop, checked inline
        if pos + 51 > size:
            w.fail(f"point {i + 1} of {n} runs past the end of the file (byte {pos})")
        (length,) = _U64.unpack_from(data, pos + 43)
        if 8 * length > size - pos - 51:
            w.fail(f"point {i + 1} of {n}: the track of {length} observations runs past the end of the file")
        pos += 51 + 8 * length
    w.pos = pos
    w.end(f"{n} points")


def _rigs_bin(w: _Walk) -> None:
    n = w.count("rigs", 8)
    for i in range(n):
        rig_id, n_sensors = w.take("II", f"rig {i + 1} of {n}")
        if n_sensors:
            w.skip(1, 8, f"rig {rig_id}: the reference sensor")
        if (n_sensors - 1) * 9 > w.size - w.pos:
            w.fail(f"rig {rig_id}: {n_sensors} sensors, impossible for the rest of the file")
        for s in range(max(0, n_sensors - 1)):
            (has_pose,) = w.take("8xB", f"rig {rig_id}: sensor {s + 2}")
            w.skip(7 if has_pose else 0, 8, f"rig {rig_id}: the pose of sensor {s + 2}")
    w.end(f"{n} rigs")


def _frames_bin(w: _Walk) -> None:
    n = w.count("frames", 68)
    for i in range(n):
        frame_id, _, *_, n_data = w.take("II7dI", f"frame {i + 1} of {n}")
        w.skip(n_data, 16, f"frame {frame_id}: the data ids")
    w.end(f"{n} frames")


_BINARY = {
    name: (lambda path, body=body: _walk(path, body))
    for name, body in (("cameras", _cameras_bin), ("images", _images_bin), ("points3D", _points3d_bin),
                       ("rigs", _rigs_bin), ("frames", _frames_bin))
}  # fmt: skip
"""File name -> check of the binary file."""


# --- text --------------------------------------------------------------------------------------------


def _numbers(tokens: list[str], kind: type, what: str) -> list:
    """``tokens`` as ints or finite floats; ValueError naming ``what`` otherwise."""
    try:
        values = [kind(t) for t in tokens]
    except ValueError:
        raise ValueError(
            f"{what} must be {'integers' if kind is int else 'numbers'}, got {' '.join(tokens)!r}"
        ) from None
    if kind is float and not all(map(math.isfinite, values)):
        raise ValueError(f"{what} must be finite, got {' '.join(tokens)!r}")
    return values


def _camera_line(t: list[str]) -> None:
    if len(t) < 4 or t[1] not in _PARAMS_BY_NAME:
        raise ValueError("expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS[] with a known COLMAP model")
    _numbers(t[:1] + t[2:4], int, "CAMERA_ID, WIDTH and HEIGHT")
    if len(t) - 4 != _PARAMS_BY_NAME[t[1]]:
        raise ValueError(f"model {t[1]} has {_PARAMS_BY_NAME[t[1]]} parameters, the line has {len(t) - 4}")
    _numbers(t[4:], float, "the parameters")


def _image_line(t: list[str]) -> None:
    if len(t) < 10:
        raise ValueError("expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME")
    _numbers([t[0], t[8]], int, "IMAGE_ID and CAMERA_ID")
    _numbers(t[1:8], float, "the pose QW QX QY QZ TX TY TZ")


def _points2d_line(t: list[str]) -> None:
    if len(t) % 3:
        raise ValueError(f"expected POINTS2D[] as (X, Y, POINT3D_ID) triples, got {len(t)} values")
    _numbers([v for i, v in enumerate(t) if i % 3 < 2], float, "2D point coordinates")
    _numbers(t[2::3], int, "POINT3D_ID")


def _point3d_line(t: list[str]) -> None:
    if len(t) < 8 or (len(t) - 8) % 2:
        raise ValueError("expected POINT3D_ID X Y Z R G B ERROR TRACK[] as (IMAGE_ID, POINT2D_IDX) pairs")
    _numbers(t[1:4] + t[7:8], float, "X Y Z and ERROR")
    if not all(0 <= v <= 255 for v in _numbers(t[4:7], int, "R G B")):
        raise ValueError(f"R G B must be in 0..255, got {' '.join(t[4:7])!r}")
    _numbers([t[0], *t[8:]], int, "POINT3D_ID and the track")


def _check_text(path: Path, record) -> None:
    """Check each record (its line checks in order) of a text model file; DataError naming the file and line."""
    with open(path, encoding="utf-8", errors="replace") as f:
        numbered = enumerate(f, start=1)
        for number, line in numbered:
            if not line.strip() or line.lstrip().startswith("#"):
                continue
            for i, check in enumerate(record):
                if i:  # the record's next line (images.txt: the 2D points, maybe empty)
                    number, line = next(numbered, (number + 1, ""))
                try:
                    check(line.split())
                except ValueError as exc:
                    raise DataError(path, f"line {number}: {exc}: {line.strip()[:120]!r}") from None


_TEXT = {
    "cameras": lambda path: _check_text(path, (_camera_line,)),
    "images": lambda path: _check_text(path, (_image_line, _points2d_line)),
    "points3D": lambda path: _check_text(path, (_point3d_line,)),
}
"""File name -> check of the text file."""
