"""Restored photos kept between runs: a photo goes through a restorer once per content and settings.

Restoring 25 photos of 514x384 with Kang 2012 + DCP takes minutes on a CPU; runs that hold the clean branch to
restored photos (`pseudo_references`) would otherwise pay that at every start. An entry is named by a digest of
the photo's pixels (as training sees them) and of the restorer: its name, its config and, for a learned one, the
size and time of its weights file, so a changed photo, option or network never reads another's result.

    image, seconds, cached = cached_restore(restorer, photo)   # [H, W, 3] float32 in [0, 1] -> same shape

Entries live in ``user_cache("restored")`` (``$XDG_CACHE_HOME/metegs/restored``) as ``.npz`` files holding the
image and the seconds its restoring took, so that a benchmark reading it back still reports what restoring costs.
One that cannot be read back (truncated, wrong shape, not finite) is restored again and replaced.
"""

from __future__ import annotations

import hashlib
import io
import json
import time
import zipfile
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from metegs.config import to_dict, user_cache
from metegs.files import atomic_write_bytes
from metegs.restore.base import Restorer, check_image

CACHE_VERSION = 2
"""Bumped when a restorer's output changes without a change of its name or config."""


class Restored(NamedTuple):
    """A photo restored, or read back from the cache."""

    image: np.ndarray
    """[H, W, 3] float32 in [0, 1]."""
    seconds: float
    """How long restoring it took (now, or when the cache entry was made)."""
    cached: bool
    """Whether it was read from the cache rather than restored now."""


def restored_cache_dir() -> Path:
    """Where restored photos are kept between runs."""
    return user_cache("restored")


def restorer_fingerprint(restorer: Restorer) -> list[dict[str, Any]]:
    """What a restorer's output depends on besides the photo: each stage's name, config and weights file."""
    stages = getattr(restorer, "stages", None) or [restorer]
    out = []
    for stage in stages:
        entry: dict[str, Any] = {"name": stage.name}
        config = getattr(stage, "config", None)
        if config is not None:
            entry["config"] = to_dict(config)
        weights = getattr(stage, "weights_path", None)
        if weights is not None:
            stat = Path(weights).stat()
            entry["weights"] = [str(Path(weights).resolve()), stat.st_size, stat.st_mtime_ns]
        out.append(entry)
    return out


def cache_key(restorer: Restorer, image: np.ndarray) -> str:
    """Hex digest naming ``image`` [H, W, 3] float32 restored by ``restorer``."""
    digest = hashlib.sha256()
    head = {"version": CACHE_VERSION, "restorer": restorer_fingerprint(restorer), "shape": list(image.shape)}
    digest.update(json.dumps(head, sort_keys=True, default=str).encode())
    digest.update(image.tobytes())
    return digest.hexdigest()[:32]


def _read(path: Path, shape: tuple[int, ...]) -> tuple[np.ndarray, float] | None:
    """(image, seconds) of the entry at ``path`` if it holds a finite float32 image of ``shape`` in [0, 1] and a
    non-negative time, else None."""
    try:
        with np.load(path, allow_pickle=False) as entry:
            arr, seconds = entry["image"], float(entry["seconds"])
    except (OSError, ValueError, EOFError, KeyError, TypeError, zipfile.BadZipFile):
        return None
    if arr.shape != shape or arr.dtype != np.float32 or not np.isfinite(arr).all():
        return None
    if arr.size and (arr.min() < 0.0 or arr.max() > 1.0):
        return None
    if not np.isfinite(seconds) or seconds < 0:
        return None
    return arr, seconds


def cached_restore(restorer: Restorer, image: np.ndarray, cache_dir: Path | None = None) -> Restored:
    """``image`` [H, W, 3] in [0, 1] restored by ``restorer`` (same shape), read from the cache
    (`restored_cache_dir`, or ``cache_dir``) when an entry for this photo and restorer is there.

    A cache that cannot be written (read-only home, full disk) only costs the restoring again next time."""
    image = check_image(image, restorer.name)
    folder = Path(cache_dir) if cache_dir is not None else restored_cache_dir()
    path = folder / f"{cache_key(restorer, image)}.npz"
    if path.is_file():
        hit = _read(path, image.shape)
        if hit is not None:
            return Restored(hit[0], hit[1], True)
    t0 = time.perf_counter()
    restored = check_image(restorer.restore(image), restorer.name)
    seconds = time.perf_counter() - t0
    buffer = io.BytesIO()
    np.savez(buffer, image=restored, seconds=np.float64(seconds))
    try:
        atomic_write_bytes(path, buffer.getvalue())
    except OSError:
        pass
    return Restored(restored, seconds, False)
