"""The preview contact sheet: per view, clean (top), degraded (middle, labelled with θ) and their amplified
difference (bottom: thin, faint rain streaks are hard to see at preview size)."""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

TILE_HEIGHT = 240
"""Height of one tile in the sheet, px (small images are enlarged, large ones reduced)."""
LABEL_HEIGHT = 40
"""Height of the text band above each tile, px."""
DIFF_GAIN = 4.0
"""Gain of the |degraded − clean| row."""


def theta_label(theta: dict, drawn: dict[str, int] | None = None) -> list[str]:
    """Two short lines describing a view's θ (from ``Theta.to_dict()``): rain rate, class and count (``drawn``: the
    Gaussians each weather model drew in the view instead, e.g. ``{"snow": 1520}``); fog."""
    rain, fog = theta.get("rain", {}), theta.get("fog", {})
    p = rain.get("precip_mm_per_h") or 0.0
    line1 = f"P {p:.1f} mm/h {rain.get('intensity_class', '?')}"
    if drawn:
        line1 += ", " + ", ".join(f"{name} {n}" for name, n in drawn.items())
    elif rain.get("active"):
        line1 += f", N {rain.get('count', 0)}"
    vis = fog.get("visibility_m")
    beta = fog.get("beta_veil_per_m") or 0.0
    if vis is not None:
        line2 = f"vis {_metres(vis)}" + (f" ({fog.get('kind')})" if fog.get("kind") else "")
    elif beta > 0:
        line2 = f"vis n/a (rain veil ~{_metres(np.log(20.0) / beta)})"
    else:
        line2 = "vis n/a"
    return [line1, line2]


def record_label(record: dict) -> list[str]:
    """Two short lines describing a degraded view from its weather.json record: θ (physical family) or the met
    conditions and what the independent family drew."""
    if "theta" in record:
        return theta_label(record["theta"], record.get("gaussians_per_model"))
    cond = record.get("conditions", {})
    rain = record.get("rain")
    line1 = f"P {cond.get('precip_mm_h') or 0.0:.1f} mm/h {cond.get('wmo_class', '?')}"
    if rain:
        line1 += f", {len(rain['layers'])} layers"
    vis = cond.get("visibility_m")
    fog = record.get("fog")
    line2 = "vis n/a" if vis is None else f"vis {_metres(vis)}"
    if fog:
        line2 += f", t {fog['mean_transmittance']:.2f}"
    return [line1, line2]


def _metres(v: float) -> str:
    return f"{v / 1000:.1f} km" if v >= 1000 else f"{v:.0f} m"


def pick_views(n: int, count: int = 4) -> list[int]:
    """``count`` view indices spread evenly over ``n`` views."""
    count = max(1, min(count, n))
    return sorted({int(round(i * (n - 1) / max(count - 1, 1))) for i in range(count)})


def _tile(image: np.ndarray, height: int) -> np.ndarray:
    img = (np.clip(np.asarray(image, dtype=np.float32), 0, 1) * 255 + 0.5).astype(np.uint8)
    h, w = img.shape[:2]
    width = max(1, int(round(w * height / h)))
    interp = cv2.INTER_NEAREST if height >= 2 * h else cv2.INTER_AREA
    return cv2.resize(img, (width, height), interpolation=interp)


def _band(width: int, lines: Sequence[str], height: int = LABEL_HEIGHT) -> np.ndarray:
    band = np.full((height, width, 3), 255, np.uint8)
    for k, text in enumerate(lines[:2]):
        cv2.putText(band, text, (4, 16 + 18 * k), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (20, 20, 20), 1, cv2.LINE_AA)
    return band


def contact_sheet(
    cleans: Sequence[np.ndarray],
    degraded: Sequence[np.ndarray],
    labels: Sequence[Sequence[str]],
    names: Sequence[str],
    title: str = "",
    tile_height: int = TILE_HEIGHT,
    differences: bool = True,
) -> np.ndarray:
    """[H, W, 3] uint8 RGB sheet: one column per view, clean on top, degraded below with its θ label, then
    (``differences``) the amplified difference."""
    columns = []
    for clean, deg, label, name in zip(cleans, degraded, labels, names):
        top, middle = _tile(clean, tile_height), _tile(deg, tile_height)
        diff = np.abs(np.asarray(deg, np.float32) - np.asarray(clean, np.float32)) * DIFF_GAIN
        w = top.shape[1]
        parts = [_band(w, [f"{name} clean"]), top, _band(w, list(label)), middle]
        if differences:
            parts += [_band(w, [f"|degraded - clean| x{DIFF_GAIN:g}"], 22), _tile(diff, tile_height)]
        columns.append(np.concatenate(parts, axis=0))
    gap = np.full((columns[0].shape[0], 6, 3), 255, np.uint8)
    body = columns[0]
    for col in columns[1:]:
        body = np.concatenate([body, gap, col], axis=1)
    if title:
        body = np.concatenate([_band(body.shape[1], [title], 24), body], axis=0)
    return body


def encode_png(sheet: np.ndarray) -> bytes:
    """PNG bytes of an RGB uint8 image."""
    ok, buf = cv2.imencode(".png", cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR))
    if not ok:
        raise RuntimeError("could not encode the contact sheet")
    return buf.tobytes()
