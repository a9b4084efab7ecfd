"""The independent degradation family: weather made without metegs's weather models or θ mapping.

metegs's own family (`metegs.weather.degrade`) renders the very rain-streak Gaussians and fog model that training
then fits, so a method judged on it can fit its own generator (the inverse crime). This family is written apart
from them, in the style of the public deraining and dehazing datasets, and is driven only by the met conditions
(WMO rain class, visibility, wind) that also set training's θ:

- **rain**: 2D streak layers as in Rain100L/H and Rain800: per view, several depth layers of sparse seeds smeared
  by a line kernel, each layer with its own density, length, angle, width, brightness and blur drawn anew for every
  view from ranges set by the WMO class; screen-blended over the photo, with a faint veil in heavy rain;
- **fog**: a heterogeneous medium fixed in the scene (so every view sees the same fog): extinction that falls
  with height above the ground and varies in patches (a sum of random 3D waves), a slightly different
  extinction per colour channel, and an airlight that brightens towards the horizon and towards a sun direction.
  Its mean extinction at ground level, where stations measure, follows the visibility (Koschmieder: β = 3.912 / V);
- **lens drops**: blurred, slightly magnified blobs with a dark rim and a highlight (an image-space model of
  out-of-focus drops, as in the raindrop-removal datasets), not the refractive model of ``lens-droplets``.

Every random choice comes from a generator seeded by (seed, view), and what was drawn goes into weather.json.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import cv2
import numpy as np

from metegs.cameras import Cameras
from metegs.meteo.aggregate import WeatherConditions

KOSCHMIEDER = 3.912
"""β · V for a 2 % contrast threshold: the mean extinction at ground level is 3.912 / visibility (1/m)."""

CLEAR_VISIBILITY_M = 10_000.0
"""At or above this visibility no fog is added (WMO: fog below 1 km, mist up to 5 km, haze beyond)."""

REFERENCE_WIDTH_PX = 640
"""Streak lengths and drop sizes are drawn for this image width and scaled to the view's."""


@dataclass(frozen=True)
class RainStyle:
    """Ranges of the streak layers of one WMO rain class (lengths and widths at `REFERENCE_WIDTH_PX`)."""

    layers: tuple[int, int]
    density: tuple[float, float]
    """Streak seeds per pixel of a layer."""
    length_px: tuple[float, float]
    width_px: tuple[float, float]
    brightness: tuple[float, float]
    veil: float
    """Share of airlight blended over the photo (rain too dense to see through, in heavy rain)."""


RAIN_STYLES = {
    "light": RainStyle((1, 2), (0.0008, 0.0015), (10, 20), (0.8, 1.2), (0.35, 0.55), 0.0),
    "moderate": RainStyle((2, 3), (0.0015, 0.003), (15, 30), (0.8, 1.5), (0.45, 0.7), 0.02),
    "heavy": RainStyle((3, 4), (0.003, 0.006), (20, 40), (1.0, 2.0), (0.55, 0.85), 0.06),
    "violent": RainStyle((4, 5), (0.005, 0.009), (25, 50), (1.2, 2.5), (0.6, 0.9), 0.12),
}
"""Streak styles per WMO intensity class: few thin dim streaks in light rain (Rain100L), many long bright layers
in several directions in heavy rain (Rain100H)."""

DROP_COUNTS = {"light": (2, 5), "moderate": (4, 9), "heavy": (7, 14), "violent": (10, 20)}
"""Lens drops per view by WMO class (only with ``+drops``)."""


@dataclass(frozen=True)
class FogField:
    """The heterogeneous medium of one scene: the same in every view."""

    beta_per_m: float
    """Mean extinction at ground level, where stations measure visibility, 1/m (from the visibility)."""
    scale_height_m: float
    """Extinction falls as exp(−height / this) above the ground."""
    channel_scale: tuple[float, float, float]
    """Per-channel factors of the extinction (R, G, B)."""
    patch_amplitude: float
    """Relative amplitude of the patches."""
    wave_vectors_per_m: tuple[tuple[float, float, float], ...]
    """World-space wave vectors of the patches, 1/m (scene axes)."""
    wave_phases: tuple[float, ...]
    airlight: tuple[float, float, float]
    """Airlight at the horizon, RGB."""
    sun_dir: tuple[float, float, float]
    """Unit world direction of the sun, for the forward-scattering lobe of the airlight."""


def rain_class(conditions: WeatherConditions) -> str | None:
    """The WMO class that sets the rain's style, or None when it does not rain."""
    p = conditions.precip_mm_per_h or 0.0
    if p <= 0:
        return None
    if conditions.intensity_class in RAIN_STYLES:
        return conditions.intensity_class
    return "light" if p < 2.5 else "moderate" if p < 10 else "heavy" if p < 50 else "violent"


