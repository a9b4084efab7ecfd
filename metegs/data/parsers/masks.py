"""Per-view masks (white = keep) beside the images: one convention for the COLMAP and LLFF parsers.

The masks of ``<scene>/images[_N]/`` lie in ``<scene>/masks[_N]/``, one per image, named by the image's stem
(``a.jpg`` → ``a.png``, nerfstudio's and LLFF's habit) or by its whole name plus ``.png`` (``a.jpg.png``,
COLMAP's ``--ImageReader.mask_path`` habit). A scene exposes them only when every view has one; a partial set is
ignored with a warning.
"""

from __future__ import annotations

import warnings
from pathlib import Path


def mask_paths(path: Path, images: list[Path], image_dir: Path) -> list[Path] | None:
    """Masks of ``images`` (files in ``image_dir``) in the scene ``path``'s matching masks folder, else None."""
    folder = path / image_dir.name.replace("images", "masks", 1)
    if not folder.is_dir():
        return None
    files = [p for p in folder.iterdir() if p.is_file()]
    by_name = {p.name: p for p in files}
    by_stem = {p.stem: p for p in files}
    found = [by_name.get(im.name + ".png") or by_stem.get(im.stem) for im in images]
    missing = [im.name for im, m in zip(images, found) if m is None]
    if missing:
        warnings.warn(
            f"{folder}: ignoring the masks, {len(missing)} image(s) have none (e.g. {missing[0]})", stacklevel=3
        )
        return None
    return found
