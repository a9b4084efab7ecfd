"""Exposure times from the photos' EXIF: how long each frame was open sets how long a falling drop's streak is."""

from __future__ import annotations

import math
import statistics
from collections.abc import Sequence
from pathlib import Path

EXIF_IFD = 0x8769
"""EXIF sub-IFD pointer tag (where cameras write ExposureTime)."""
EXPOSURE_TIME = 0x829A
"""EXIF ExposureTime tag, seconds (a rational such as 1/125)."""


def exposure_time_s(path: Path) -> float | None:
    """The EXIF ExposureTime of one image file in seconds, or None when it has none (or no readable EXIF)."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:  # reads the header only, not the pixels
            exif = im.getexif()
            value = exif.get_ifd(EXIF_IFD).get(EXPOSURE_TIME, exif.get(EXPOSURE_TIME))
    except (OSError, UnidentifiedImageError, ValueError, SyntaxError):
        return None  # the image loader names unreadable files; here they only have no exposure
    try:
        seconds = float(value)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return seconds if math.isfinite(seconds) and 0 < seconds <= 3600 else None


def exposure_times_s(paths: Sequence[Path]) -> list[float] | None:
    """Exposure time per image of ``paths`` from their EXIF, seconds; frames without one take the median of the
    others; None when no image has one."""
    times = [exposure_time_s(Path(p)) for p in paths]
    found = [t for t in times if t is not None]
    if not found:
        return None
    median = statistics.median(found)
    return [median if t is None else t for t in times]
