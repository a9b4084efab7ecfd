"""Videos and frames as files: RGB uint8 frames to an MP4 a browser plays, else GIF, else PNG frames.

MP4s are H.264 (yuv420p, even sizes, ``+faststart``) through imageio-ffmpeg's own ffmpeg (the ``video`` extra),
so they play in browsers. Without it (or when it fails) OpenCV writes ``mp4v``, which browsers such as Chromium refuse,
with a `BrowserVideoWarning` once; when OpenCV cannot write MP4 either, an animated GIF (``cv2.imwriteanimation``,
then imageio), else a folder of PNG frames; the path written says which.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Iterable
from pathlib import Path

import cv2
import numpy as np
import torch

from metegs.files import atomic_output, atomic_write_bytes


def to_uint8(image: torch.Tensor) -> np.ndarray:
    """[H, W, 3] float in [0, 1] -> contiguous uint8 array (a video frame)."""
    return np.ascontiguousarray((image.detach().float().clamp(0, 1).cpu().numpy() * 255.0 + 0.5).astype(np.uint8))


def caption(image: np.ndarray, text: str) -> np.ndarray:
    """A copy of the RGB uint8 frame ``image`` [H, W, 3] with ``text`` written at its bottom left (white on black)."""
    out = image.copy()
    h = out.shape[0]
    scale = max(0.35, h / 720.0)
    org = (max(4, h // 40), h - max(6, h // 30))
    cv2.putText(out, text, org, cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), max(2, int(3 * scale)), cv2.LINE_AA)
    cv2.putText(out, text, org, cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), max(1, int(scale)), cv2.LINE_AA)
    return out


def save_png(path: Path, image: np.ndarray) -> Path:
    """Write an RGB uint8 image [H, W, 3] as PNG, atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    ok, buf = cv2.imencode(".png", cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2BGR))
    if not ok:
        raise OSError(f"{path}: could not encode the PNG")
    atomic_write_bytes(path, buf.tobytes())
    return path


def write_video(
    path: Path, frames: Iterable[np.ndarray], fps: float = 12.0, on_frame: Callable[[int], None] | None = None
) -> Path:
    """Write RGB uint8 frames [H, W, 3] (all one size) as ``path`` (.mp4 or .gif) -> the file actually written.

    MP4 is H.264 with imageio-ffmpeg, else OpenCV's ``mp4v`` (with a `BrowserVideoWarning`), else GIF; GIF falls back
    to PNG frames in a folder.
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


class BrowserVideoWarning(UserWarning):
    """The MP4 was written as ``mp4v``, which browsers do not play (imageio-ffmpeg's H.264 was not available)."""


MP4V_HINT = 'pip install imageio-ffmpeg (the "video" extra: pip install -e ".[video]" in a metegs checkout)'
_warned_mp4v = False  # the mp4v warning is given once per process


def _write_mp4(path: Path, frames: list[np.ndarray], fps: float) -> bool:
    h, w = frames[0].shape[:2]
    w2, h2 = w - w % 2, h - h % 2  # H.264 in yuv420p (and most MP4 codecs) want even sizes
    frames = [np.ascontiguousarray(f[:h2, :w2]) for f in frames]
    why = _write_h264(path, frames, fps)
    if why is None:
        return True
    if not _write_mp4v(path, frames, fps):
        return False
    global _warned_mp4v
    if not _warned_mp4v:
        _warned_mp4v = True
        warnings.warn(
            f"{path}: written as OpenCV's mp4v ({why}); browsers such as Chromium will not play it. "
            f"For H.264: {MP4V_HINT}",
            BrowserVideoWarning,
            stacklevel=3,
        )
    return True


def _write_h264(path: Path, frames: list[np.ndarray], fps: float) -> str | None:
    """H.264 / yuv420p / +faststart through imageio-ffmpeg -> None when written, else why not."""
    try:
        import imageio_ffmpeg
    except ImportError:
        return "imageio-ffmpeg is not installed"
    h, w = frames[0].shape[:2]
    try:
        with atomic_output(path, ".mp4") as tmp:
            writer = imageio_ffmpeg.write_frames(
                str(tmp),
                (w, h),
                fps=float(fps),
                codec="libx264",
                pix_fmt_in="rgb24",
                pix_fmt_out="yuv420p",
                macro_block_size=2,  # the sizes are even already: no rescaling
                quality=7,  # crf 15: fine rain streaks survive
                ffmpeg_log_level="error",
                output_params=["-movflags", "+faststart"],
            )
            writer.send(None)  # starts ffmpeg
            try:
                for frame in frames:
                    writer.send(frame)
            finally:
                writer.close()
            if tmp.stat().st_size == 0:
                raise OSError("ffmpeg wrote an empty file")
        return None
    except Exception as exc:  # ffmpeg missing for this platform, no libx264, ...: OpenCV's mp4v instead
        return f"imageio-ffmpeg failed: {exc}".splitlines()[0]


def _write_mp4v(path: Path, frames: list[np.ndarray], fps: float) -> bool:
    h, w = frames[0].shape[:2]
    try:
        with atomic_output(path, ".mp4") as tmp:
            writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), float(fps), (w, h))
            if not writer.isOpened():
                raise _NoWriter
            for frame in frames:
                writer.write(cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
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
