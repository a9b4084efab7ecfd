"""What the viewer writes: the current view as PNG, the clean scene as PLY and weather-sweep videos.

Videos go through OpenCV's writer: MP4 (``mp4v``) when the build has the codec, else an animated GIF
(``cv2.imwriteanimation``, then imageio), else a folder of PNG frames; the path written says which.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from pathlib import Path

import cv2
import numpy as np

from metegs.config import atomic_output, atomic_write_bytes
from metegs.gaussians.ply import save_ply
from metegs.viewer.render import Snapshot


def save_png(path: Path, image: np.ndarray) -> Path:
    """Write an RGB uint8 image [H, W, 3] as PNG, atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    ok, buf = cv2.imencode(".png", cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2BGR))
    if not ok:
        raise OSError(f"{path}: could not encode the PNG")
    atomic_write_bytes(path, buf.tobytes())
    return path


def save_scene_ply(path: Path, snapshot: Snapshot, comments: Iterable[str] = ()) -> Path:
    """The clean scene Gaussians of ``snapshot`` as an INRIA-layout PLY (no weather Gaussians)."""
    save_ply(snapshot.state, path, comments=comments)
    return Path(path)


def write_video(
    path: Path, frames: Iterable[np.ndarray], fps: float = 12.0, on_frame: Callable[[int], None] | None = None
) -> Path:
    """Write RGB uint8 frames [H, W, 3] (all one size) as ``path`` (.mp4 or .gif) -> the file actually written.

    MP4 falls back to GIF when OpenCV cannot encode ``mp4v``; GIF falls back to PNG frames in a folder.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    frames = list(_counted(frames, on_frame))
    if not frames:
        raise ValueError("no frames to write")
    if path.suffix.lower() == ".mp4" and _write_mp4(path, frames, fps):
        return path
    gif = path.with_suffix(".gif")
    if _write_gif(gif, frames, fps):
        return gif
    folder = path.with_suffix("")
    folder.mkdir(parents=True, exist_ok=True)
    for i, frame in enumerate(frames):
        save_png(folder / f"frame-{i:04d}.png", frame)
    return folder


def _counted(frames: Iterable[np.ndarray], on_frame: Callable[[int], None] | None):
    for i, frame in enumerate(frames):
        if on_frame is not None:
            on_frame(i)
        yield frame


def _write_mp4(path: Path, frames: list[np.ndarray], fps: float) -> bool:
    h, w = frames[0].shape[:2]
    w2, h2 = w - w % 2, h - h % 2  # most MP4 codecs want even sizes
    try:
        with atomic_output(path, ".mp4") as tmp:
            writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), float(fps), (w2, h2))
            if not writer.isOpened():
                raise _NoWriter
            for frame in frames:
                writer.write(cv2.cvtColor(np.ascontiguousarray(frame[:h2, :w2]), cv2.COLOR_RGB2BGR))
            writer.release()
            if tmp.stat().st_size == 0:
                raise _NoWriter
        return True
    except (cv2.error, _NoWriter):
        return False


class _NoWriter(Exception):
    """OpenCV could not write the format here (the caller falls back to another)."""


def _write_gif(path: Path, frames: list[np.ndarray], fps: float) -> bool:
    duration_ms = max(10, round(1000.0 / fps))
    if hasattr(cv2, "imwriteanimation") and hasattr(cv2, "Animation"):
        try:
            animation = cv2.Animation()
            animation.frames = [cv2.cvtColor(np.ascontiguousarray(f), cv2.COLOR_RGB2BGR) for f in frames]
            animation.durations = [duration_ms] * len(frames)
            with atomic_output(path, ".gif") as tmp:
                if not (cv2.imwriteanimation(str(tmp), animation) and tmp.stat().st_size > 0):
                    raise _NoWriter
            return True
        except (cv2.error, _NoWriter):
            pass
    try:
        import imageio.v3 as iio

        data = iio.imwrite("<bytes>", np.stack(frames), extension=".gif", duration=duration_ms, loop=0)
        atomic_write_bytes(path, data)
        return True
    except Exception:  # imageio or its GIF plugin missing: the caller writes PNG frames
        return False
