"""Degrade the views of a scene with weather from θ: per-view rain streaks, one fog medium, optional lens drops.

For each view the photo is treated as a backdrop at its depth map (z along the optical axis, scene units):

1. fog (``fog-analytic``): ``C = I·t + A·(1 − t)``, ``t = exp(−β·d)``, d the ray length to the backdrop in
   metres; pixels of unknown depth (non-finite or ≤ 0, e.g. where a trained run renders nothing) take the
   depth of the nearest known pixel (a view without any known depth is infinitely far: airlight);
2. rain (``rain-streaks``): that view's streak Gaussians (seeded per view) are rasterised alone and
   composited over the fogged photo; a streak behind the backdrop is hidden (its mean is culled when it
   lies behind the depth at its pixel, and pixels whose rendered rain depth lies behind the backdrop are
   masked), and the air between the camera and the streak fogs it like everything else;
3. lens drops (``lens-droplets``, only when asked for): image-space refractive drops, last.

The medium (β, airlight) is the same in every view: the airlight is estimated once from all clean images
(unless θ gives it), so two views of one point agree on its fog; the rain is drawn anew for every view.
"""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from metegs.data.images import load_image
from metegs.data.scene import SceneData
from metegs.errors import ConfigError, DataError
from metegs.meteo.mapping import Theta
from metegs.registry import registry
from metegs.render.base import RenderOutput, RenderSettings
from metegs.render.cpu_backend import single_thread
from metegs.weather.airlight import estimate_airlight
from metegs.weather.base import WeatherModel, WeatherScene
from metegs.weather.compose import build_weather_models
from metegs.weather.fog_analytic import ray_lengths

KINDS = ("rain", "fog", "drops")
"""Weather kinds ``kinds`` may join with ``+``: ``rain`` (the streaks within their far distance and the veil of the
rain beyond it, θ_fog.beta_rain_per_m, over clear air), ``fog`` (the fog medium, plus the rain's veil when it
rains) and ``drops`` (lens drops when it rains: θ_drops' count when the record implies drops,
else the model's forced default). Lens drops are a property of one camera's glass, not of the scene's weather, and
they hide large parts of the view: they are added only when asked for."""

FAMILIES = ("physical", "independent")
"""Degradation families: metegs's own weather models from θ, or `metegs.weather.independent` (a benchmark that the
method cannot fit with its own generator)."""

UNKNOWN_DEPTH = 1e9
"""Depth (scene units) given to pixels whose depth is unknown: far beyond any fog's reach."""


def parse_kinds(kinds: str) -> frozenset[str]:
    """``"rain+fog"`` → {"rain", "fog"}; ConfigError for unknown or empty kinds."""
    parts = frozenset(k.strip().lower() for k in str(kinds).split("+") if k.strip())
    unknown = sorted(parts - set(KINDS))
    if unknown or not parts & {"rain", "fog"}:
        raise ConfigError(
            f"kinds={kinds!r}: expected 'rain', 'fog' or 'rain+fog' (optionally '+drops' to force lens drops)"
            + (f"; unknown: {', '.join(unknown)}" if unknown else "")
        )
    return parts


@dataclass
class DegradedView:
    """One degraded view."""

    index: int
    """View index in the scene."""
    image: np.ndarray
    """[H, W, 3] float32 degraded image in [0, 1]."""
    clean: np.ndarray
    """[H, W, 3] float32 original image."""
    record: dict
    """What weather.json says about this view (θ, seeds, what was drawn)."""


