"""A PNG of a precipitation record with WMO class bands and the mapped N_rain and β (drawn with OpenCV).

matplotlib is not a dependency of metegs, OpenCV is, so the plot is drawn with ``cv2`` primitives.
"""

from __future__ import annotations

import math
from datetime import datetime, timezone

import cv2
import numpy as np

from metegs.meteo.mapping import CameraSpec, MappingConfig, theta_from_values
from metegs.meteo.observations import ObservationTable, epoch_s
from metegs.meteo.rates import PrecipSeries

WMO_BANDS = (
    (0.0, 2.5, "light", (200, 235, 200)),
    (2.5, 10.0, "moderate", (170, 230, 250)),
    (10.0, 50.0, "heavy", (150, 190, 250)),
    (50.0, math.inf, "violent", (170, 150, 245)),
)
"""(low, high, name, BGR colour) of the WMO rain classes drawn behind the series."""

_FONT = cv2.FONT_HERSHEY_SIMPLEX
_W, _H = 1200, 760
_LEFT, _RIGHT = 90, 90
_TOP1, _BOTTOM1 = 50, 420
_TOP2, _BOTTOM2 = 470, 690


def _text(img: np.ndarray, s: str, x: int, y: int, scale: float = 0.45, color=(40, 40, 40), thickness: int = 1) -> None:
    cv2.putText(img, s, (int(x), int(y)), _FONT, scale, color, thickness, cv2.LINE_AA)


def _rate_to_y(rate: np.ndarray | float, top_rate: float) -> np.ndarray | float:
    """Square-root scale so that light rain stays visible next to violent bursts."""
    frac = np.sqrt(np.clip(rate, 0, None) / top_rate)
    return _BOTTOM1 - frac * (_BOTTOM1 - _TOP1)


