"""The built-in procedural scene: analytic primitives ray-cast with numpy, in metres, world up = +z.

A paved plaza with a lawn around it (the ground plane z = 0), a few boxes and spheres resting on it and
a sky dome of radius 20 m (distant hills at its foot, soft clouds above), so every ray hits something and
every pixel has a finite depth. Shading is Lambertian under a fixed sun with hard shadows plus ambient
light: view-independent, so all views agree. Textures are smooth procedural patterns (soft checkers,
smooth stripes, low-frequency value noise) with features several pixels wide at 160x120, and pixels are
supersampled so that silhouettes are anti-aliased. Nothing here is made of Gaussians.

Rays are never normalised: a camera ray's direction is ``R @ ((u - cx) / fx, (v - cy) / fy, 1)``, so the
ray parameter ``t`` of a hit *is* its z-depth along the optical axis.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np

from metegs.cameras import Cameras
from metegs.data.config import DatasetConfig, SyntheticSceneConfig
from metegs.data.scene import SceneData, split_every_nth
from metegs.errors import DataError

SUPERSAMPLE = 2
"""Samples per pixel along each axis (2 -> 2x2 samples averaged per pixel)."""
HFOV_DEG = 60.0
"""Horizontal field of view of every view."""
EXPOSURE_TIME_S = 1.0 / 250.0
"""Exposure time of every view (sets the rain streak length downstream)."""
DOME_RADIUS = 20.0
"""Radius (m) of the sky dome centred at the world origin."""
SUN_DIR = np.array([0.45, 0.3, 0.84]) / np.linalg.norm([0.45, 0.3, 0.84])
"""[3] unit direction towards the sun."""
AMBIENT = 0.4
"""Fraction of light that is ambient (reaches shadowed surfaces too)."""
EPS = 1e-6

SKY, GROUND = 0, 1
"""Material ids; boxes follow (2 ...), then spheres."""

PALETTE = np.array(
    [
        [0.72, 0.30, 0.22],  # brick red
        [0.80, 0.62, 0.25],  # ochre
        [0.25, 0.45, 0.70],  # painted blue
        [0.30, 0.58, 0.50],  # teal
        [0.78, 0.76, 0.70],  # concrete
        [0.55, 0.38, 0.25],  # wood
        [0.62, 0.35, 0.58],  # plum
        [0.85, 0.80, 0.40],  # yellow
    ]
)
"""[K, 3] base albedos of the objects (jittered per object)."""


# --------------------------------------------------------------------------------------------- scene


@dataclass
class Box:
    """A box standing on the ground, rotated by ``yaw`` about +z."""

    center: np.ndarray
    """[3] centre (m)."""
    half: np.ndarray
    """[3] half extents along its local axes (m)."""
    yaw: float
    """Rotation about +z (rad)."""
    albedo: np.ndarray
    """[3] base colour."""
    pattern: int
    """0: horizontal smooth stripes, 1: soft 3D checker, 2: value-noise blotches."""
    period: float
    """Pattern period (m)."""

    def to_local(self, v: np.ndarray) -> np.ndarray:
        """World vectors [..., 3] -> box axes [..., 3] (rotation only)."""
        c, s = np.cos(self.yaw), np.sin(self.yaw)
        return np.stack([c * v[..., 0] + s * v[..., 1], -s * v[..., 0] + c * v[..., 1], v[..., 2]], axis=-1)

    def to_world(self, v: np.ndarray) -> np.ndarray:
        """Box-axis vectors [..., 3] -> world [..., 3] (rotation only)."""
        c, s = np.cos(self.yaw), np.sin(self.yaw)
        return np.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1], v[..., 2]], axis=-1)


@dataclass
class Sphere:
    """A sphere resting on the ground."""

    center: np.ndarray
    """[3] centre (m)."""
    radius: float
    albedo: np.ndarray
    """[3] base colour."""
    axis: np.ndarray
    """[3] unit normal of its smooth stripes."""
    period: float
    """Stripe period (m)."""


class ValueNoise:
    """Smooth value noise: random values on a periodic integer lattice, smoothstep-interpolated in between."""

    SIZE = 64

    def __init__(self, rng: np.random.Generator):
        self.table = rng.random(self.SIZE**3)
        """[SIZE^3] flattened lattice values (the first SIZE^2 also serve as the 2D lattice)."""

    def __call__(self, p: np.ndarray, freq: float, octaves: int = 2) -> np.ndarray:
        """Points [R, 2] or [R, 3] (m), base frequency (1/m) -> values [R] in [0, 1] (mean 0.5)."""
        total, norm, amp = np.zeros(len(p)), 0.0, 1.0
        for o in range(octaves):
            total += amp * self._octave(p * (freq * 2.0**o) + 17.3 * o)
            norm += amp
            amp *= 0.5
        return total / norm

    def _octave(self, q: np.ndarray) -> np.ndarray:
        """Lattice coordinates [R, D] (D = 2 or 3) -> interpolated lattice values [R]."""
        i0 = np.floor(q)
        f = q - i0
        s = f * f * (3.0 - 2.0 * f)
        i0 = i0.astype(np.int64) % self.SIZE
        i1 = (i0 + 1) % self.SIZE
        # Corners are visited axis by axis: (flat index, weight) pairs double with each axis.
        corners = [(np.zeros(len(q), dtype=np.int64), np.ones(len(q)))]
        for axis in range(q.shape[1]):
            corners = [
                (idx * self.SIZE + i[:, axis], w * ws)
                for idx, w in corners
                for i, ws in ((i0, 1.0 - s[:, axis]), (i1, s[:, axis]))
            ]
        return sum(w * np.take(self.table, idx) for idx, w in corners)


@dataclass
class Scene:
    """Everything needed to trace and shade rays; built from a seed by `make_scene`."""

    boxes: list[Box]
    spheres: list[Sphere]
    noise: ValueNoise
    hill_harmonics: np.ndarray
    """[K, 3] (frequency, amplitude m, phase) of the hill silhouette around the dome."""
    ground_colors: np.ndarray
    """[4, 3] plaza tile A, plaza tile B, lawn dark, lawn light."""


def make_scene(rng: np.random.Generator) -> Scene:
    """Seeded layout: 4 boxes and 4 spheres on the plaza (within 4.8 m of the origin), not overlapping."""
    placed: list[tuple[np.ndarray, float]] = []  # (xy centre, footprint radius)

    def place(radius: float) -> np.ndarray:
        for _ in range(200):
            xy = rng.uniform(-4.0, 4.0, 2)
            if np.linalg.norm(xy) + radius > 4.8:
                continue
            if all(np.linalg.norm(xy - c) > radius + r + 0.3 for c, r in placed):
                placed.append((xy, radius))
                return xy
        placed.append((xy, radius))  # give up on spacing (never happens with these sizes)
        return xy

    def color() -> np.ndarray:
        return np.clip(PALETTE[rng.integers(len(PALETTE))] * rng.uniform(0.85, 1.1) + rng.normal(0, 0.03, 3), 0, 1)

    boxes = []
    for k in range(4):
        half = np.array([rng.uniform(0.3, 0.8), rng.uniform(0.3, 0.8), rng.uniform(0.25, 1.0 if k else 1.4)])
        xy = place(float(np.hypot(half[0], half[1])))
        boxes.append(
            Box(
                np.array([xy[0], xy[1], half[2]]),
                half,
                float(rng.uniform(0, np.pi)),
                color(),
                int(rng.integers(3)),
                float(rng.uniform(0.35, 0.6)),
            )
        )
    spheres = []
    for _ in range(4):
        r = float(rng.uniform(0.3, 0.75))
        xy = place(r)
        axis = rng.normal(size=3)
        spheres.append(
            Sphere(np.array([xy[0], xy[1], r]), r, color(), axis / np.linalg.norm(axis), float(rng.uniform(0.3, 0.5)))
        )
    k = np.arange(2, 8)
    hills = np.stack([k, rng.uniform(0.3, 1.0, len(k)) / k**0.7, rng.uniform(0, 2 * np.pi, len(k))], axis=1)
    ground = np.array([[0.62, 0.60, 0.55], [0.45, 0.43, 0.40], [0.25, 0.38, 0.16], [0.42, 0.50, 0.22]])
    ground = np.clip(ground * rng.uniform(0.9, 1.1, (4, 1)), 0, 1)
    return Scene(boxes, spheres, ValueNoise(rng), hills, ground)


# ------------------------------------------------------------------------------------- intersection


def dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise dot product of [R, 3] and [R, 3] or [3] arrays -> [R] (or a scalar for two [3] vectors)."""
    if a.ndim == 1 or b.ndim == 1:
        return a @ b if b.ndim == 1 else b @ a
    return np.einsum("ij,ij->i", a, b)