def degrade_scene(
    scene: SceneData,
    theta: Theta | Sequence[Theta],
    *,
    kinds: str = "rain+fog",
    seed: int = 0,
    metres_per_unit: float | None = None,
    depths: Sequence[np.ndarray] | None = None,
    family: str = "physical",
) -> tuple[SceneData, list[dict]]:
    """A copy of ``scene`` whose views carry the weather of ``theta``.

    Args:
        scene: any parsed scene; its images are read from ``images`` or ``image_paths``.
        theta: one θ for every view, or one per view (same length as the scene).
        kinds: ``rain``, ``fog`` or ``rain+fog``; ``+drops`` adds lens drops when it rains (θ_drops' count, or the
            lens model's forced default when θ_drops has none).
        seed: seed of every random choice (view v's rain and lens drops are seeded from (seed, v)).
        metres_per_unit: length of a scene unit in metres; None: ``scene.metric_scale`` or 1.0.
        depths: per view [H, W] depth (z along the optical axis, scene units; non-finite or ≤ 0 where unknown,
            filled from the nearest known pixel); None: ``scene.depths``.
        family: ``physical`` or ``independent`` (see `iter_degraded_views`).

    Returns:
        (scene copy, records): the copy's ``images`` are the degraded views (float32 [H, W, 3] in memory),
        its ``clean_images`` the original images (``image_paths``/``clean_image_paths`` are None: the arrays
        are authoritative); one record per view for weather.json (view, name, seed, kinds, θ.to_dict(), the
        number of rain Gaussians drawn and their visible coverage, and with fog the medium's β per channel
        and airlight).
    """
    images, cleans, records = [], [], []
    for view in iter_degraded_views(
        scene, theta, kinds=kinds, seed=seed, metres_per_unit=metres_per_unit, depths=depths, family=family
    ):
        images.append(view.image)
        cleans.append(view.clean)
        records.append(view.record)
    out = dataclasses.replace(scene, images=images, clean_images=cleans, image_paths=None, clean_image_paths=None)
    return out, records


def iter_degraded_views(
    scene: SceneData,
    theta: Theta | Sequence[Theta],
    *,
    kinds: str = "rain+fog",
    seed: int = 0,
    metres_per_unit: float | None = None,
    depths: Sequence[np.ndarray] | None = None,
    views: Sequence[int] | None = None,
    family: str = "physical",
) -> Iterator[DegradedView]:
    """`degrade_scene` one view at a time (for progress bars); ``views`` picks a subset (default: all).
    ``family``: ``physical`` (metegs's weather models from θ) or ``independent`` (`metegs.weather.independent`:
    made without them, from θ's met conditions only)."""
    wanted = parse_kinds(kinds)
    n = len(scene)
    thetas = _per_view_thetas(theta, n)
    mpu = float(metres_per_unit if metres_per_unit is not None else (scene.metric_scale or 1.0))
    if not (np.isfinite(mpu) and mpu > 0):
        raise ConfigError(f"metres_per_unit must be a positive number, got {metres_per_unit}")
    depth_maps = depths if depths is not None else scene.depths
    if depth_maps is None:
        raise DataError(
            scene.source or "scene",
            "no depth maps: weather needs each view's depth (the synthetic scene has exact depth; for other "
            "scenes render it from a trained 3dgs run, e.g. metegs-synth --depth-from RUN_DIR)",
        )
    if len(depth_maps) != n:
        raise DataError(scene.source or "scene", f"{len(depth_maps)} depth maps for {n} views")
    clean = _clean_images(scene)
    if family == "physical":
        engine = _Engine(scene, thetas, wanted, seed, mpu, clean)
    elif family == "independent":
        from metegs.weather.independent import IndependentEngine

        engine = IndependentEngine(scene, [t.conditions for t in thetas], wanted, seed, mpu)
    else:
        raise ConfigError(f"family={family!r}: expected one of {', '.join(FAMILIES)}")
    for i in range(n) if views is None else views:
        image = clean[i]() if callable(clean[i]) else clean[i]
        depth = _depth_for(depth_maps[i], image.shape[:2], scene, i)
        with single_thread():
            degraded, record = engine.view(i, image, depth)
        yield DegradedView(i, degraded, image, record)


# ------------------------------------------------------------------------------------------------ internals


def _per_view_thetas(theta: Theta | Sequence[Theta], n: int) -> list[Theta]:
    if isinstance(theta, Theta):
        return [theta] * n
    thetas = list(theta)
    if len(thetas) != n or not all(isinstance(t, Theta) for t in thetas):
        raise ConfigError(f"theta must be one Theta or one per view ({n}), got {len(thetas)} items")
    return thetas


def _clean_images(scene: SceneData) -> list:
    """Per view the image (array) or a loader of it (files are read when needed)."""
    if scene.images is not None:
        if len(scene.images) != len(scene):
            raise DataError(scene.source or "scene", f"{len(scene.images)} images for {len(scene)} views")
        return [np.asarray(im, dtype=np.float32) for im in scene.images]
    if scene.image_paths is None:
        raise DataError(scene.source or "scene", "the scene has no images (neither in memory nor as files)")
    return [lambda p=p: load_image(p) for p in scene.image_paths]


