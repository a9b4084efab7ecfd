"""Degrade the views of a scene with weather from θ, made by the registered weather models of the kinds asked for.

Every registered model says through `WeatherModelConfig.for_synthesis` whether and how it makes the kinds asked for
(``rain`` = `rain-streaks`, ``fog`` = `fog-analytic`, ``drops`` = `lens-droplets`, ``snow`` = the snow plugin ...).
For each view the photo is treated as a backdrop at its depth map (z along the optical axis, scene units):

1. media (``fog-analytic``: ``C = I·t + A·(1 − t)``, ``t = exp(−β·d)``, d the ray length to the backdrop in
   metres; the fog of rain+fog includes the rain's own veil); pixels of unknown depth (non-finite or ≤ 0, e.g.
   where a trained run renders nothing) take the depth of the nearest known pixel (a view without any known depth
   is infinitely far: airlight);
2. world-space weather (rain streaks, snowflakes): that view's Gaussians of every such model (seeded per view) are
   rasterised together, alone, and composited over the fogged photo; a Gaussian behind the backdrop is hidden (its
   mean is culled when it lies behind the depth at its pixel, and pixels whose rendered depth lies behind the
   backdrop are masked), and the air between the camera and the Gaussian fogs it like everything else;
3. lens effects (``lens-droplets``, only when asked for), last.

The medium (β, airlight) is the same in every view: the airlight is estimated once from all clean images
(unless θ gives it), so two views of one point agree on its fog; rain and snow are drawn anew for every view.
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
from metegs.gaussians.model import GaussianSet
from metegs.meteo.mapping import Theta
from metegs.registry import registry
from metegs.render.base import RenderOutput, RenderSettings
from metegs.render.cpu_backend import single_thread
from metegs.weather.airlight import estimate_airlight
from metegs.weather.base import SynthesisRequest, WeatherModel, WeatherScene
from metegs.weather.compose import build_weather_models
from metegs.weather.kinds import join_kinds, parse_kinds

FAMILIES = ("physical", "independent")
"""Degradation families: the registered weather models from θ (metegs's own and plugins'), or
`metegs.weather.independent` (rain, fog and drops made without them: a benchmark that the method cannot fit with its
own generator)."""

INDEPENDENT_KINDS = frozenset({"rain", "fog", "drops"})
"""The kinds the independent family makes."""

UNKNOWN_DEPTH = 1e9
"""Depth (scene units) given to pixels whose depth is unknown: far beyond any fog's reach."""


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
        kinds: registered weather kinds joined with ``+`` (`metegs.weather.kinds`): ``rain``, ``fog``, ``rain+fog``,
            a plugin's (``snow+fog``); ``+drops`` adds lens drops when it rains (θ_drops' count, or the lens model's
            forced default when θ_drops has none).
        seed: seed of every random choice (view v's rain, snow and lens drops are seeded from (seed, v)).
        metres_per_unit: length of a scene unit in metres; None: ``scene.metric_scale`` or 1.0.
        depths: per view [H, W] depth (z along the optical axis, scene units; non-finite or ≤ 0 where unknown,
            filled from the nearest known pixel); None: ``scene.depths``.
        family: ``physical`` or ``independent`` (see `iter_degraded_views`).

    Returns:
        (scene copy, records): the copy's ``images`` are the degraded views (float32 [H, W, 3] in memory) and its
        points' colours are read from them (`metegs.data.point_colours.colours_seen`); its ``clean_images`` are
        the original images (``image_paths``/``clean_image_paths`` are None: the arrays
        are authoritative); one record per view for weather.json (view, name, seed, kinds, θ.to_dict(), the
        number of weather Gaussians (rain, snow) drawn, per model and in all, and their visible coverage, and each
        medium's summary, e.g. the fog's β per channel and airlight).
    """
    images, cleans, records = [], [], []
    for view in iter_degraded_views(
        scene, theta, kinds=kinds, seed=seed, metres_per_unit=metres_per_unit, depths=depths, family=family
    ):
        images.append(view.image)
        cleans.append(view.clean)
        records.append(view.record)
    colours = scene.point_colors
    if scene.points is not None and len(scene.points):  # what the degraded photos show, not the clean ones
        from metegs.data.point_colours import colours_seen

        colours = colours_seen(scene.points, scene.cameras, images, depths if depths is not None else scene.depths)
    out = dataclasses.replace(
        scene, images=images, clean_images=cleans, image_paths=None, clean_image_paths=None, point_colors=colours
    )
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
    ``family``: ``physical`` (the registered weather models from θ) or ``independent``
    (`metegs.weather.independent`: rain, fog and drops made without them, from θ's met conditions only)."""
    wanted = parse_kinds(kinds)
    if family == "independent" and wanted - INDEPENDENT_KINDS:
        raise ConfigError(
            f"kinds={kinds!r}: the independent family makes {', '.join(sorted(INDEPENDENT_KINDS))} only; "
            f"{', '.join(sorted(wanted - INDEPENDENT_KINDS))} needs the physical family (its registered model)"
        )
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


class _Engine:
    """Builds the weather models once per distinct θ and degrades views with them."""

    def __init__(self, scene: SceneData, thetas: list[Theta], kinds: frozenset[str], seed: int, mpu: float, clean):
        self.scene, self.thetas, self.kinds, self.seed, self.mpu = scene, thetas, kinds, int(seed), mpu
        self.clean = clean
        self._groups: list[tuple[Theta, dict[str, list[WeatherModel]], dict]] = []
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

    def models(self, theta: Theta) -> tuple[dict[str, list[WeatherModel]], dict]:
        """Active models by stage (``gaussians``, ``medium``, ``lens``) and the θ record for ``theta``, built on first use."""
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
        request = SynthesisRequest(self.kinds, theta, self.airlight)
        configs = [c for e in registry("weather").entries() if (c := e.load()().for_synthesis(request)) is not None]
        wscene.images = self._images()  # drop and flake colours are lit by each view's sky
        built = build_weather_models(configs, theta, wscene) if configs else []
        models = {
            stage: [m for m in built if m.active and m.stage == stage] for stage in ("gaussians", "medium", "lens")
        }
        plain = theta.to_dict()
        self._groups.append((theta, models, plain))
        return models, plain

    # --- one view -----------------------------------------------------------------------------------------
    @torch.no_grad()
    def view(self, i: int, image: np.ndarray, depth: np.ndarray) -> tuple[np.ndarray, dict]:
        theta = self.thetas[i]
        models, plain = self.models(theta)
        media = models["medium"]
        record = {
            "view": i,
            "name": self.scene.names[i] if i < len(self.scene.names) else str(i),
            "seed": self.seed,
            "kinds": join_kinds(self.kinds),
            "num_rain_gaussians": 0,
            "rain_coverage": 0.0,
            "fog": bool(media),
            "lens_drops": 0,
            "theta": copy.deepcopy(plain),
        }
        if not any(models.values()):  # nothing called for: exactly the clean image
            return image.copy(), record
        rgb = torch.from_numpy(image).float()
        d = torch.from_numpy(depth)
        H, W = d.shape
        backdrop = RenderOutput(rgb, torch.ones(H, W), d, torch.zeros(0), torch.zeros(0, 2), 0, W, H)
        for medium in media:
            rgb = medium.apply(rgb, backdrop, i, self.settings)
            if (summary := medium.summary()) is not None:
                record[medium.name] = summary  # e.g. the fog's β per channel and airlight
        if models["gaussians"]:
            rgb, counts, coverage = self._gaussians(models["gaussians"], media, i, rgb, d)
            record["num_rain_gaussians"], record["rain_coverage"] = sum(counts.values()), coverage
            record["gaussians_per_model"] = counts
        for lens in models["lens"]:
            rgb = lens.apply(rgb, backdrop, i, self.settings)
            record["lens_drops"] += int(getattr(lens, "count", 0))
        return rgb.clamp(0.0, 1.0).numpy().astype(np.float32, copy=False), record

    def _gaussians(
        self, models: list[WeatherModel], media: list[WeatherModel], i: int, rgb: torch.Tensor, depth: torch.Tensor
    ) -> tuple[torch.Tensor, dict[str, int], float]:
        """Composite view ``i``'s weather Gaussians of every model over ``rgb`` (hidden behind the backdrop, fogged by
        the media in front) -> (image, visible Gaussians per model, their mean coverage)."""
        cam = self.scene.cameras[i]
        H, W = depth.shape
        w2c = cam.world_to_cameras()[0]
        sets, counts = [], {}
        for m in models:
            g = m.gaussians_for(i)
            if g is None or len(g) == 0:
                counts[m.name] = 0
                continue
            p = g.means @ w2c[:3, :3].to(g.means).T + w2c[:3, 3].to(g.means)
            z = p[:, 2]
            u = (cam.fx[0] * p[:, 0] / z.clamp_min(1e-9) + cam.cx[0]).floor().long()
            v = (cam.fy[0] * p[:, 1] / z.clamp_min(1e-9) + cam.cy[0]).floor().long()
            inside = (u >= 0) & (u < W) & (v >= 0) & (v < H)
            behind = torch.zeros_like(inside)
            behind[inside] = z[inside] > depth[v[inside], u[inside]]
            keep = ~behind
            sets.append(type(g)(g.means[keep], g.quats[keep], g.scales[keep], g.opacities[keep], g.sh[keep]))
            counts[m.name] = int(keep.sum())
        sets = [g for g in sets if len(g) > 0]
        if not sets:
            return rgb, counts, 0.0
        out = self.rasterizer().render(GaussianSet.cat(sets) if len(sets) > 1 else sets[0], cam, self.settings)
        visible = (out.depth <= depth).to(out.alpha)
        alpha = out.alpha * visible
        colour = out.rgb * visible[..., None]  # premultiplied (black background)
        for medium in media:  # the air between the camera and the layer
            colour = medium.seen_through(colour, alpha, out.depth, i)
        rgb = rgb * (1.0 - alpha[..., None]) + colour
        return rgb, counts, float(alpha.mean())