def draw_fog_field(rng: np.random.Generator, visibility_m: float, mpu: float) -> FogField:
    """A random heterogeneous medium whose mean extinction at camera height gives ``visibility_m``."""
    waves = []
    for _ in range(6):
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        wavelength_m = rng.uniform(15.0, 80.0)
        waves.append(tuple(float(v) for v in direction * (2 * math.pi / wavelength_m)))
    tint = np.array([0.97, 1.0, 1.04]) * rng.normal(1.0, 0.015, size=3)  # grey to slightly blue, as fog looks
    sun = rng.normal(size=3)
    return FogField(
        beta_per_m=KOSCHMIEDER / visibility_m,
        scale_height_m=float(rng.uniform(15.0, 60.0)),
        channel_scale=tuple(float(v) for v in np.array([0.92, 1.0, 1.1]) * rng.uniform(0.95, 1.05, 3)),
        patch_amplitude=float(rng.uniform(0.3, 0.6)),
        wave_vectors_per_m=tuple(waves),
        wave_phases=tuple(float(v) for v in rng.uniform(0, 2 * math.pi, 6)),
        airlight=tuple(float(v) for v in np.clip(rng.uniform(0.72, 0.9) * tint, 0, 1)),
        sun_dir=tuple(float(v) for v in sun / np.linalg.norm(sun)),
    )


def pixel_rays(camera: Cameras, height: int, width: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(centre [3], unit world ray directions [H, W, 3], length of the ray per unit of depth [H, W]) of one camera
    at the image size (intrinsics scaled from the camera's size)."""
    c2w = camera.camera_to_worlds[0].double().numpy()
    sx, sy = width / float(camera.width[0]), height / float(camera.height[0])
    fx, fy = float(camera.fx[0]) * sx, float(camera.fy[0]) * sy
    cx, cy = float(camera.cx[0]) * sx, float(camera.cy[0]) * sy
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    d_cam = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)], axis=-1)
    per_depth = np.linalg.norm(d_cam, axis=-1)
    d_world = (d_cam / per_depth[..., None]) @ c2w[:3, :3].T
    return c2w[:3, 3], d_world, per_depth


def fog_view(
    image: np.ndarray,
    depth: np.ndarray,
    camera: Cameras,
    field: FogField,
    up: np.ndarray,
    ground: float,
    mpu: float,
    samples: int = 12,
) -> tuple[np.ndarray, np.ndarray]:
    """(fogged image [H, W, 3], transmittance [H, W, 3]) of one view through ``field``: the optical depth is
    integrated along each pixel's ray to its surface (``depth``: [H, W] along the optical axis, scene units) with
    ``samples`` midpoints, up to 5 visibilities away (the sky, or unknown depth, ends there); ``ground``: height
    (scene units along ``up``) where the extinction is ``beta_per_m``."""
    h, w = depth.shape
    centre, dirs, per_depth = pixel_rays(camera, h, w)
    reach = 5.0 * KOSCHMIEDER / field.beta_per_m / mpu  # scene units
    dist = np.minimum(depth.astype(np.float64) * per_depth, reach)  # scene units along the ray
    waves = np.array(field.wave_vectors_per_m) * mpu  # 1/scene unit
    phases = np.array(field.wave_phases)
    tau = np.zeros((h, w))
    for k in range(samples):
        s = dist * (k + 0.5) / samples
        x = centre + dirs * s[..., None]  # [H, W, 3]
        height_m = (x @ up - ground) * mpu
        patches = 1.0 + field.patch_amplitude * np.sin(x @ waves.T + phases).mean(axis=-1) * math.sqrt(2)
        tau += field.beta_per_m * np.exp(-np.maximum(height_m, 0.0) / field.scale_height_m) * np.maximum(patches, 0.1)
    tau *= dist * mpu / samples  # metres per sample
    t = np.exp(-tau[..., None] * np.array(field.channel_scale))
    elevation = np.clip(dirs @ up, -1.0, 1.0)
    sun = np.maximum(dirs @ np.array(field.sun_dir), 0.0) ** 8
    air = np.array(field.airlight) * (0.85 + 0.15 * (1.0 - np.abs(elevation)))[..., None]
    air = air + 0.12 * sun[..., None] * np.array([1.0, 0.95, 0.85])
    out = image * t + np.clip(air, 0.0, 1.0) * (1.0 - t)
    return out.astype(np.float32), t.astype(np.float32)