def _depth_for(depth: np.ndarray, hw: tuple[int, int], scene: SceneData, i: int) -> np.ndarray:
    """[H, W] float32 depth at the image size (nearest-neighbour resize), unknown → UNKNOWN_DEPTH."""
    import cv2

    d = np.asarray(depth, dtype=np.float32)
    if d.ndim == 3 and d.shape[2] == 1:
        d = d[..., 0]
    if d.ndim != 2:
        raise DataError(scene.source or "scene", f"depth of view {i} must be [H, W], got shape {list(d.shape)}")
    if d.shape != hw:
        d = cv2.resize(d, (hw[1], hw[0]), interpolation=cv2.INTER_NEAREST)
    return fill_unknown_depth(d)


def fill_unknown_depth(depth: np.ndarray) -> np.ndarray:
    """[H, W] depth with unknown pixels (non-finite or ≤ 0) given the depth of the nearest known pixel;
    a map without any known pixel becomes ``UNKNOWN_DEPTH`` (infinitely far) everywhere."""
    import cv2

    d = np.asarray(depth, dtype=np.float32)
    known = np.isfinite(d) & (d > 0)
    if known.all():
        return d.copy()
    if not known.any():
        return np.full(d.shape, UNKNOWN_DEPTH, np.float32)
    # DIST_LABEL_PIXEL labels every zero (known) pixel in raster order; each pixel gets its nearest one's label
    _, labels = cv2.distanceTransformWithLabels(
        (~known).astype(np.uint8), cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL
    )
    return d[known][labels - 1].astype(np.float32)


def _config(name: str, **fields):
    """Default config of the registered weather model ``name`` with the given fields set (when it has them)."""
    config = registry("weather").get(name)()
    known = {f.name for f in dataclasses.fields(config)}
    return dataclasses.replace(config, **{k: v for k, v in fields.items() if k in known})


