"""Line charts of error against run time (PSNR vs seconds), drawn with OpenCV and written as PNG.

matplotlib is not a dependency of metegs, OpenCV is: axes, ticks, lines, markers and the legend are
drawn with ``cv2`` primitives (``metegs.meteo.plot`` does the same for met records).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from metegs.files import atomic_write_bytes

_FONT = cv2.FONT_HERSHEY_SIMPLEX
PALETTE_BGR = (
    (180, 119, 31),
    (14, 127, 255),
    (44, 160, 44),
    (40, 39, 214),
    (189, 103, 148),
    (75, 86, 140),
    (194, 119, 227),
    (127, 127, 127),
    (34, 189, 188),
    (207, 190, 23),
    (0, 0, 0),
)
"""Line colours (BGR), the tab10 set then black."""


@dataclass
class Series:
    """One method's curve."""

    label: str
    x: list[float]
    y: list[float]
    dashed: bool = False
    """Drawn dashed (reference rows such as the clean-photo upper bound)."""
    extra: dict = field(default_factory=dict)


def nice_ticks(lo: float, hi: float, n: int = 6) -> list[float]:
    """About ``n`` round tick values covering [lo, hi]."""
    if not (math.isfinite(lo) and math.isfinite(hi)) or hi <= lo:
        hi = lo + 1.0
    raw = (hi - lo) / max(n - 1, 1)
    mag = 10 ** math.floor(math.log10(raw))
    step = next(m * mag for m in (1, 2, 2.5, 5, 10) if m * mag >= raw)
    start = math.floor(lo / step) * step
    ticks, t = [], start
    while True:
        ticks.append(round(t, 10))
        if t >= hi - 1e-9 * step:
            return ticks
        t += step


def _fmt(v: float) -> str:
    return f"{v:g}" if abs(v) >= 1 or v == 0 else f"{v:.2g}"


def _text(img, s: str, x: float, y: float, scale: float = 0.45, color=(40, 40, 40), thickness: int = 1) -> None:
    cv2.putText(img, s, (int(x), int(y)), _FONT, scale, color, thickness, cv2.LINE_AA)


def _dashed(img, p0, p1, color, thickness=2, dash=8) -> None:
    (x0, y0), (x1, y1) = p0, p1
    length = math.hypot(x1 - x0, y1 - y0)
    if length < 1:
        return
    n = max(1, int(length // dash))
    for i in range(0, n, 2):
        a, b = i / n, min(1.0, (i + 1) / n)
        cv2.line(
            img,
            (int(x0 + (x1 - x0) * a), int(y0 + (y1 - y0) * a)),
            (int(x0 + (x1 - x0) * b), int(y0 + (y1 - y0) * b)),
            color,
            thickness,
            cv2.LINE_AA,
        )


def line_chart_png(
    series: list[Series],
    title: str,
    xlabel: str = "time (s): training, + restoration for restored photos",
    ylabel: str = "PSNR (dB)",
    size: tuple[int, int] = (1000, 560),
) -> bytes:
    """PNG bytes of the curves (a legend on the right)."""
    W, H = size
    left, right, top, bottom = 70, 250, 50, 60
    img = np.full((H, W, 3), 255, np.uint8)
    pts = [(x, y) for s in series for x, y in zip(s.x, s.y) if x is not None and y is not None and math.isfinite(y)]
    _text(img, title, left, 22, 0.6, (0, 0, 0), 1)
    x0p, x1p, y0p, y1p = left, W - right, top, H - bottom
    cv2.rectangle(img, (x0p, y0p), (x1p, y1p), (90, 90, 90), 1)
    if not pts:
        _text(img, "no finished runs", left + 20, top + 40)
        return cv2.imencode(".png", img)[1].tobytes()
    xs, ys = [p[0] for p in pts], [p[1] for p in pts]
    xt = nice_ticks(0.0, max(max(xs), 1e-3))
    ypad = max(0.5, 0.05 * (max(ys) - min(ys)))
    yt = nice_ticks(min(ys) - ypad, max(ys) + ypad)
    xmin, xmax, ymin, ymax = xt[0], xt[-1], yt[0], yt[-1]

    def px(x: float, y: float) -> tuple[int, int]:
        return (
            int(round(x0p + (x - xmin) / (xmax - xmin) * (x1p - x0p))),
            int(round(y1p - (y - ymin) / (ymax - ymin) * (y1p - y0p))),
        )

    for t in xt:
        x, _ = px(t, ymin)
        cv2.line(img, (x, y0p), (x, y1p), (235, 235, 235), 1)
        _text(img, _fmt(t), x - 10, y1p + 18, 0.4)
    for t in yt:
        _, y = px(xmin, t)
        cv2.line(img, (x0p, y), (x1p, y), (235, 235, 235), 1)
        _text(img, _fmt(t), 12, y + 4, 0.4)
    cv2.rectangle(img, (x0p, y0p), (x1p, y1p), (90, 90, 90), 1)
    _text(img, xlabel, (x0p + x1p) / 2 - 4 * len(xlabel), H - 18, 0.5)
    _text(img, ylabel, 8, top - 8, 0.45)
    for k, s in enumerate(series):
        color = PALETTE_BGR[k % len(PALETTE_BGR)]
        points = [px(x, y) for x, y in zip(s.x, s.y) if x is not None and y is not None and math.isfinite(y)]
        for a, b in zip(points, points[1:]):
            if s.dashed:
                _dashed(img, a, b, color)
            else:
                cv2.line(img, a, b, color, 2, cv2.LINE_AA)
        for p in points:
            cv2.circle(img, p, 3, color, -1, cv2.LINE_AA)
        ly = top + 10 + 22 * k
        if s.dashed:
            _dashed(img, (x1p + 15, ly), (x1p + 45, ly), color, dash=6)
        else:
            cv2.line(img, (x1p + 15, ly), (x1p + 45, ly), color, 2, cv2.LINE_AA)
        _text(img, s.label[:26], x1p + 52, ly + 5, 0.42)
    return cv2.imencode(".png", img)[1].tobytes()


def write_line_chart(path: Path, series: list[Series], title: str, **kwargs) -> Path:
    atomic_write_bytes(Path(path), line_chart_png(series, title, **kwargs))
    return Path(path)
