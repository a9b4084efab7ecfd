"""Reading images and masks from disk as float32 arrays in [0, 1].

Every image becomes RGB ``[H, W, 3]``: BGR is swapped to RGB, 16-bit images are scaled by 1/65535,
grey images are repeated to three channels and RGBA images are composited on a white background
(the Blender/NeRF-synthetic convention). EXIF orientation is ignored, like COLMAP does. Empty files and
JPEG/PNG files that stop before their end marker (EOI / IEND) are refused: OpenCV would decode the part it has.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from metegs.errors import DataError

LUMA = (0.299, 0.587, 0.114)
"""Rec. 601 weights of R, G and B in a photo's luma."""

IMAGE_EXTENSIONS = frozenset({".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp", ".exr"})
"""File suffixes (lower case) treated as images when listing a folder."""


def list_images(folder: Path) -> list[Path]:
    """Image files directly inside ``folder``, sorted by name; DataError if the folder is missing or empty."""
    folder = Path(folder)
    if not folder.is_dir():
        raise DataError(folder, "image folder does not exist")
    files = sorted(
        p
        for p in folder.iterdir()
        if p.is_file() and not p.name.startswith(".") and p.suffix.lower() in IMAGE_EXTENSIONS
    )
    if not files:
        raise DataError(folder, f"no images found in {folder}")
    return files


def _jpeg_problem(raw: bytes) -> str | None:
    """Why a JPEG is incomplete: its segments must lead to a scan whose data ends with the EOI marker FF D9."""
    pos = 2
    while pos + 4 <= len(raw):
        if raw[pos] != 0xFF:  # stray bytes between segments: skip to the next marker, as libjpeg does
            pos = raw.find(b"\xff", pos)
            if pos < 0:
                break
            continue
        marker = raw[pos + 1]
        if marker == 0xDA:  # start of scan: in the entropy-coded data that follows, FF D9 can only be the EOI
            return None if raw.find(b"\xff\xd9", pos) >= 0 else "JPEG data is truncated (no end-of-image marker)"
        if marker == 0xFF:  # fill byte
            pos += 1
        elif marker == 0x01 or 0xD0 <= marker <= 0xD8:  # markers without a length
            pos += 2
        else:
            pos += 2 + int.from_bytes(raw[pos + 2 : pos + 4], "big")
    return "JPEG data is truncated (it ends before the image data)"


def _png_problem(raw: bytes) -> str | None:
    """Why a PNG is incomplete: its chunks must lead to an IEND chunk within the file."""
    pos = 8
    while pos + 8 <= len(raw):
        length, kind = int.from_bytes(raw[pos : pos + 4], "big"), raw[pos + 4 : pos + 8]
        pos += 12 + length  # length, type, data, CRC
        if pos > len(raw):
            return f"PNG data is truncated (chunk {kind.decode('latin-1')!r} runs past the end of the file)"
        if kind == b"IEND":
            return None
    return "PNG data is truncated (no IEND chunk)"


def read_image_bytes(path: Path) -> bytes:
    """The bytes of an image file; DataError naming it when it is missing, empty or a truncated JPEG/PNG."""
    path = Path(path)
    if not path.is_file():
        raise DataError(path, "image file does not exist")
    raw = path.read_bytes()
    problem = "empty file (0 bytes)" if not raw else None
    if raw.startswith(b"\xff\xd8\xff"):
        problem = _jpeg_problem(raw)
    elif raw.startswith(b"\x89PNG\r\n\x1a\n"):
        problem = _png_problem(raw)
    if problem:
        raise DataError(path, problem)
    return raw


def _read(path: Path) -> np.ndarray:
    """Raw decoded image (as cv2.imread with IMREAD_UNCHANGED); DataError naming the file when it is missing,
    truncated or unreadable."""
    raw = read_image_bytes(path)
    data = cv2.imdecode(np.frombuffer(raw, np.uint8), cv2.IMREAD_UNCHANGED)
    if data is None or data.size == 0:
        raise DataError(path, "cannot read image (corrupt file or unsupported format)")
    return data


def _to_unit_float(data: np.ndarray, path: Path) -> np.ndarray:
    """uint8 / uint16 / float array -> float32 in [0, 1] (floats are passed through unchanged)."""
    if data.dtype == np.uint8:
        return data.astype(np.float32) / 255.0
    if data.dtype == np.uint16:
        return data.astype(np.float32) / 65535.0
    if data.dtype in (np.float32, np.float64, np.float16):
        return data.astype(np.float32)
    raise DataError(path, f"unsupported image pixel type {data.dtype} (expected 8/16-bit or float)")


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) of an image file (reads the file; DataError if it cannot be read)."""
    data = _read(path)
    return int(data.shape[1]), int(data.shape[0])


def load_image(path: Path) -> np.ndarray:
    """Read an image file as float32 RGB ``[H, W, 3]`` in [0, 1] (RGBA is composited on white)."""
    path = Path(path)
    img = _to_unit_float(_read(path), path)
    if img.ndim == 2:
        img = img[:, :, None]
    channels = img.shape[2]
    if channels == 1:
        return np.ascontiguousarray(np.repeat(img, 3, axis=2))
    if channels == 2:  # grey + alpha
        grey, alpha = img[:, :, :1], img[:, :, 1:2]
        return np.ascontiguousarray(np.repeat(grey * alpha + (1.0 - alpha), 3, axis=2))
    if channels in (3, 4):
        rgb = img[:, :, 2::-1]
        if channels == 4:
            alpha = img[:, :, 3:4]
            rgb = rgb * alpha + (1.0 - alpha)
        return np.ascontiguousarray(rgb, dtype=np.float32)
    raise DataError(path, f"unsupported number of image channels: {channels}")


def load_mask(path: Path) -> np.ndarray:
    """Read a mask file as float32 ``[H, W]`` in [0, 1] (white = keep); colour masks are averaged."""
    path = Path(path)
    mask = _to_unit_float(_read(path), path)
    if mask.ndim == 3:
        mask = mask[:, :, :3].mean(axis=2)
    return np.ascontiguousarray(mask, dtype=np.float32)


def resize_image(img: np.ndarray, width: int, height: int) -> np.ndarray:
    """Resize ``[H, W, C]`` or ``[H, W]`` float32 to ``[height, width, ...]`` with area interpolation."""
    if img.shape[1] == width and img.shape[0] == height:
        return img
    out = cv2.resize(img, (int(width), int(height)), interpolation=cv2.INTER_AREA)
    if img.ndim == 3 and out.ndim == 2:  # cv2 drops a single channel axis
        out = out[:, :, None]
    return out


def save_image(path: Path, img) -> None:
    """Write an RGB image in [0, 1] (HxWx3 numpy array or tensor) as 8-bit PNG/JPEG, atomically (temp file + rename)."""
    from metegs.files import atomic_write_bytes

    arr = img.detach().cpu().numpy() if hasattr(img, "detach") else np.asarray(img)
    arr = (np.clip(arr, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    path = Path(path)
    ok, buf = cv2.imencode(path.suffix or ".png", cv2.cvtColor(arr, cv2.COLOR_RGB2BGR))
    if not ok:
        raise DataError(path, "could not encode the image (unsupported extension?)")
    atomic_write_bytes(path, buf.tobytes())