def rows(x: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """``x[idx]`` for per-ray arrays [R, 3]; a shared vector [3] is returned as it is."""
    return x if x.ndim == 1 else x[idx]


class Rays:
    """R rays o + t d. Either ``o`` or ``d`` may be one shared vector [3] (a camera centre, the sun direction).

    Directions need not be unit length: ``t`` is measured in units of |d|.
    """

    def __init__(self, o: np.ndarray, d: np.ndarray):
        self.o, self.d = o, d
        self.n = max(len(x) if x.ndim == 2 else 1 for x in (o, d))
        self.dd = dot(d, d)
        """[R] (or scalar) squared direction lengths."""
        if o.ndim == 2 and d.ndim == 1:  # shadow rays: precompute what every sphere test needs
            self.od, self.oo = o @ d, dot(o, o)

    def subset(self, idx: np.ndarray) -> Rays:
        return Rays(rows(self.o, idx), rows(self.d, idx))


def intersect_ground(rays: Rays) -> np.ndarray:
    """Rays vs the plane z = 0 -> t [R] (inf where missed)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.broadcast_to(-rays.o[..., 2] / rays.d[..., 2], (rays.n,))
    return np.where(np.isfinite(t) & (t > EPS), t, np.inf)


def intersect_sphere(rays: Rays, center: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Rays vs a sphere -> (indices [K] of the rays that hit it in front of their origin, their t [K]).

    From outside the near root is returned, from inside (the sky dome) the far one.
    """
    if rays.o.ndim == 2 and rays.d.ndim == 1:  # shared direction: expand |o - c|^2 (cheaper, precise enough)
        b = rays.od - center @ rays.d
        c = rays.oo - 2.0 * (rays.o @ center) + (center @ center - radius * radius)
    else:
        oc = rays.o - center
        b, c = dot(rays.d, oc), dot(oc, oc) - radius * radius
    disc = b * b - rays.dd * c
    idx = np.flatnonzero(disc >= 0)
    b, disc, a = b[idx], disc[idx], rays.dd if np.ndim(rays.dd) == 0 else rays.dd[idx]
    root = np.sqrt(disc)
    t_near, t_far = (-b - root) / a, (-b + root) / a
    t = np.where(t_near > EPS, t_near, t_far)
    front = t > EPS
    return idx[front], t[front]


def intersect_box(rays: Rays, box: Box) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rays vs a box (slab method, from outside) -> (ray indices [K], t [K], outward world normals [K, 3]).

    Only the rays that hit the box's bounding sphere run the slab test (most rays miss most boxes).
    """
    idx, _ = intersect_sphere(rays, box.center, float(np.linalg.norm(box.half)))
    ol = box.to_local(rows(rays.o, idx) - box.center)
    dl = box.to_local(rows(rays.d, idx))
    ol, dl = np.broadcast_arrays(ol.reshape(-1, 3), dl.reshape(-1, 3))
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / dl
        t1, t2 = (-box.half - ol) * inv, (box.half - ol) * inv
    t_min, t_max = np.minimum(t1, t2), np.maximum(t1, t2)
    t_near, t_far = np.nanmax(t_min, axis=1), np.nanmin(t_max, axis=1)
    hit = (t_near <= t_far) & (t_near > EPS)
    axis = np.argmax(np.nan_to_num(t_min[hit], nan=-np.inf), axis=1)
    local_normal = np.zeros((len(axis), 3))
    k = np.arange(len(axis))
    local_normal[k, axis] = -np.sign(dl[hit][k, axis])
    return idx[hit], t_near[hit], box.to_world(local_normal)


@dataclass
class Hit:
    """Nearest hits of R rays."""

    t: np.ndarray
    """[R] ray parameter (= z-depth for camera rays with unit z in camera axes)."""
    point: np.ndarray
    """[R, 3] world hit points."""
    normal: np.ndarray
    """[R, 3] unit outward normals (zero on the sky dome, which is not lit)."""
    material: np.ndarray
    """[R] int material id (SKY, GROUND, 2 + box index, 2 + #boxes + sphere index)."""


def trace(scene: Scene, o: np.ndarray, d: np.ndarray) -> Hit:
    """Nearest hit of every ray o + t d (o: [R, 3] or one shared origin [3]; d: [R, 3]) among the ground,
    boxes, spheres and the sky dome (which encloses everything, so every ray hits)."""
    rays = Rays(o, d)
    t = np.full(rays.n, np.inf)
    idx, t_dome = intersect_sphere(rays, np.zeros(3), DOME_RADIUS)
    t[idx] = t_dome
    material = np.full(rays.n, SKY)
    t_ground = intersect_ground(rays)
    closer = t_ground < t
    t[closer], material[closer] = t_ground[closer], GROUND
    normal = np.zeros((rays.n, 3))
    normal[closer, 2] = 1.0
    for k, box in enumerate(scene.boxes):
        idx, tb, nb = intersect_box(rays, box)
        closer = tb < t[idx]
        idx = idx[closer]
        t[idx], material[idx], normal[idx] = tb[closer], 2 + k, nb[closer]
    for k, sph in enumerate(scene.spheres):
        idx, ts = intersect_sphere(rays, sph.center, sph.radius)
        closer = ts < t[idx]
        idx, ts = idx[closer], ts[closer]
        t[idx], material[idx] = ts, 2 + len(scene.boxes) + k
        normal[idx] = (rows(o, idx) + ts[:, None] * d[idx] - sph.center) / sph.radius
    return Hit(t, o + t[:, None] * d, normal, material)


def in_shadow(scene: Scene, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """[R] bool: the sun is blocked by a box or sphere (the ground and the dome never cast shadows)."""
    rays = Rays(points + 1e-4 * normals, SUN_DIR)
    blocked = np.zeros(len(points), dtype=bool)
    for box in scene.boxes:
        blocked[intersect_box(rays, box)[0]] = True
    for sph in scene.spheres:
        blocked[intersect_sphere(rays, sph.center, sph.radius)[0]] = True
    return blocked


# ------------------------------------------------------------------------------------------ texture


def soft_checker(u: np.ndarray, v: np.ndarray, period: float, softness: float = 0.25) -> np.ndarray:
    """Checkerboard in [0, 1] with cells ``period`` wide and smooth (tanh) borders; u, v [R] (m)."""
    s = np.sin(np.pi * u / period) * np.sin(np.pi * v / period)
    return 0.5 + 0.5 * np.tanh(s / softness)


def smoothstep(e0: float, e1: float, x: np.ndarray) -> np.ndarray:
    x = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def ground_albedo(scene: Scene, p: np.ndarray) -> np.ndarray:
    """Ground points [R, 3] -> albedo [R, 3]: checker-tiled plaza (radius ~6.5 m) fading into a lawn."""
    tile_a, tile_b, lawn_a, lawn_b = scene.ground_colors
    p = p[:, :2]  # 2D noise on the plane
    edge = 6.5 + 0.8 * (scene.noise(p + 300.0, 0.4, 1) - 0.5)
    w = smoothstep(edge - 0.4, edge + 0.4, np.hypot(p[:, 0], p[:, 1]))[:, None]
    out = np.zeros((len(p), 3))
    near, far = np.flatnonzero(w[:, 0] < 1.0), np.flatnonzero(w[:, 0] > 0.0)
    q = p[near]
    tiles = soft_checker(q[:, 0], q[:, 1], 1.0)[:, None]
    grain = scene.noise(q + 100.0, 1.2, 2)[:, None]
    out[near] = (1 - w[near]) * (tile_b + (tile_a - tile_b) * tiles) * (0.9 + 0.2 * grain)
    out[far] += w[far] * (lawn_a + (lawn_b - lawn_a) * scene.noise(p[far] + 200.0, 0.35, 3)[:, None])
    return out


def box_albedo(scene: Scene, box: Box, p: np.ndarray) -> np.ndarray:
    """Points on ``box`` [R, 3] -> albedo [R, 3] from its pattern in box coordinates."""
    q = box.to_local(p - box.center)
    if box.pattern == 0:
        m = 0.5 + 0.5 * np.sin(2 * np.pi * q[:, 2] / box.period)
    elif box.pattern == 1:
        s = np.sin(np.pi * q[:, 0] / box.period) * np.sin(np.pi * q[:, 1] / box.period)
        m = 0.5 + 0.5 * np.tanh(s * np.sin(np.pi * (q[:, 2] + 0.25) / box.period) / 0.3)
    else:
        m = smoothstep(0.3, 0.7, scene.noise(q + 400.0, 1.0 / box.period / 2.0, 2))
    return box.albedo * (0.62 + 0.38 * m[:, None])


def sphere_albedo(sphere: Sphere, p: np.ndarray) -> np.ndarray:
    """Points on ``sphere`` [R, 3] -> albedo [R, 3]: smooth stripes in world space (uniform frequency)."""
    m = 0.5 + 0.5 * np.tanh(2.0 * np.sin(2 * np.pi * ((p - sphere.center) @ sphere.axis) / sphere.period))
    light = np.clip(sphere.albedo * 0.45 + 0.5, 0, 1)
    return sphere.albedo + (light - sphere.albedo) * m[:, None]


def sky_color(scene: Scene, p: np.ndarray) -> np.ndarray:
    """Points on the dome [R, 3] -> emitted colour [R, 3]: hazy hills at the horizon, blue sky, soft clouds."""
    elev = np.clip(p[:, 2] / DOME_RADIUS, 0.0, 1.0)[:, None]
    horizon, zenith = np.array([0.78, 0.84, 0.90]), np.array([0.32, 0.52, 0.82])
    sky = horizon + (zenith - horizon) * np.sqrt(elev)
    cloud_plane = p[:, :2] * (6.0 / (np.maximum(p[:, 2:], 0.0) + 6.0))  # flattened towards the horizon
    clouds = smoothstep(0.5, 0.75, scene.noise(cloud_plane + 500.0, 0.12, 3))[:, None]
    sky = sky + (np.array([0.95, 0.95, 0.96]) - sky) * 0.85 * clouds
    az = np.arctan2(p[:, 1], p[:, 0])
    f, amp, phase = scene.hill_harmonics.T
    height = 2.2 + np.sin(az[:, None] * f + phase) @ amp
    hill_plane = p[:, :2] + p[:, 2:] * np.array([0.6, -0.4])  # a 2D slice through 3D space
    hill = np.array([0.36, 0.46, 0.42]) * (0.85 + 0.3 * scene.noise(hill_plane + 600.0, 0.3, 2)[:, None])
    hill = hill + (horizon - hill) * 0.25 * smoothstep(0.0, 4.0, p[:, 2])[:, None]  # aerial perspective
    w = smoothstep(-0.25, 0.25, p[:, 2] - height)[:, None]
    return hill * (1 - w) + sky * w


def shade(scene: Scene, hit: Hit) -> np.ndarray:
    """Hits -> display colours [R, 3] in [0, 1]: albedo x (ambient + sun x (n . sun) x lit); the sky emits."""
    rgb = np.empty((len(hit.t), 3))
    sky = np.flatnonzero(hit.material == SKY)
    rgb[sky] = sky_color(scene, hit.point[sky])
    solid = np.flatnonzero(hit.material != SKY)
    p, n, m = hit.point[solid], hit.normal[solid], hit.material[solid]
    albedo = np.empty((len(solid), 3))
    sel = np.flatnonzero(m == GROUND)
    albedo[sel] = ground_albedo(scene, p[sel])
    for k, box in enumerate(scene.boxes):
        sel = np.flatnonzero(m == 2 + k)
        albedo[sel] = box_albedo(scene, box, p[sel])
    for k, sph in enumerate(scene.spheres):
        sel = np.flatnonzero(m == 2 + len(scene.boxes) + k)
        albedo[sel] = sphere_albedo(sph, p[sel])
    cos = np.clip(n @ SUN_DIR, 0.0, 1.0)
    light = AMBIENT + (1.0 - AMBIENT) * 1.1 * cos * ~in_shadow(scene, p, n)
    rgb[solid] = albedo * light[:, None]
    return np.clip(rgb, 0.0, 1.0)


# ------------------------------------------------------------------------------------------ cameras


def look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Camera-to-world [4, 4] (OpenCV axes: x right, y down, z forward) at ``eye`` looking at ``target``, z up."""
    forward = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    c2w = np.eye(4)
    c2w[:3, :3] = np.stack([right, down, forward], axis=1)
    c2w[:3, 3] = eye
    return c2w


def orbit_poses(n: int, rng: np.random.Generator) -> np.ndarray:
    """[N, 4, 4] camera-to-worlds on a jittered 360 degree orbit: radius 6-9 m, height 1.5-3.5 m."""
    i = np.arange(n)
    phase_r, phase_h = rng.uniform(0, 2 * np.pi, 2)
    theta = 2 * np.pi * (i + rng.uniform(-0.2, 0.2, n)) / n
    radius = np.clip(7.5 + 1.2 * np.sin(3 * theta + phase_r) + rng.uniform(-0.3, 0.3, n), 6.0, 9.0)
    height = np.clip(2.5 + 0.8 * np.sin(2 * theta + phase_h) + rng.uniform(-0.2, 0.2, n), 1.5, 3.5)
    eyes = np.stack([radius * np.cos(theta), radius * np.sin(theta), height], axis=1)
    targets = np.array([0.0, 0.0, 0.6]) + rng.normal(0.0, [0.3, 0.3, 0.15], (n, 3))
    return np.stack([look_at(e, t) for e, t in zip(eyes, targets)])


def pixel_rays(
    c2w: np.ndarray, fx: float, cx: float, cy: float, width: int, height: int, offsets: np.ndarray
) -> np.ndarray:
    """Directions [H, W, S, 3] of the rays through pixel (column, row) + offset for each offset [S, 2].

    Directions have unit z in camera axes, so the hit parameter t is the z-depth (square pixels, fy = fx).
    """
    u = np.arange(width)[None, :, None] + offsets[None, None, :, 0]
    v = np.arange(height)[:, None, None] + offsets[None, None, :, 1]
    u, v = np.broadcast_arrays(u, v)
    d_cam = np.stack([(u - cx) / fx, (v - cy) / fx, np.ones_like(u)], axis=-1)
    return d_cam @ c2w[:3, :3].T


# ------------------------------------------------------------------------------------------- render


def render_view(scene: Scene, c2w: np.ndarray, fx: float, cx: float, cy: float, width: int, height: int):
    """One view -> image [H, W, 3] (supersampled), z-depth [H, W] and the centre-ray directions [H, W, 3]."""
    g = (np.arange(SUPERSAMPLE) + 0.5) / SUPERSAMPLE
    offsets = np.stack(np.meshgrid(g, g, indexing="ij"), axis=-1).reshape(-1, 2)
    eye = c2w[:3, 3]
    d = pixel_rays(c2w, fx, cx, cy, width, height, offsets)
    rgb = shade(scene, trace(scene, eye, d.reshape(-1, 3)))
    image = rgb.reshape(height, width, len(offsets), 3).mean(axis=2)
    d = pixel_rays(c2w, fx, cx, cy, width, height, np.array([[0.5, 0.5]]))
    depth = trace(scene, eye, d.reshape(-1, 3)).t.reshape(height, width)
    return image.astype(np.float32), depth.astype(np.float32), d[:, :, 0]


def sample_points(
    scene: Scene, poses: np.ndarray, rays: list[np.ndarray], views: list[int], count: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """``count`` surface points seen through random pixel centres of ``views``, coloured by their shading."""
    if not views or count <= 0:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32)
    h, w = rays[0].shape[:2]
    view = np.asarray(views)[rng.integers(len(views), size=count)]
    row, col = rng.integers(h, size=count), rng.integers(w, size=count)
    d = np.stack(rays)[view, row, col]
    hit = trace(scene, poses[view, :3, 3], d)
    return hit.point.astype(np.float32), shade(scene, hit).astype(np.float32)


def build_scene(cfg: SyntheticSceneConfig, test_every: int = 8) -> SceneData:
    """The whole synthetic scene as `SceneData` (images in memory, exact depths, surface points)."""
    if cfg.width < 1 or cfg.height < 1:
        raise DataError("synthetic", f"width and height must be positive, got {cfg.width}x{cfg.height}")
    if not cfg.metres_per_unit > 0:
        raise DataError("synthetic", f"metres_per_unit must be positive, got {cfg.metres_per_unit}")
    if cfg.num_views < 1:
        raise DataError("synthetic", f"num_views must be positive, got {cfg.num_views}")
    rng = np.random.default_rng(cfg.seed)
    scene = make_scene(rng)
    # Render with exactly the float32 values stored in `Cameras`, so depths are exact for those cameras.
    poses = orbit_poses(cfg.num_views, rng).astype(np.float32).astype(np.float64)
    fx = float(np.float32(0.5 * cfg.width / np.tan(np.radians(HFOV_DEG) / 2)))
    cx, cy = cfg.width / 2.0, cfg.height / 2.0
    # Views are independent and numpy releases the GIL in its array loops: render them on all cores.
    with ThreadPoolExecutor(max_workers=min(len(poses), os.cpu_count() or 1)) as pool:
        rendered = list(pool.map(lambda c2w: render_view(scene, c2w, fx, cx, cy, cfg.width, cfg.height), poses))
    images, depths, rays = (list(x) for x in zip(*rendered))
    train, test = split_every_nth(cfg.num_views, test_every)
    points, colors = sample_points(scene, poses, rays, train or test, cfg.num_points, rng)
    cameras = Cameras.create(poses.astype(np.float32), fx, fx, cx, cy, cfg.width, cfg.height, EXPOSURE_TIME_S)
    return SceneData(
        cameras=cameras,
        names=[f"view_{i:03d}" for i in range(cfg.num_views)],
        images=images,
        clean_images=images,
        depths=depths,
        train_indices=train,
        test_indices=test,
        points=points,
        point_colors=colors,
        up=np.array([0.0, 0.0, 1.0], dtype=np.float32),
        metric_scale=cfg.metres_per_unit,
        source=None,
        image_space="srgb",
        rendered=True,
    )


class SyntheticParser:
    """The procedural default scene (no files): `DatasetConfig.synthetic` sets its size, views and seed."""

    priority: ClassVar[int] = 1000

    @staticmethod
    def can_parse(path: Path) -> bool:
        """Never detected from a folder: the synthetic scene is used when no ``--data`` is given."""
        return False

    def parse(self, path: Path | None, options: DatasetConfig) -> SceneData:
        """Build the scene from ``options.synthetic`` (``path`` is ignored)."""
        return build_scene(options.synthetic, options.test_every)
