"""Atomic checkpoints: model parameters, optimiser moments, densifier statistics and the step.

Checkpoints are read with ``torch.load(weights_only=True)``: tensors, numbers, strings and containers only, so a
crafted file cannot run code. What is read is checked before use: the fields a metegs checkpoint has, the Gaussian
parameters' shapes and finiteness, and (when the checkpoint records them) the method and the scene it was made for.
"""

from __future__ import annotations

import math
import pickle
import warnings
from pathlib import Path
from typing import Any

import torch

from metegs.errors import DataError
from metegs.files import atomic_output
from metegs.gaussians.sh import MAX_SH_DEGREE

REQUIRED = ("step", "params", "sh_degree")
"""Fields every metegs checkpoint holds."""

PARAM_SHAPES = {"means": (3,), "quats": (4,), "scales": (3,), "opacities": (), "sh0": (1, 3)}
"""Per-Gaussian trailing shape of each parameter (``shN`` is [N, K, 3] with K set by the SH degree)."""


def save_checkpoint(path: Path, payload: dict[str, Any]) -> Path:
    """Write ``payload`` with torch.save to a temp file, then rename: never a half-written checkpoint."""
    with atomic_output(path) as tmp:
        torch.save(payload, tmp)
    return Path(path)


def resolve_checkpoint(path: Path) -> Path:
    """``path`` itself, or the latest ``*.ckpt`` of a folder (or of its ``checkpoints/``); DataError if none."""
    path = Path(path)
    if path.is_dir():
        found = sorted(path.glob("*.ckpt")) or sorted((path / "checkpoints").glob("*.ckpt"))
        if not found:
            raise DataError(path, "no .ckpt checkpoint in this folder")
        path = found[-1]
    if not path.is_file():
        raise DataError(path, "checkpoint file not found")
    return path


def load_checkpoint(path: Path, device: torch.device | str = "cpu") -> dict[str, Any]:
    """Read and check a checkpoint written by `save_checkpoint` (a folder: its latest); a clear error names the file
    and the field otherwise. No code in the file runs."""
    path = resolve_checkpoint(path)
    try:
        with warnings.catch_warnings():  # torch warns about the pickle protocol of files it then refuses
            warnings.simplefilter("ignore", UserWarning)
            payload = torch.load(path, map_location=device, weights_only=True)
    except pickle.UnpicklingError as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise DataError(path, f"refused: not a metegs checkpoint, or it holds objects other than tensors and "
                              f"plain data, which are never loaded ({first})") from None  # fmt: skip
    except Exception as exc:  # noqa: BLE001 - whatever a damaged file makes the reader raise
        raise DataError(path, f"not a readable metegs checkpoint ({type(exc).__name__}: {exc})") from None
    check_checkpoint(payload, path)
    return payload


def check_checkpoint(payload: Any, path: Path) -> None:
    """Raise DataError naming ``path`` and the field unless ``payload`` is a complete metegs checkpoint with
    consistent, finite Gaussian parameters."""
    if not isinstance(payload, dict):
        raise DataError(path, f"not a metegs checkpoint (a {type(payload).__name__}, not a mapping)")
    missing = [k for k in REQUIRED if k not in payload]
    if missing:
        raise DataError(path, f"not a metegs checkpoint (missing {', '.join(map(repr, missing))})")
    step, degree, params = payload["step"], payload["sh_degree"], payload["params"]
    if not isinstance(step, int) or step < 0:
        raise DataError(path, f"field 'step' is {step!r}, not a step number")
    if not isinstance(degree, int) or not 0 <= degree <= MAX_SH_DEGREE:
        raise DataError(path, f"field 'sh_degree' is {degree!r}, not an SH degree 0-{MAX_SH_DEGREE}")
    if not isinstance(params, dict) or any(not isinstance(v, torch.Tensor) for v in params.values()):
        raise DataError(path, "field 'params' is not a mapping of tensors")
    shapes = {**PARAM_SHAPES, "shN": ((degree + 1) ** 2 - 1, 3)}
    count = None
    for name, trailing in shapes.items():
        if name not in params:
            raise DataError(path, f"field 'params' has no {name!r}")
        t = params[name]
        if tuple(t.shape[1:]) != trailing or (count is not None and t.shape[0] != count):
            raise DataError(path, f"params[{name!r}] has shape {tuple(t.shape)}, expected ({count or 'N'}, "
                                  f"{', '.join(map(str, trailing))}) for SH degree {degree}")  # fmt: skip
        count = t.shape[0]
        if not t.is_floating_point():
            raise DataError(path, f"params[{name!r}] is {t.dtype}, not floating point")
        bad = int((~torch.isfinite(t)).sum())
        if bad:
            raise DataError(path, f"params[{name!r}] holds {bad} non-finite (NaN/Inf) values: this checkpoint "
                                  "cannot be rendered or resumed; use an earlier one")  # fmt: skip


def check_compatible(payload: dict[str, Any], path: Path, method: str, scene: dict[str, Any]) -> None:
    """Raise DataError unless the checkpoint was made by ``method`` on the scene ``scene`` describes
    (`scene_signature`); checkpoints older than these records are taken as they are."""
    made_by = payload.get("method")
    if made_by is not None and made_by != method:
        raise DataError(path, f"a checkpoint of method {made_by!r}, not of {method!r}: train {made_by} to resume it, "
                              "or start a new run without --load-checkpoint")  # fmt: skip
    recorded = payload.get("scene")
    if not isinstance(recorded, dict):
        return
    for key, value in scene.items():
        saved = recorded.get(key)
        if saved is None:
            continue
        same = math.isclose(saved, value, rel_tol=1e-3) if isinstance(value, float) else saved == value
        if not same:
            raise DataError(path, f"made for another scene: its {key} is {saved!r}, this scene's is {value!r}")


def scene_signature(parser: str, num_views: int, extent: float) -> dict[str, Any]:
    """What a checkpoint records of its scene to be recognised again: the parser, the view count and the
    cameras' extent (scene units)."""
    return {"parser": parser, "num_views": int(num_views), "extent": float(extent)}