def line_kernel(length_px: float, angle_deg: float) -> np.ndarray:
    """[n, n] float32, n the odd side at least 3 nearest ``length_px``: ones along a line through the centre at
    ``angle_deg`` from the image's vertical (clockwise positive), zeros elsewhere (not normalised)."""
    n = max(3, int(round(length_px)) | 1)
    kernel = np.zeros((n, n), np.float32)
    c = n // 2
    a = math.radians(angle_deg)
    dx, dy = math.sin(a), math.cos(a)
    for s in np.linspace(-c, c, 4 * n):
        kernel[int(round(c + s * dy)), int(round(c + s * dx))] = 1.0
    return kernel


def streak_layer(
    rng: np.random.Generator,
    height: int,
    width: int,
    density: float,
    length_px: float,
    angle_deg: float,
    width_px: float,
    brightness: float,
    blur_px: float,
) -> np.ndarray:
    """[H, W] float32 intensity of one layer of rain streaks: seeds at ``density`` per pixel, smeared along a line
    of ``length_px`` at ``angle_deg`` from the image's vertical (clockwise positive), widened and blurred; the
    brightest streaks reach about ``brightness``."""
    seeds = (rng.random((height, width)) < density).astype(np.float32) * rng.uniform(0.5, 1.0, (height, width))
    kernel = line_kernel(length_px, angle_deg)
    layer = cv2.filter2D(seeds, -1, kernel / kernel.sum(), borderType=cv2.BORDER_REFLECT)
    sigma = max(0.3, 0.5 * (width_px - 1.0) + blur_px)
    layer = cv2.GaussianBlur(layer, (0, 0), sigma)
    peak = float(np.percentile(layer[layer > 0], 99.5)) if (layer > 0).any() else 1.0
    return np.clip(layer / max(peak, 1e-6), 0.0, 1.0) * brightness


def rain_view(
    rng: np.random.Generator, image: np.ndarray, klass: str, wind_angle_deg: float, airlight: np.ndarray
) -> tuple[np.ndarray, dict]:
    """(rainy image [H, W, 3], what was drawn) of one view: `RAIN_STYLES` layers screen-blended over ``image``."""
    h, w = image.shape[:2]
    style = RAIN_STYLES[klass]
    scale = w / REFERENCE_WIDTH_PX
    view_angle = wind_angle_deg + rng.normal(0.0, 6.0)
    rain = np.zeros((h, w), np.float32)
    layers = []
    for k in range(int(rng.integers(style.layers[0], style.layers[1] + 1))):
        depth = k / max(1, style.layers[1] - 1)  # 0: nearest layer, 1: farthest
        params = {
            "density": float(rng.uniform(*style.density)),
            "length_px": float(max(3.0, rng.uniform(*style.length_px) * scale * (1.0 - 0.4 * depth))),
            "angle_deg": float(view_angle + rng.normal(0.0, 4.0 + 6.0 * (klass in ("heavy", "violent")))),
            "width_px": float(max(0.6, rng.uniform(*style.width_px) * max(scale, 0.5) * (1.0 - 0.3 * depth))),
            "brightness": float(rng.uniform(*style.brightness) * (1.0 - 0.35 * depth)),
            "blur_px": float(rng.uniform(0.0, 0.6) + 0.8 * depth),
        }
        rain = 1.0 - (1.0 - rain) * (1.0 - streak_layer(rng, h, w, **params))
        layers.append(params)
    tint = np.array([0.95, 0.97, 1.0], np.float32)
    veiled = image * (1.0 - style.veil) + airlight * style.veil
    out = 1.0 - (1.0 - veiled) * (1.0 - rain[..., None] * tint)
    return out.astype(np.float32), {"class": klass, "veil": style.veil, "layers": layers}


