"""Atomic checkpoints: model parameters, optimiser moments, densifier statistics and the step."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Any

import torch

from metegs.errors import DataError


def save_checkpoint(path: Path, payload: dict[str, Any]) -> Path:
    """Write ``payload`` with torch.save to a temp file, then rename: never a half-written checkpoint."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.close(fd)
    try:
        torch.save(payload, tmp)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def load_checkpoint(path: Path, device: torch.device | str = "cpu") -> dict[str, Any]:
    """Read a checkpoint written by `save_checkpoint`; a clear error names the file otherwise."""
    path = Path(path)
    if path.is_dir():
        found = sorted(path.glob("*.ckpt")) or sorted((path / "checkpoints").glob("*.ckpt"))
        if not found:
            raise DataError(path, "no .ckpt checkpoint in this folder")
        path = found[-1]
    if not path.is_file():
        raise DataError(path, "checkpoint file not found")
    try:
        payload = torch.load(path, map_location=device, weights_only=False)
    except Exception as exc:  # noqa: BLE001
        raise DataError(path, f"not a readable metegs checkpoint ({type(exc).__name__}: {exc})") from exc
    if not isinstance(payload, dict) or "params" not in payload or "step" not in payload:
        raise DataError(path, "not a metegs checkpoint (missing 'params' or 'step')")
    return payload