class _Engine:
    """Builds the weather models once per distinct θ and degrades views with them."""

    def __init__(self, scene: SceneData, thetas: list[Theta], kinds: frozenset[str], seed: int, mpu: float, clean):
        self.scene, self.thetas, self.kinds, self.seed, self.mpu = scene, thetas, kinds, int(seed), mpu
        self.clean = clean
        self._groups: list[tuple[Theta, dict[str, WeatherModel], dict]] = []
        self._airlight: tuple[float, float, float] | None = None
        self._images_t: list[torch.Tensor] | None = None
        self._rasterizer = None
        self.settings = RenderSettings(background=(0.0, 0.0, 0.0))

    # --- shared state, built lazily -----------------------------------------------------------------------
    def _images(self) -> list[torch.Tensor]:
        if self._images_t is None:
            self._images_t = [torch.from_numpy(c() if callable(c) else c) for c in self.clean]
        return self._images_t

    def airlight(self) -> tuple[float, float, float]:
        """The airlight of every view: estimated once from all clean images (dark channel prior)."""
        if self._airlight is None:
            self._airlight = tuple(float(a) for a in estimate_airlight(self._images()))
        return self._airlight

    def rasterizer(self):
        if self._rasterizer is None:
            from metegs.render import make_rasterizer

            self._rasterizer = make_rasterizer("auto", "cpu")
        return self._rasterizer

    def models(self, theta: Theta) -> tuple[dict[str, WeatherModel], dict]:
        """Models (by stage name) and the θ record for ``theta``, built on first use."""
        for t, models, plain in self._groups:
            if t is theta or t == theta:
                return models, plain
        wscene = WeatherScene(
            cameras=self.scene.cameras,
            up=torch.as_tensor(np.asarray(self.scene.up, dtype=np.float32)),
            metres_per_unit=self.mpu,
            images=None,
            seed=self.seed,
        )
        configs = []
        rain_wanted = "rain" in self.kinds and theta.rain.active
        if rain_wanted:
            wscene.images = self._images()  # the drop colour is lit by each view's sky
            configs.append(_config("rain-streaks"))
        if "fog" in self.kinds or rain_wanted:  # rain beyond the streaks' reach acts as a veil (weather-physics.md)
            airlight = None if theta.fog.airlight_rgb is not None else self.airlight()
            configs.append(
                _config("fog-analytic", airlight=airlight, include_rain_veil="rain" in self.kinds, learnable=False)
            )
        if "drops" in self.kinds and theta.rain.active:  # θ_drops' count when it implies drops, else forced
            configs.append(_config("lens-droplets", force=True))
        built = build_weather_models(configs, theta, wscene) if configs else []
        models = {m.stage: m for m in built if m.active}
        plain = theta.to_dict()
        self._groups.append((theta, models, plain))
        return models, plain

    # --- one view -----------------------------------------------------------------------------------------
    @torch.no_grad()
    def view(self, i: int, image: np.ndarray, depth: np.ndarray) -> tuple[np.ndarray, dict]:
        theta = self.thetas[i]
        models, plain = self.models(theta)
        record = {
            "view": i,
            "name": self.scene.names[i] if i < len(self.scene.names) else str(i),
            "seed": self.seed,
            "kinds": "+".join(k for k in KINDS if k in self.kinds),
            "num_rain_gaussians": 0,
            "rain_coverage": 0.0,
            "fog": "medium" in models,
            "lens_drops": 0,
            "theta": copy.deepcopy(plain),
        }
        if not models:  # nothing called for: exactly the clean image
            return image.copy(), record
        rgb = torch.from_numpy(image).float()
        d = torch.from_numpy(depth)
        H, W = d.shape
        full = torch.ones(H, W)
        backdrop = RenderOutput(rgb, full, d, torch.zeros(0), torch.zeros(0, 2), 0, W, H)
        fog = models.get("medium")
        if fog is not None:
            rgb = fog.apply(rgb, backdrop, i, self.settings)
            record["fog_beta_rgb_per_m"] = [float(b) for b in fog.beta_rgb.detach()]
            record["airlight_rgb"] = [float(a) for a in fog.airlight.detach()]
        rain = models.get("gaussians")
        if rain is not None:
            rgb, n, coverage = self._rain(rain, fog, i, rgb, d)
            record["num_rain_gaussians"], record["rain_coverage"] = n, coverage
        lens = models.get("lens")
        if lens is not None:
            rgb = lens.apply(rgb, backdrop, i, self.settings)
            record["lens_drops"] = int(getattr(lens, "count", 0))
        return rgb.clamp(0.0, 1.0).numpy().astype(np.float32, copy=False), record

    def _rain(self, rain: WeatherModel, fog: WeatherModel | None, i: int, rgb: torch.Tensor, depth: torch.Tensor):
        """Composite view ``i``'s streaks over ``rgb`` (hidden behind the backdrop, fogged by the air in front)."""
        g = rain.gaussians_for(i)
        if g is None or len(g) == 0:
            return rgb, 0, 0.0
        cam = self.scene.cameras[i]
        H, W = depth.shape
        w2c = cam.world_to_cameras()[0].to(g.means)
        p = g.means @ w2c[:3, :3].T + w2c[:3, 3]
        z = p[:, 2]
        u = (cam.fx[0] * p[:, 0] / z.clamp_min(1e-9) + cam.cx[0]).floor().long()
        v = (cam.fy[0] * p[:, 1] / z.clamp_min(1e-9) + cam.cy[0]).floor().long()
        inside = (u >= 0) & (u < W) & (v >= 0) & (v < H)
        behind = torch.zeros_like(inside)
        behind[inside] = z[inside] > depth[v[inside], u[inside]]
        keep = ~behind
        g = type(g)(g.means[keep], g.quats[keep], g.scales[keep], g.opacities[keep], g.sh[keep])
        if len(g) == 0:
            return rgb, 0, 0.0
        out = self.rasterizer().render(g, cam, self.settings)
        visible = (out.depth <= depth).to(out.alpha)
        alpha = out.alpha * visible
        colour = out.rgb * visible[..., None]  # premultiplied (black background)
        if fog is not None:
            rays = ray_lengths(cam, H, W)
            t = torch.exp(-(out.depth * rays * self.mpu)[..., None] * fog.beta_rgb.detach())
            colour = colour * t + fog.airlight.detach() * alpha[..., None] * (1.0 - t)
        rgb = rgb * (1.0 - alpha[..., None]) + colour
        return rgb, int(len(g)), float(alpha.mean())