def drops_view(rng: np.random.Generator, image: np.ndarray, klass: str) -> tuple[np.ndarray, dict]:
    """(image with out-of-focus lens drops [H, W, 3], what was drawn): each drop shows the blurred, slightly
    magnified view behind it, a darker rim and a highlight, with a soft irregular edge."""
    h, w = image.shape[:2]
    out = image.copy()
    drops = []
    blurred = cv2.GaussianBlur(image, (0, 0), max(1.0, 0.02 * w))
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    for _ in range(int(rng.integers(*DROP_COUNTS[klass]))):
        r = float(rng.uniform(0.02, 0.06) * w)
        cx, cy = float(rng.uniform(0, w)), float(rng.uniform(0, h))
        squash = float(rng.uniform(0.75, 1.0))
        angle = np.arctan2(yy - cy, xx - cx)
        wobble = 1.0 + 0.12 * np.sin(3 * angle + rng.uniform(0, 6.3)) + 0.06 * np.sin(5 * angle + rng.uniform(0, 6.3))
        rho = np.hypot(xx - cx, (yy - cy) / squash) / (r * wobble)
        alpha = np.clip((1.0 - rho) / 0.25, 0.0, 1.0)[..., None]
        if not alpha.any():
            continue
        mx, my = cx + (xx - cx) * 0.7, cy + (yy - cy) * 0.7  # magnified: the centre's surroundings spread out
        inside = cv2.remap(blurred, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        rim = np.exp(-(((rho - 0.9) / 0.08) ** 2))[..., None]
        glint = np.exp(-(((xx - cx + 0.35 * r) ** 2 + (yy - cy + 0.35 * r) ** 2) / (0.12 * r) ** 2))[..., None]
        drop = np.clip(inside * 1.05 - 0.25 * rim + 0.5 * glint, 0.0, 1.0)
        out = out * (1.0 - alpha) + drop * alpha
        drops.append({"x": cx, "y": cy, "radius_px": r, "squash": squash})
    return out.astype(np.float32), {"count": len(drops), "drops": drops}


def ground_height(scene, up: np.ndarray) -> float:
    """Height of the ground along ``up`` (scene units): a low percentile of the scene's points, else the lowest
    camera."""
    if scene.points is not None and len(scene.points) > 0:
        return float(np.percentile(np.asarray(scene.points, np.float64) @ up, 2))
    return float((scene.cameras.camera_to_worlds[:, :3, 3].double().numpy() @ up).min())


def wind_angle_deg(conditions: WeatherConditions) -> float:
    """Slant of the streaks from the vertical, degrees: the wind against a fall speed of about 6 m/s, its side
    set by where the wind comes from (the cameras' headings are not known to this family)."""
    speed = conditions.wind_speed_m_per_s or 0.0
    side = 1.0 if math.sin(math.radians(conditions.wind_dir_deg_from or 90.0)) >= 0 else -1.0
    return side * math.degrees(math.atan2(speed, 6.0))


class IndependentEngine:
    """Degrades the views of one scene with the independent family (same interface as the physical engine)."""

    def __init__(self, scene, conditions: list[WeatherConditions], kinds: frozenset[str], seed: int, mpu: float):
        self.scene, self.conditions, self.kinds, self.seed, self.mpu = scene, conditions, kinds, int(seed), mpu
        self.up = np.asarray(scene.up, np.float64) / np.linalg.norm(scene.up)
        self.ground = ground_height(scene, self.up)
        self.fields: dict[float, FogField] = {}

    def field(self, visibility_m: float) -> FogField:
        """The scene's medium for ``visibility_m`` (one per visibility: the same in every view)."""
        if visibility_m not in self.fields:
            self.fields[visibility_m] = draw_fog_field(np.random.default_rng([self.seed, 7919]), visibility_m, self.mpu)
        return self.fields[visibility_m]

    def view(self, i: int, image: np.ndarray, depth: np.ndarray) -> tuple[np.ndarray, dict]:
        """(degraded image [H, W, 3], weather.json record) of view ``i``."""
        cond = self.conditions[i]
        rng = np.random.default_rng([self.seed, i])
        out = np.asarray(image, np.float32)
        record: dict = {"view": i, "name": self.scene.names[i], "family": "independent", "seed": [self.seed, i]}
        record["conditions"] = {
            "precip_mm_h": cond.precip_mm_per_h,
            "wmo_class": cond.intensity_class,
            "visibility_m": cond.visibility_m,
            "wind_speed_m_s": cond.wind_speed_m_per_s,
            "wind_dir_deg": cond.wind_dir_deg_from,
        }
        vis = cond.visibility_m
        airlight = np.full(3, 0.8, np.float32)
        if "fog" in self.kinds and vis is not None and vis < CLEAR_VISIBILITY_M:
            field = self.field(float(vis))
            out, t = fog_view(out, depth, self.scene.cameras[i], field, self.up, self.ground, self.mpu)
            airlight = np.array(field.airlight, np.float32)
            record["fog"] = {**asdict(field), "mean_transmittance": float(t.mean())}
        klass = rain_class(cond)
        if "rain" in self.kinds and klass is not None:
            out, record["rain"] = rain_view(rng, out, klass, wind_angle_deg(cond), airlight)
            if "drops" in self.kinds:
                out, record["drops"] = drops_view(rng, out, klass)
        record["kinds"] = "+".join(k for k in ("rain", "fog", "drops") if k in record)
        return np.clip(out, 0.0, 1.0), record
