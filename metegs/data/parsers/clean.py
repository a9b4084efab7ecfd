"""Clean references next to degraded images (as `metegs-synth` writes them): one convention for every parser.

The clean reference of ``<scene>/<folder>/<rest>`` is ``<scene>/<folder>_clean/<rest>`` (``images_8/a.jpg`` →
``images_8_clean/a.jpg``); an image directly in the scene folder has its reference in ``<scene>/clean/``.
A scene exposes them as `SceneData.clean_image_paths` only when every view has one; a partial set is
ignored with a warning.
"""

from __future__ import annotations

import warnings
from pathlib import Path, PurePosixPath

CLEAN_SUFFIX = "_clean"
"""Suffix of the folder holding the clean references of an image folder."""
ROOT_CLEAN_FOLDER = "clean"
"""Folder of the clean references of images lying directly in the scene folder."""


def clean_relative_path(relative: str | Path) -> PurePosixPath:
    """Clean reference of an image path relative to the scene folder: ``images/x.png`` → ``images_clean/x.png``."""
    parts = PurePosixPath(Path(relative).as_posix()).parts
    parts = tuple(p for p in parts if p != ".")
    if len(parts) <= 1:
        return PurePosixPath(ROOT_CLEAN_FOLDER, *parts)
    return PurePosixPath(parts[0] + CLEAN_SUFFIX, *parts[1:])


def find_clean_paths(root: Path, image_paths: list[Path]) -> list[Path] | None:
    """Clean reference file per image (all of them), else None; images outside ``root`` have none."""
    root = Path(root)
    found = []
    for p in image_paths:
        try:
            rel = Path(p).relative_to(root)
        except ValueError:
            return None
        found.append(root / clean_relative_path(rel))
    exists = [p.is_file() for p in found]
    if all(exists) and found:
        return found
    if any(exists):
        missing = [p for p, e in zip(found, exists) if not e]
        warnings.warn(
            f"{root}: ignoring the clean references, {len(missing)} of {len(found)} views have none "
            f"(e.g. {missing[0]})",
            stacklevel=3,
        )
    return None