def render_summary_png(
    table: ObservationTable,
    series: PrecipSeries,
    *,
    start_s: float,
    end_s: float,
    camera: CameraSpec | None = None,
    config: MappingConfig | None = None,
    title: str = "",
) -> bytes:
    """PNG bytes: top, the precipitation rate of each period (mm/h, square-root axis) over WMO class bands;
    bottom, the mapped rain Gaussians per camera N_rain and the veil extinction β (1/km)."""
    camera = camera or CameraSpec()
    config = config or MappingConfig()
    img = np.full((_H, _W, 3), 255, np.uint8)
    if end_s <= start_s:
        end_s = start_s + 3600.0
    span = end_s - start_s

    def x_of(t):
        return _LEFT + (np.asarray(t) - start_s) / span * (_W - _LEFT - _RIGHT)

    sel = (series.end_s > start_s) & (series.start_s < end_s)
    rates = series.rate_mm_per_h[sel]
    top_rate = max(60.0, float(rates.max()) * 1.1 if rates.size else 0.0)
    for low, high, name, colour in WMO_BANDS:
        y0, y1 = int(_rate_to_y(min(high, top_rate), top_rate)), int(_rate_to_y(low, top_rate))
        cv2.rectangle(img, (_LEFT, y0), (_W - _RIGHT, y1), colour, -1)
        _text(img, name, _W - _RIGHT + 6, (y0 + y1) // 2 + 4, 0.42)
    for s, e, r in zip(series.start_s[sel], series.end_s[sel], rates):
        x0, x1 = int(x_of(max(s, start_s))), int(x_of(min(e, end_s)))
        y = int(_rate_to_y(r, top_rate))
        cv2.rectangle(img, (x0, y), (max(x1 - 1, x0), _BOTTOM1), (160, 90, 30), -1)
    for tick in (0.5, 2.5, 10, 50, 100, 200, 500):
        if tick <= top_rate:
            y = int(_rate_to_y(tick, top_rate))
            cv2.line(img, (_LEFT - 5, y), (_LEFT, y), (0, 0, 0), 1)
            _text(img, f"{tick:g}", 40, y + 4, 0.42)
    cv2.rectangle(img, (_LEFT, _TOP1), (_W - _RIGHT, _BOTTOM1), (0, 0, 0), 1)
    _text(img, "rate mm/h (sqrt axis)", 8, _TOP1 - 8, 0.45)
    _text(img, title, _LEFT + 120, 22, 0.6, (0, 0, 0), 1)
    _text(img, "blank = no data (gap)", _W - _RIGHT - 190, _TOP1 - 8, 0.42, (90, 90, 90))

    # bottom panel: mapped quantities at each period's rate (visibility and wind of the record ending it)
    by_end = {round(epoch_s(r.time_utc)): r for r in table.records}
    xs, counts, betas = [], [], []
    cache: dict[tuple, tuple[int, float]] = {}
    for s, e, r in zip(series.start_s[sel], series.end_s[sel], rates):
        rec = by_end.get(round(e))
        vis = None
        wind, direction = 0.0, None
        if rec is not None:
            if rec.visibility_m is not None and not rec.visibility_at_least:
                vis = rec.visibility_m
            wind = rec.wind_speed_m_per_s or 0.0
            direction = rec.wind_dir_deg_from
        key = (round(float(r), 3), vis, round(wind, 1), direction)
        if key not in cache:
            theta = theta_from_values(key[0], vis, key[2], direction, camera=camera, config=config)
            cache[key] = (theta.rain.count, theta.fog.beta_veil_per_m * 1000.0)
        xs.append(x_of(0.5 * (max(s, start_s) + min(e, end_s))))
        counts.append(cache[key][0])
        betas.append(cache[key][1])
    cv2.rectangle(img, (_LEFT, _TOP2), (_W - _RIGHT, _BOTTOM2), (0, 0, 0), 1)
    _text(img, "N_rain per camera", 8, _TOP2 - 10, 0.45, (180, 60, 0))
    _text(img, "beta veil 1/km", _W - _RIGHT - 40, _TOP2 - 10, 0.45, (140, 0, 160))
    if xs:
        n_top = max(1.0, max(counts) * 1.1)
        b_top = max(1e-3, max(betas) * 1.1)
        pts_n = np.array([[x, _BOTTOM2 - c / n_top * (_BOTTOM2 - _TOP2)] for x, c in zip(xs, counts)], np.int32)
        pts_b = np.array([[x, _BOTTOM2 - b / b_top * (_BOTTOM2 - _TOP2)] for x, b in zip(xs, betas)], np.int32)
        cv2.polylines(img, [pts_n.reshape(-1, 1, 2)], False, (180, 60, 0), 2, cv2.LINE_AA)
        cv2.polylines(img, [pts_b.reshape(-1, 1, 2)], False, (140, 0, 160), 2, cv2.LINE_AA)
        for frac in (0.0, 0.5, 1.0):
            y = int(_BOTTOM2 - frac / 1.1 * (_BOTTOM2 - _TOP2))
            _text(img, f"{frac / 1.1 * n_top:.3g}", 8, y + 4, 0.42, (180, 60, 0))
            _text(img, f"{frac / 1.1 * b_top:.3g}", _W - _RIGHT + 6, y + 4, 0.42, (140, 0, 160))
    # time axis (shared)
    for i in range(7):
        t = start_s + span * i / 6
        x = int(x_of(t))
        for y0 in (_BOTTOM1, _BOTTOM2):
            cv2.line(img, (x, y0), (x, y0 + 5), (0, 0, 0), 1)
        label = datetime.fromtimestamp(t, tz=timezone.utc).strftime("%m-%d %H:%M")
        _text(img, label, x - 42, _BOTTOM2 + 22, 0.42)
    _text(img, "time (UTC)", _W // 2 - 40, _BOTTOM2 + 48, 0.45)
    _text(
        img,
        f"mapping: physical (Marshall-Palmer), exposure {camera.exposure_s:.4g} s, N_max {config.n_max}",
        _LEFT,
        _H - 12,
        0.42,
        (90, 90, 90),
    )
    ok, buf = cv2.imencode(".png", img)
    if not ok:  # pragma: no cover - OpenCV always encodes PNG
        raise RuntimeError("OpenCV could not encode the PNG")
    return buf.tobytes()
