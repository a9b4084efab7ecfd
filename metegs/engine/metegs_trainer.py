"""The MeteGS dual-branch trainer.

Weather branch: GTN(G_s, view) ∪ G_w(θ) rendered in one rasterisation, then the medium and lens effects,
fit to the observed (degraded) photo with (1−λ)·L1 + λ·(1−SSIM) plus the weather's coverage prior.
Clean branch: G_s alone against the clean reference (the same L1 + SSIM and a perceptual loss) when references exist.
Evaluation, renders and export use the clean branch only.
"""

from __future__ import annotations

import functools
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from metegs.engine.metegs_config import BLURRED_PRUNE_OPACITY, SHARP_PRUNE_OPACITY, MeteGSConfig
from metegs.engine.optim import adam
from metegs.engine.run import surface_depth
from metegs.engine.trainer import StepRender, Trainer
from metegs.errors import ConfigError
from metegs.eval.veil import photo_veil
from metegs.eval.view_spread import EVEN_SPREAD_RATIO, SPARSE_STREAKS_RATIO, quantile_from_spread, view_spread
from metegs.gaussians.model import GaussianModel
from metegs.gaussians.sh import rgb_to_sh
from metegs.losses.dark_channel import dark_channel_loss
from metegs.losses.photometric import box_detail
from metegs.losses.robust import (
    LOW_QUANTILE,
    THIN_STREAK_PX,
    VEILED_QUANTILE,
    inlier_weights,
    stroke_energy,
    stroke_width_px,
    thin_strokes,
    without_bright_strokes,
)
from metegs.meteo.physics import LN20
from metegs.models.gtn import may_be_visible
from metegs.render import RenderSettings
from metegs.weather.airlight import typical_airlight
from metegs.weather.base import WeatherModel, WeatherScene, model_seed
from metegs.weather.compose import render_with_weather
from metegs.weather.conditions import LIGHT_OR_NONE, rain_phrase
from metegs.weather.fog_analytic import FogAnalytic
from metegs.weather.kinds import kind_of
from metegs.weather.learnable import LearnableTransients
from metegs.weather.medium import (
    MEASURABLE_DISTANCE_SPREAD,
    VISIBLE_CONTRAST_LOSS,
    distance_spread,
    typical_depth_m,
    veil_fraction,
)
from metegs.weather.medium_fit import (
    MediumFit,
    PointObservations,
    airlight_under_haze,
    fit_medium,
    fit_uniform_medium,
    point_observations,
    veil_evidence,
)

DENSE_OPTICAL_DEPTH = LN20 / 3
"""Optical depth β·d above which fog is dense at depth d: its visibility (the meteorological optical range, where
the contrast falls to 5 %) is at most 3× d. Opacity resets stay off there when the Gaussians start from an SfM
cloud (blind, heavy rain and 200 m fog on the Lund street: 13.43 dB without them against 9.87 with them, 12.08
against 10.37 under the independent family); from random points they clear floaters and stay on (the Ethiopian
head, independent family: 15.58 dB with them, 15.11 without)."""

MIN_SPREAD_POINTS = 200
"""Points seen by 6 or more views under which `_choose_quantile` keeps `LOW_QUANTILE` (the Lund street at 3DGS's
step 300: 698)."""

MEASURED_POINTS = 2048
"""Most starting points at which the photos' fog is measured (`_measured_medium`; evenly spread over the cloud)."""

MIN_MEASURED_POINTS = 100
"""Fewest points seen from distances `MEASURABLE_DISTANCE_SPREAD` times apart from which the photos' measure of the
fog is trusted."""

MIN_MEDIUM_EXPLAINED = 0.05
"""Share of clear air's robust loss at the scene's points that a uniform medium must explain (`MediumFit.explained`)
for blind training to hold β at that measure, and for the dark-channel prior's airlight to take their fit
(`_dehazing_airlight`); under it the veil is too thin to measure there and β learns in training. Fog: 14-51 % (the
built-in scene, the Lund street, the fox); thin veils 0.4-2.4 %, whose measure missed (the fox's rain veil: 1.63e-3/m
against 2.45e-3, 25.30 dB held there, 29.70 learnt in training)."""

MIN_VEIL_Z = 2.0
"""How many standard errors better than clear air the rain's veil must explain the colours at the scene's points
(`veil_evidence`) for a medium to model it where the record gives no visibility: metegs's own heavy rain, 7.0 on the
fox and 31 on the built-in scene; streaks without a veil −0.2 to 4.8 (the photos' exposures differing), clear
photos −16 to 2.9."""

MIN_AIRLIGHT_OUTSHINES = 0.9
"""Share of the colours at the scene's points that the rain's veil's fitted airlight must outshine, as scattered
daylight outshines nearly every surface it veils: 0.98-1.0 under metegs's own heavy rain (the built-in scene, the
fox); 0.56-0.74 where there is no veil and a fitted one takes the scene's middle grey for airlight."""

PERCEPTUAL_CACHE_MB = 512
"""Largest memory the clean references' perceptual features may take when cached for the whole run."""


BLIND_STREAKS = (
    "blind, per-view learnable streaks fitted the photos' rain no better than the robust mask and the low-quantile "
    "fit alone (twelve rain cells of three real captures: 0.20 dB more on average without them)"
)
"""Why blind training leaves rain's learnable streaks out (docs/benchmark.md, "A third generator")."""


class MeteGSTrainer(Trainer):
    """Scene Gaussians fit through the weather branch and, with clean references, the clean branch."""

    config: MeteGSConfig
    _coloured_from_points = False
    """Whether this run's Gaussians started from the scene's or triangulated points (`_clear_start_colours`)."""

    # --- setup -------------------------------------------------------------------------------------
    def weather_kinds(self) -> set[str]:
        """The kinds of the `weather` models (rain, fog; a plugin's such as snow); rain and fog in the ablation without
        a weather branch."""
        if not self.config.weather_branch:
            return {"rain", "fog"}
        from metegs.weather.kinds import kind_of

        return {kind_of(name) for name in self.config.weather}

    def setup_method(self) -> None:
        c = self.config
        has_clean = self.dataset.clean_images is not None
        self.use_clean = has_clean and c.clean_supervision
        self.dehazing: list[WeatherModel] = []
        """The media the dark-channel prior holds (`_decide_dark_channel`)."""
        self.medium_optical_depth = 0.0
        """Largest optical depth β·d of a weather model's medium at the scene's typical depth d (0: none)."""
        self.active_kinds: set[str] = set()
        """Kinds of the weather that the photos show and the run takes out (rain, fog, ...; `_build_weather`): those
        of the weather models that are on, and blind rain above light, whose learnable streaks stay off."""
        self.weather_models: list[WeatherModel] = self._build_weather() if c.weather_branch else []
        if not c.weather_branch:
            self.decide("weather", "off (ablation): the scene alone fits the degraded photos")
        self.gtn = self._build_gtn()
        if not has_clean:
            self.decide("clean branch", "off: the scene has no clean references (blind mode)")
        elif not c.clean_supervision:
            self.decide("clean branch", "off: --clean-supervision False (blind mode)")
        else:
            self.decide(
                "clean branch", f"on: 3dgs's L1 + SSIM against the clean references, weight {c.weights.clean:g}"
            )
        self._clear_start_colours()
        self.pseudo_references = self._restore_training_photos()
        """Training view -> its photo restored in 2D [H, W, 3] (`pseudo_references`; empty: off)."""
        self.perceptual = self._build_perceptual()
        self._setup_robust()
        self._feature_cache: dict[int, list[dict[str, torch.Tensor]]] = {}
        self._setup_extra_points()
        self._setup_camera_clearance()
        self.method_optimizers = self._method_optimizers()

    def _triangulation_photos(self) -> tuple[list[Path] | None, list[torch.Tensor], str]:
        """The clean references where the clean branch trains on them: rain streaks, drops and haze take the
        features that triangulation matches (the independent family's heavy rain on the Ethiopian head: 37 points
        from the photos, 3000 and more from the clean references), and a run that is given the clean photos is
        expected to start from their points as 3DGS on them does."""
        paths = self.scene.clean_image_paths
        if self.config.clean_supervision and paths is not None:
            return paths, self.dataset.clean_images, "clean references"
        return super()._triangulation_photos()

    def _initial_model(self) -> GaussianModel:
        model = super()._initial_model()
        self._coloured_from_points = not self.random_init
        return model

    def _clear_start_colours(self) -> None:
        """Recolour the points this run started from (not a checkpoint's, not random ones) by the scene without its
        weather (`MeteGSConfig.clear_start_colours`): SfM colours are the photos', fog and rain veil included, and a
        hazed start is slow to leave (3000 steps on Lund's 200 m fog: 12.28 dB from the photos' colours, 13.05 from
        these)."""
        if not self._coloured_from_points:
            return
        if not self.config.clear_start_colours:
            self.decide("start colours", "the photos' (--no-clear-start-colours)")
            return
        from metegs.data.point_colours import colours_seen

        ds, views = self.dataset, self.dataset.train_indices
        cameras = ds.cameras[views].to("cpu")
        depths = None if ds.depths is None else [ds.depths[i].cpu().numpy() for i in views]
        means = self.model.params["means"].detach()
        if self.use_clean:
            colours = colours_seen(
                means.cpu().numpy(), cameras, [ds.clean_images[i].cpu().numpy() for i in views], depths
            )
            self.decide("start colours", f"the clean references' ({len(views)} training views)")
        else:
            media = [m for m in self.weather_models if m.active and m.transmittance(means[:1], views[0]) is not None]
            lit = [m for m in media if isinstance(getattr(m, "airlight", None), torch.Tensor)]
            if not lit:
                self.decide("start colours", "the photos': no medium between the cameras and the scene")
                return

            def transmittance(k: int) -> np.ndarray:
                with torch.no_grad():
                    t = torch.ones(len(means), device=means.device)
                    for medium in media:
                        t = t * medium.transmittance(means, views[k])
                return t.cpu().numpy()

            airlight = lit[0].airlight.detach().cpu().numpy()
            images = [ds.images[i].cpu().numpy() for i in views]
            colours = colours_seen(
                means.cpu().numpy(), cameras, images, depths, transmittance=transmittance, airlight=airlight
            )
            names = " + ".join(m.name for m in media)
            self.decide("start colours", f"the photos' with the {names} medium taken out along each point's distance")
        with torch.no_grad():
            sh0 = self.model.params["sh0"]
            sh0[:, 0] = rgb_to_sh(torch.from_numpy(colours)).to(sh0)

    def _setup_robust(self) -> None:
        """The robust mask (`robust_from`) where rain heavier than light falls, and with it the low quantile of a
        pixel's photos that its L1 fits (`RobustMaskConfig.quantile`) and the strokes D-SSIM does not see
        (`stroke_width`)."""
        c, r = self.config, self.config.robust
        rain = self.weather_theta(self.scene).rain
        wanted = r.enabled and rain.intensity_class not in LIGHT_OR_NONE
        self.robust_from = int(round(r.start * c.max_steps)) if wanted else None
        """Step from which the weather branch's photometric loss is trimmed to inliers (None: never)."""
        self.stroke_width = 1
        """Width of the square that takes bright strokes out of D-SSIM's pair in the low-quantile fit (1: none)."""
        self.quantile = 0.5
        """Quantile of a pixel's photos that the trimmed L1 fits (0.5: the median; `RobustMaskConfig.quantile`)."""
        self._quantile_reason = ""
        """What chose `quantile`, if not the record's rain alone (`_decide_quantile`)."""
        self._quantile_pending = False
        """Whether the quantile is still to be chosen from how the photos spread about a point's median
        (`_choose_quantile`, at `robust_from`)."""
        self.thin_width = 1
        """Width under which a photo's bright stroke is thin enough to be trimmed (`RobustMaskConfig.thin_only`; 1:
        any outlier is)."""
        self._thin: dict[int, torch.Tensor] = {}
        """Training view -> its photo's `thin_strokes` [H, W] (`_thin_strokes`)."""
        if not r.enabled:
            self.decide("robust mask", "off")
            return
        if not wanted:
            self.decide(
                "robust mask",
                f"off: {rain_phrase(rain)} leaves no streak bright enough to stand out, so trimming would only drop "
                "the scene's hardest pixels",
            )
            return
        seen = ""
        if r.min_stroke_energy > 0:
            energy = self._photos_stroke_energy()
            strokes = f"their thin bright strokes of one orientation hold {energy:.4f} of energy"
            if energy < r.min_stroke_energy:
                self.robust_from = None
                self.decide(
                    "robust mask",
                    f"off: the photos do not show the streaks of {rain_phrase(rain)} ({strokes}, under "
                    f"{r.min_stroke_energy:g}): the weather models take what shows of it, and trimming the "
                    "photos' brightest pixels would dim the scene (--robust.min-stroke-energy 0: the record alone "
                    "decides)",
                )
                return
            seen = f", as the photos show streaks ({strokes})"
        longer = max(max(size) for size in self.dataset.sizes)
        if r.thin_only and (streak := stroke_width_px(THIN_STREAK_PX, longer)) > 1:
            self.thin_width = 2 * streak - 1
            seen += f"; only the photo's bright strokes under {self.thin_width} px wide (a streak, not a highlight)"
        self.decide(
            "robust mask",
            f"on from step {self.robust_from}: pixels {'brighter' if r.brighter_only else 'further'} than "
            f"{r.k_sigma:g} robust sigmas of their view's residuals (grown by {r.dilate_px} px) are left out{seen}",
        )
        veiled = r.quantile is None and bool(self.dehazing)
        self._low_quantile = VEILED_QUANTILE if veiled else LOW_QUANTILE
        """The quantile the trimmed L1 fits where rain brightens most of a point's photos (`_choose_quantile`)."""
        self._quantile_pending = r.quantile is None
        if r.quantile is not None:
            self._decide_quantile(r.quantile, "--robust.quantile")
        else:
            self._decide_quantile(
                self._low_quantile,
                f"until step {self.robust_from}, where the photos' spread about a point's median says whether their "
                "median or this quantile is nearer the clear scene",
            )

    def _decide_quantile(self, quantile: float, reason: str) -> None:
        """Fit ``quantile`` of a pixel's photos in the trimmed L1 and say why (``reason``: what chose it, if not the
        record's rain alone), with the strokes D-SSIM then leaves out (`stroke_width`)."""
        r, rain = self.config.robust, self.weather_theta(self.scene).rain
        self.quantile, self.stroke_width, self._quantile_reason = quantile, 1, reason
        if quantile == 0.5:
            self.decide("low-quantile fit", f"off: {reason} (the L1 fits the median of a pixel's photos)")
            return
        why = (
            f"on: the trimmed L1 fits the {quantile:.0%} quantile of a pixel's photos, not their median: "
            f"{rain_phrase(rain)} brightens nearly every pixel a little, and rain only adds light"
        )
        if self._low_quantile == VEILED_QUANTILE and r.quantile is None:
            why += (
                f" ({quantile:.0%}, not {LOW_QUANTILE:.0%}: the dark-channel prior holds the medium, whose "
                "veil takes the even part of that light, and a lower fit would darken the scene a second time)"
            )
        if reason:
            why += f"; {reason}"
        if r.ssim_lambda is not None:
            why += f"; D-SSIM at weight {r.ssim_lambda:g} (--robust.ssim-lambda)"
        longer = max(max(size) for size in self.dataset.sizes)
        self.stroke_width = stroke_width_px(r.stroke_px, longer)
        if self.stroke_width > 1:
            why += (
                f"; D-SSIM without the bright strokes under {self.stroke_width} px wide and {r.min_excess:g} over "
                "their surroundings, in the photo or the render (the photo's streaks, which the render would fake "
                "by darkening between them)"
            )
        elif r.stroke_px > 0:
            why += f"; streaks are under 2 px wide at {longer} px, so D-SSIM sees render and photo as they are"
        self.decide("low-quantile fit", why)

    def _choose_quantile(self) -> None:
        """At `robust_from`, blind of the clear scene: how far above a point's median its photos spread against how far
        below (`metegs.eval.view_spread`, at the surfaces the run's Gaussians render at that step) moves the quantile
        from `LOW_QUANTILE` (or, where the dark-channel prior holds the medium, `VEILED_QUANTILE`) towards the median
        (`quantile_from_spread`)."""
        self._quantile_pending = False
        ds, views = self.dataset, list(self.dataset.train_indices)
        with self.status("reading how the photos spread about the scene's points"), torch.no_grad():
            scene = self.model.activated()
            depths = [surface_depth(self.rasterizer, scene, ds.cameras[i]) for i in views]
            spread = view_spread(ds.cameras[views], [ds.images[i] for i in views], depths, seed=self.config.seed)
        low = self._low_quantile
        if spread.points < MIN_SPREAD_POINTS:
            self._decide_quantile(low, f"{spread.points} points seen by 6 or more views, too few to read the photos")
            return
        quantile = quantile_from_spread(spread.ratio, low)
        said = (
            f"at {spread.points} points seen by 6 or more views the photos spread {spread.ratio:.2f} times as far above "
            f"a point's median as below it ({spread.above:.3f} against {spread.below:.3f}, medians over the points)"
        )
        if quantile == 0.5:
            said += (
                f", {SPARSE_STREAKS_RATIO:g} or more: the streaks reach too few of a point's views to brighten the "
                "median of its photos, which a lower fit would darken"
            )
        elif quantile == low:
            said += f", up to {EVEN_SPREAD_RATIO:g}, as evenly as in clear weather: rain brightens most of them"
        else:
            said += (
                f", between {EVEN_SPREAD_RATIO:g} and {SPARSE_STREAKS_RATIO:g}: the streaks reach only some of a "
                f"point's views, so the fit lies that far from {low:.0%} towards the median"
            )
        self._decide_quantile(quantile, said)

    def _thin_strokes(self, index: int) -> torch.Tensor | None:
        """[H, W] bool: the pixels of view ``index``'s photo that the robust mask may trim (`thin_strokes`, found once
        per view), or None where any outlier may be."""
        if self.thin_width <= 1:
            return None
        if index not in self._thin:
            photo = self.dataset.images[index]
            self._thin[index] = thin_strokes(photo, self.thin_width, self.config.robust.min_excess)
        return self._thin[index]

    def _sampled_photos(self, most: int = 16) -> list[torch.Tensor]:
        """Up to ``most`` training photos [H, W, 3], evenly spread over the training views: what the run asks of the
        photos before training (`_photos_stroke_energy`, `_photos_veil`)."""
        views = self.dataset.train_indices
        return [self.dataset.images[i] for i in views[:: max(1, -(-len(views) // most))]]

    def _photos_stroke_energy(self) -> float:
        """Median `stroke_energy` of the `_sampled_photos`."""
        return float(np.median([stroke_energy(photo) for photo in self._sampled_photos()]))

    def _photos_veil(self, airlight: torch.Tensor) -> float:
        """Median `photo_veil` of the `_sampled_photos` under ``airlight`` [3]."""
        return float(np.median([photo_veil(photo, airlight) for photo in self._sampled_photos()]))

    def _rain_veil_unseen(self, beta: float) -> str | None:
        """Blind, where the record gives no visibility, so that its medium of ``beta`` (1/m over clear air) is the
        rain's veil, and the views see the scene's points from distances far enough apart (`_views_measure_medium`):
        why the photos show no such veil, else None. A veil must explain the colours at the points better than clear
        air by `MIN_VEIL_Z` standard errors, under an airlight brighter than `MIN_AIRLIGHT_OUTSHINES` of them
        (`veil_evidence`): without a veil, a fitted one takes the scene's middle grey for airlight. Streaks drawn
        without a veil fooled the dark channel on the built-in scene (its grey ground reads as 10 % of veil in clear
        air), and a learnt veil cost 8 dB there."""
        theta = self.weather_theta(self.scene)
        if self.use_clean or theta.fog.visibility_m is not None or not self._views_measure_medium[0]:
            return None
        if (obs := self._medium_observations) is None:
            return None
        with self.status("testing the rain's veil at the scene's points"):
            evidence = veil_evidence(obs, beta)
        if evidence.z >= MIN_VEIL_Z and evidence.brighter >= MIN_AIRLIGHT_OUTSHINES:
            return None
        weak = f", under {MIN_VEIL_Z:g}" if evidence.z < MIN_VEIL_Z else ""
        grey = f", under {MIN_AIRLIGHT_OUTSHINES:.0%}" if evidence.brighter < MIN_AIRLIGHT_OUTSHINES else ""
        return (
            f"the record gives no visibility, so its β {beta:.2e}/m over clear air is the veil of "
            f"{rain_phrase(theta.rain)}; at {len(torch.unique(obs.point))} of the scene's points "
            f"({self._views_measure_medium[1]}) that veil explains {evidence.explained:.1%} of the colour differences "
            f"that clear air leaves (z {evidence.z:.1f}{weak}) under an airlight brighter than {evidence.brighter:.0%} "
            f"of them{grey}: the photos show no veil of the rain"
        )

    def _build_weather(self) -> list[WeatherModel]:
        from metegs.weather.conditions import describe, scene_metres_per_unit

        c, ds = self.config, self.dataset
        theta = self.weather_theta(self.scene)
        self.decide("conditions", describe(theta))
        scene = WeatherScene(
            cameras=ds.cameras,
            up=torch.as_tensor(self.scene.up, dtype=torch.float32, device=self.device),
            metres_per_unit=scene_metres_per_unit(c.conditions, self.scene.metric_scale),
            images=ds.images,
            seed=model_seed(c.seed),
        )
        built, depth_m, shown_veil = [], None, {}
        for name in c.weather:
            config = c.weather_config(name)
            model = config.setup(theta=theta, scene=scene).to(self.device)
            if not model.active:
                self.decide(f"weather {name}", "off: the weather does not call for it")
                continue
            beta = getattr(model, "extinction_per_m", None)
            if beta is not None:  # the clean photos' own clear air is no weather: what the weather adds must show
                beta = max(beta - theta.fog.beta_background_per_m, 0.0)
                if depth_m is None:
                    depth_m = typical_depth_m(ds.cameras, self.scene.points, scene.metres_per_unit)
                veil = veil_fraction(beta, depth_m)
                if veil < VISIBLE_CONTRAST_LOSS:
                    self.decide(
                        f"weather {name}",
                        f"off: at β {beta:.2e}/m over clear air the weather takes {veil:.1%} of the contrast at "
                        f"the scene's typical depth ({depth_m:.0f} m), under the {VISIBLE_CONTRAST_LOSS:.0%} a person "
                        "notices: the photos cannot tell it from the surfaces' colours; removing it could only bias them",
                    )
                    continue
                shown = self._photos_veil(model.airlight.detach()) if c.min_photo_veil > 0 else None
                if shown is not None and shown < c.min_photo_veil:
                    self.decide(
                        f"weather {name}",
                        f"off: the record's β {beta:.2e}/m over clear air would take {veil:.0%} of the contrast at the "
                        f"scene's typical depth ({depth_m:.0f} m), but the photos' darkest patches show {shown:.1%} "
                        f"of veil, under {c.min_photo_veil:.0%}: they show no medium (--min-photo-veil 0: the record "
                        "decides)",
                    )
                    continue
                if c.min_photo_veil > 0 and (unseen := self._rain_veil_unseen(beta)) is not None:
                    self.decide(f"weather {name}", f"off: {unseen} (--min-photo-veil 0: the record decides)")
                    continue
                if shown is not None:
                    shown_veil[name] = f": the photos' darkest patches show {shown:.1%} of veil"
                self.medium_optical_depth = max(self.medium_optical_depth, beta * depth_m)
            if isinstance(model, FogAnalytic):
                self._decide_record_prior(name, model)
            built.append((name, model))
        sharp = self._blind_sharp_weather([m for _, m in built])
        models = []
        for name, model in built:
            if getattr(model, "transient", False):
                if not self.use_clean and kind_of(name) == "rain":
                    self.decide(f"weather {name}", "off: " + (f"{sharp}; " if sharp else "") + BLIND_STREAKS)
                    if sharp is None:  # the photos still show the rain: the 2D restorers take it out
                        self.active_kinds.add(kind_of(name))
                    continue
                model = LearnableTransients(model, list(ds.train_indices), c.learnable_weather)
                count = sum(len(v.means) for v in model.views.values()) / max(len(model.views), 1)
                self.decide(f"weather {name}", f"on: {count:.0f} learnable Gaussians per training view")
            else:
                self.decide(f"weather {name}", "on" + shown_veil.get(name, ""))
            self.active_kinds.add(kind_of(name))
            models.append(model)
        return models

    def _restore_training_photos(self) -> dict[int, torch.Tensor]:
        """Each training photo restored in 2D by the restorers of the active weather's rain and fog
        (`pseudo_references`), or {} where that is off or the run has clean references."""
        if self.config.pseudo_references == "off":
            return {}
        if self.use_clean:
            self.decide("pseudo references", "off: the clean references hold the clean branch")
            return {}
        kinds = "+".join(k for k in ("rain", "fog") if k in self.active_kinds)
        if not kinds:
            self.decide("pseudo references", "off: no rain or fog model is on, so there is nothing to restore")
            return {}
        from metegs.restore import restorer_for_kinds
        from metegs.restore.cache import cached_restore, restored_cache_dir

        restorer = restorer_for_kinds(kinds)
        views = list(self.dataset.train_indices)
        restored, cached = {}, 0
        with self.status("") as shown:
            for n, i in enumerate(views):
                if shown is not None:
                    shown.update(f"restoring the training photos in 2D ({restorer.name}): {n}/{len(views)}")
                photo = self.dataset.images[i].detach().cpu().numpy()
                result = cached_restore(restorer, photo)
                restored[i] = torch.from_numpy(result.image).to(self.device)
                cached += result.cached
        width = self.config.pseudo_detail_px
        held = f"detail (x - its {width | 1}-px box mean)" if width > 0 else "colours"
        self.decide(
            "pseudo references",
            f"on: the clean branch's {held} is held to the {len(views)} training photos restored by {restorer.name} "
            f"({cached} read from {restored_cache_dir()}; L1 weight {self.config.weights.pseudo})",
        )
        return restored

    def _decide_record_prior(self, name: str, fog: FogAnalytic) -> None:
        """What sets ``fog``'s β where the photometric fit alone cannot: ``auto`` asks if the views see the scene's
        (initial) points over distances far enough apart for the photos to measure β (`MEASURABLE_DISTANCE_SPREAD`;
        unknown, so not, from random points or a sweep where triangulation failed); where they are not, or the fog is
        dense (rain or not) and the points do not measure it, blind training holds it by the dark-channel prior
        (`_decide_dark_channel`), training with clean references (or with that prior off) near the met record's. Blind
        under rain heavier than light through dense fog that the points do measure, the record holds it
        (`_rain_through_dense_fog`). Elsewhere blind, where they are, the photos' colours at the starting points measure
        it (`_measured_medium`), and where that measure explains enough of them (`MIN_MEDIUM_EXPLAINED`) the prior holds
        it there: left free, it drifts while the Gaussians take the haze in (the fox in metegs's own 200 m fog: from the
        exact 0.0150/m to 0.011 within 1000 steps, 17.34 dB; held at the measure of 0.0153, 24.16). Under the
        dark-channel prior, or beside clean references where the views do not measure β, a per-view grid scales the
        optical depth (`FogAnalytic.learn_patches`), but not blind in the rain's veil alone (no visibility in the
        record), where it takes in the rain's light: the Ethiopian head's blind heavy rain gained 0.56-0.67 dB without
        it (metegs's own, two seeds) and 0.17-0.27 (the independent family's). Under that prior, where rain heavier than
        light falls through the record's fog and the views see the scene from about one distance
        (`_rain_through_fog_seen_from_one_distance`), neither the grid nor β's height profile learns: they take each
        view's rain light for fog (the Ethiopian head, blind, 3000 steps: a uniform fog 15.52 ± 0.15 dB over three seeds
        under the independent rain + fog against 14.91 ± 0.40, 22.23 against 21.61 under metegs's own), where the fox's
        views, 2.15x apart, measure them (18.26 dB with both, 15.37 uniform)."""
        if not fog.log_beta.requires_grad:
            return
        measurable, seen = self._views_measure_medium
        dark = self._decide_dark_channel(fog, measurable, seen, self._dense_fog())
        mode, beta = fog.config.record_prior, f"{float(fog.record_log_beta.exp().mean()):.2e}/m"
        flat = "off: where the photos cannot measure β they cannot tell how it varies"
        if mode != "auto":
            fog.use_record_prior = mode == "on"
            why = f"--{name}.record-prior {mode}" + (f" (β near {beta})" if fog.use_record_prior else "")
        elif dark:
            fog.use_record_prior = False
            why = f"the dark channel prior measures β; the record's {beta} is where it starts"
        elif measurable and (rain := self._rain_through_dense_fog()) is not None:
            fog.use_record_prior = True
            why = (
                f"{seen}, but {rain} through dense fog: the light the rain adds differs from view to view and drowns "
                f"the photos' measure of β, so β stays near the record's {beta}"
            )
            flat = "off: the rain that drowns the photos' measure of β drowns how it changes with height too"
        elif measurable and (fit := self._held_measure()) is not None:
            fog.hold_at(fit.beta_per_m)
            fog.use_record_prior = True
            why = (
                f"{seen}: the photos measure β {fit.beta_per_m:.2e}/m at {fit.points} of the scene's points (the "
                f"record's {beta}; a uniform medium explains {fit.explained:.0%} of the colour differences that clear "
                "air leaves there); β starts there and stays near it, as Gaussians free to take the haze in cannot "
                "measure it"
            )
        elif measurable:
            fog.use_record_prior = False
            why = f"{seen}: the photos measure β"
            if not self.use_clean and (thin := self._rain_veil_too_thin()) is not None:
                why += f" in training, from the record's {beta}: {thin}"
            elif not self.use_clean and (fit := self._measured_medium) is not None:
                why += (
                    f" in training: at the scene's points a uniform medium explains {fit.explained:.1%} of the colour "
                    f"differences that clear air leaves, under {MIN_MEDIUM_EXPLAINED:.0%}, too little to hold β at "
                    f"their {fit.beta_per_m:.2e}/m"
                )
        else:
            fog.use_record_prior = True
            why = f"{seen}: the photos cannot tell fog from a hazy scene, so β stays near the record's {beta}"
        weight = f" (weight {fog.config.record_prior_weight:g})" if fog.use_record_prior else ""
        self.decide(f"{name} prior", f"{'on' if fog.use_record_prior else 'off'}{weight}: {why}")
        uniform = self._rain_through_fog_seen_from_one_distance() if dark else None
        one_distance = uniform and (
            f"off: {uniform}: each view's share of the light the rain adds cannot be told from fog that changes with "
            "height or from patch to patch where every point is seen from about one distance, so the fog stays uniform"
        )
        if fog.use_record_prior and fog.measured_beta is None:
            self.decide(f"{name} layers", flat)
        elif one_distance:
            self.decide(f"{name} layers", one_distance)
        elif not (fog.config.layered and fog.config.learnable):
            self.decide(f"{name} layers", f"off: --{name}.no-layered")
        elif (fit := self._points_layers(fog)) is not None and fit.height_rate < 0.0:
            self.decide(
                f"{name} layers",
                f"off: the points read the fog denser upwards (scale height {100.0 / fit.height_rate:.0f} m), as they "
                "read every uniform fog measured, which no fog over the ground does, so β is one at every height",
            )
        else:
            fog.learn_layers()
            self.decide(f"{name} layers", "on: β learns how it changes with height" + self._start_layers(fog, fit))
        if fog.config.patches <= 0:
            self.decide(f"{name} patches", f"off: --{name}.patches 0")
        elif not (dark or (self.use_clean and not measurable)):
            self.decide(
                f"{name} patches",
                "off: they learn where the views cannot measure β, under the dark channel prior or beside clean "
                "references",
            )
        elif one_distance:
            self.decide(f"{name} patches", one_distance)
        elif dark and self._rain_veil_too_thin() is not None:
            self.decide(
                f"{name} patches",
                "off: the record gives no visibility, so the medium is the rain's thin veil, and a grid that scales "
                "its optical depth takes in the light the rain adds to each view instead",
            )
        elif fog.learn_patches():
            g = fog.patch_log_scale.shape
            self.decide(f"{name} patches", f"on: per view, a {g[2]}x{g[1]} grid scales the optical depth")
        self._decide_airlight_directions(name, fog, measurable, seen)

    def _decide_airlight_directions(self, name: str, fog: FogAnalytic, measurable: bool, seen: str) -> None:
        """Whether ``fog``'s airlight learns how it changes with the viewing direction (`FogAnalytic.learn_directions`):
        where the views see the scene from distances far apart, so that they see its surfaces along many directions,
        and the record gives a visibility. Views that all look one way see each surface along about one direction,
        where such an airlight cannot be told from the scene's colours, and the rain's veil alone is too thin to show
        it. Real fog is brighter towards the horizon and the sun: on the Lund street, inverting the independent
        family's fog at the true depth and transmission under its mean airlight leaves 20.5 dB, under the best
        degree-2 fit 26.9, under its own 29.8; trained blind it moved the runs by no more than their course does
        (benchmark.md), so it is opt-in."""
        if fog.config.airlight_degree <= 0:
            self.decide(
                f"{name} airlight",
                f"one for every direction (--{name}.airlight-degree 2 lets it change with the direction where the "
                "views see the scene along many)",
            )
        elif not measurable:
            self.decide(
                f"{name} airlight",
                f"one for every direction: {seen}, so each surface is seen along about one direction, where an "
                "airlight that changes with it cannot be told from the scene's colours",
            )
        elif self.weather_theta(self.scene).fog.visibility_m is None:
            self.decide(
                f"{name} airlight",
                "one for every direction: the record gives no visibility, and the rain's veil alone is too thin to "
                "show how its airlight changes with the direction",
            )
        elif fog.learn_directions():
            self.decide(
                f"{name} airlight",
                f"changes with the viewing direction: spherical harmonics of degree {fog.config.airlight_degree} in "
                f"world axes, held near one airlight (weight {fog.config.airlight_weight:g})",
            )

    @functools.cached_property
    def _views_measure_medium(self) -> tuple[bool, str]:
        """Whether the views see the scene's points (`_geometry_points`) from distances far enough apart
        (`MEASURABLE_DISTANCE_SPREAD`) for the photos to measure a medium, and what they see in words."""
        if self.random_init:  # random points fill the views' overlap and say nothing of where the scene lies
            return False, "the Gaussians start from random points, so how far apart the views see the scene is unknown"
        if self.swept_init and self.triangulated_points is None:  # the fox under rain + fog, blind: 14.86 dB
            return False, (  # with β free, 18.30 with the prior
                "the Gaussians start from a plane sweep of the photos, coarser than triangulated points; as from "
                "random points, how far apart the views see the scene is left unmeasured"
            )
        if (spread := self._distance_spread) is None:
            return False, "the views see a scene point from distances (unknown) apart (median)"
        seen = f"the views see a scene point from distances {spread:.2f}x apart (median)"
        if spread < MEASURABLE_DISTANCE_SPREAD:
            return False, f"{seen}, under {MEASURABLE_DISTANCE_SPREAD}x"
        return True, seen

    @functools.cached_property
    def _distance_spread(self) -> float | None:
        """Median ratio of the farthest to the nearest distance at which the training views see the scene's points
        (`_geometry_points`, a sweep's included: coarse for a measure of β, enough to tell a forward-facing rig's
        1.2-1.3 from a surround's 2), or None from random points or where no point is seen twice."""
        if self.random_init:
            return None
        return distance_spread(self.dataset.cameras[self.dataset.train_indices], self._geometry_points)

    @property
    def _geometry_points(self) -> torch.Tensor:
        """[P, 3] the points that the medium's measures read the scene's geometry at: the Gaussians' starting means,
        or the points triangulated beside the sweep they start from (`Trainer.triangulated_points`), finer than its
        planes."""
        if self.triangulated_points is not None:
            return torch.as_tensor(self.triangulated_points, dtype=torch.float32, device=self.device)
        return self.model.means.detach()

    def _held_measure(self) -> MediumFit | None:
        """Blind, where the record gives a visibility, the photos' measure at the scene's points (`_measured_medium`)
        where it explains at least `MIN_MEDIUM_EXPLAINED`, else None. The rain's veil alone is too thin for that
        measure, whose bias clear photos show (`_rain_veil_too_thin`)."""
        if self.use_clean or self._rain_veil_too_thin() is not None:
            return None
        if (fit := self._measured_medium) is None or fit.explained < MIN_MEDIUM_EXPLAINED:
            return None
        return fit

    def _rain_veil_too_thin(self) -> str | None:
        """Where the record gives no visibility, so that its medium is the rain's veil: why the points' measure does
        not hold β, else None. Under the photos' airlight metegs's own heavy-rain veil of 2.5e-3/m reads 2.76e-3 on the
        built-in scene (held there 26.42 dB, learnt in training from the record's 26.03), but 2.10e-3 on the fox (held
        at its earlier 1.63e-3 it lost 4.4 dB) and 4.1e-3 on the Lund street, whose clear photos read 1.9e-3."""
        if self.weather_theta(self.scene).fog.visibility_m is not None:
            return None
        return "the rain's veil alone is too thin for the points' measure, which clear photos read up to 1.9e-3/m"

    @functools.cached_property
    def _medium_observations(self) -> PointObservations | None:
        """The training photos' colours at the scene's points (`_geometry_points`) seen from distances
        `MEASURABLE_DISTANCE_SPREAD` times apart, in the views that no other such point hides them from
        (`point_observations`), or None where fewer than `MIN_MEASURED_POINTS` points are."""
        from metegs.weather.conditions import scene_metres_per_unit

        ds = self.dataset
        views = list(ds.train_indices)
        with self.status("reading the photos' colours at the scene's points"):
            obs = point_observations(
                ds.cameras[views],
                [ds.images[i] for i in views],
                self._geometry_points,
                torch.as_tensor(self.scene.up),
                scene_metres_per_unit(self.config.conditions, self.scene.metric_scale),
                max_points=MEASURED_POINTS,
            ).spread(MEASURABLE_DISTANCE_SPREAD)
        return obs if len(torch.unique(obs.point)) >= MIN_MEASURED_POINTS else None

    @functools.cached_property
    def _measured_medium(self) -> MediumFit | None:
        """The uniform medium that the `_medium_observations` show (`fit_uniform_medium`) under the training photos'
        `typical_airlight`, or None where there are too few. Fitted along with β, the airlight trades against it (the
        fox in metegs's own 200 m fog: 0.0138/m under a fitted airlight, 0.0153 under the photos', exact 0.0150). Points
        seen from about one distance show one veil in every view, which says nothing of β but through the airlight's
        model: the built-in scene's far hills, where the fog thins with height, read 3.2e-3/m with them and 1.27e-2
        without (the independent family's 1.3e-2 at the ground)."""
        if (obs := self._medium_observations) is None:
            return None
        with self.status("measuring the fog at the scene's points"):
            return fit_uniform_medium(obs, airlight=self._photos_airlight)

    def _points_layers(self, fog: FogAnalytic) -> MediumFit | None:
        """Where β is held at the points' measure, the layered medium that the same observations show under the same
        airlight (`fit_medium`), else None. Where that reads denser upwards, as every uniform fog measured read (scale
        heights −105 to −1148 m), which no fog over the ground does, β stays one at every height: learnt from uniform
        there, the profile cost the real captures 0.49 dB on average over ten runs (−0.06 to +1.65: metegs's own fog on
        the Lund street and the fox, its rain + fog on the fox and the third generator's fog on both, two seeds each),
        though on the built-in scene, whose dome past 200 m it fogs more, it paid 0.74 dB in metegs's own fog and 1.70
        under the third generator's smog (`benchmarks/fog_layers.py`)."""
        if fog.measured_beta is None or (obs := self._medium_observations) is None:
            return None
        with self.status("measuring how the fog changes with height at the scene's points"):
            return fit_medium(obs, fog.measured_beta, airlight=self._photos_airlight)

    def _start_layers(self, fog: FogAnalytic, fit: MediumFit | None) -> str:
        """Start β and its height profile at ``fit`` (`_points_layers`) where that thins upwards, as fog over the ground
        does -> the start in words ("" where nothing was measured). From a uniform start the profile learns little of
        height fog, and a scene that takes the haze in meanwhile keeps it: the built-in scene in independent 200 m fog
        18.68 dB from the points' profile (scale height 27 m), 17.16 from a uniform start; the Lund street in it 13.52
        against 12.93 (the points read 55 m, the generator's is 27 m; training from uniform learnt 344 m)."""
        if fit is None:
            return ""
        if fit.height_rate == 0.0:
            return ", from uniform"
        fog.hold_at(fit.beta_per_m, fit.height_rate)
        return (
            f", from the points' measure of how: {fit.beta_per_m:.2e}/m at the cameras' mean height, scale height "
            f"{100.0 / fit.height_rate:.0f} m"
        )

    @functools.cached_property
    def _photos_airlight(self) -> torch.Tensor:
        """[3] the training photos' `typical_airlight`, under which the points' measure holds the medium."""
        return typical_airlight([self.dataset.images[i].detach().cpu() for i in self.dataset.train_indices])

    def _dense_medium(self) -> str | None:
        """The medium's optical depth at the scene's typical depth in words where it is dense there
        (`DENSE_OPTICAL_DEPTH`: visibility under 3x that depth), else None."""
        if self.medium_optical_depth < DENSE_OPTICAL_DEPTH:
            return None
        return f"the medium's optical depth at the scene's typical depth is {self.medium_optical_depth:.2f}"

    def _rain_through_dense_fog(self) -> str | None:
        """Blind, rain heavier than light through a dense medium (`DENSE_OPTICAL_DEPTH` at the scene's typical depth):
        the rain in words, else None. β held at the points' measure there instead of the record's lost 0.16-1.27 dB in
        the three cells of the Lund street and the kitchen where the record's wins (`_decide_dark_channel`), nearer the
        generator's fog though it was: the record's higher β takes the rain's light out with the haze."""
        rain = self.weather_theta(self.scene).rain
        if self.use_clean or rain.intensity_class in LIGHT_OR_NONE or self._dense_medium() is None:
            return None
        return rain_phrase(rain)

    def _rain_through_fog_seen_from_one_distance(self) -> str | None:
        """Blind, rain heavier than light through the record's fog, where the views see the scene's points from about
        one distance (`_distance_spread` under `MEASURABLE_DISTANCE_SPREAD`): the rain and that spread in words, else
        None."""
        theta = self.weather_theta(self.scene)
        if self.use_clean or theta.rain.intensity_class in LIGHT_OR_NONE or theta.fog.visibility_m is None:
            return None
        if (spread := self._distance_spread) is None or spread >= MEASURABLE_DISTANCE_SPREAD:
            return None
        return f"{rain_phrase(theta.rain)} through fog, seen from distances {spread:.2f}x apart"

    def _dense_fog(self) -> str | None:
        """Blind, where the record gives a visibility, a medium dense at the scene's typical depth
        (`DENSE_OPTICAL_DEPTH`): its optical depth in words, else None."""
        if self.use_clean or self._rain_veil_too_thin() is not None:
            return None
        return self._dense_medium()

    def _decide_dark_channel(self, fog: FogAnalytic, measurable: bool, seen: str, dense: str | None) -> bool:
        """Whether the dark-channel prior holds ``fog`` (then it joins `dehazing`): blind training only, and with
        ``mode`` auto where the photos cannot measure β themselves, or where the fog is ``dense`` (`_dense_fog`) and
        their measure at the scene's points does not hold it (`_held_measure`), rain or not. A scene without near-black
        patches (the built-in one's grey ground, dark channel J ≈ 0.13) biases the veil the prior reads by J·t against a
        veil of 1 − t: in thin media that swamps it (the built-in scene's default weather, 7.6 dB lost), in dense fog
        less; but the photos hold β times the rendered distance, so as the prior raises β the Gaussians move in: the
        built-in scene in its own 200 m fog ended at 0.020-0.022/m (exact 0.0150) with the test views' near surfaces
        rendered at 0.69 of their distance (0.97 held at the points' 0.0150; `benchmarks/fog_error_by_distance.py`).
        Held at the measure, 3000 steps on the Lund street (28 photos) scored 12.71 dB in metegs's own 200 m fog and
        13.52 in the independent (10.19 and 12.17 under this prior), the built-in scene in independent 200 m fog 18.68
        (16.23); its own fog 13.93 against 17.40, lost behind its sky dome, over 200 m off and seen through 2-5 % of its
        light, whose colour no β recovers. The fox's optical depth of 0.76 stays off, where forced on it cost 1.6 dB.
        Under rain through the dense fog, where the points' measure holds, the record prior holds β instead
        (`_rain_through_dense_fog`): against this prior it won by 2.11-3.23 dB on the Lund street (metegs's own and the
        independent rain + fog, uniform media explaining 43 % and 11 % at the points) and in the kitchen's own (32 %).
        Where the measure does not hold, the photos do not bear the record's fog out: the kitchen's independent rain +
        fog (3.4 % explained; its height fog is 3.5x thinner at the cameras than the record's) scored 14.23 dB under
        this prior, 11.25 under the record's β."""
        c = self.config.dark_channel
        rain = self._rain_through_dense_fog() if measurable and dense else None
        if self.use_clean:
            on, why = False, "off: the clean references measure the medium"
        elif c.weight <= 0 or c.mode == "off":
            on, why = False, "off" + (": weight 0" if c.weight <= 0 else "")
        elif c.mode == "on":
            on, why = True, "on (--dark-channel.mode on)"
        elif measurable and dense and (fit := self._held_measure()) is not None:
            on = False
            why = (
                f"off: {seen}, and though {dense} (visibility under 3x that depth), the photos measure β "
                f"{fit.beta_per_m:.2e}/m at the scene's points"
                + (f", which bear the record's fog out (under {rain} its β holds the medium)" if rain else "")
                + " (--dark-channel.mode on adds it)"
            )
        elif measurable and dense:
            on = True
            why = (
                f"on: {seen}, but {dense} (visibility under 3x that depth) and the photos' colours at the scene's "
                "points do not measure it"
                + (
                    f", so they do not bear the record's fog out and its β cannot hold the medium under {rain}"
                    if rain
                    else ""
                )
                + ": a scene without near-black patches biases the veil this prior reads by its own dark channel "
                "times the transmission, small there"
            )
        elif measurable:
            on, why = False, f"off: {seen}: the photos measure β (--dark-channel.mode on adds it)"
        else:
            on, why = True, f"on: {seen}: the photos cannot tell fog from a hazy scene"
        if on:
            self.dehazing.append(fog)
            # as He et al. estimate A once: a free A drifts down while a pale scene takes the haze in (head, fog)
            fog.airlight_logit.requires_grad_(False)
            why += (
                f"; weight {c.weight:g}: the photos dehazed by the medium keep {c.quantile:.0%} of their dark channel "
                f"at zero, as clear views do, under {self._dehazing_airlight(fog)}, held"
            )
        self.decide("dark channel prior", why)
        return on

    def _dehazing_airlight(self, fog: FogAnalytic) -> str:
        """Under the dark-channel prior, the airlight ``fog`` holds, in words: the one estimated at the start (the
        photos' brightest haze), lowered to what the scene's points fit along with β where a medium explains enough of
        their colours (`airlight_under_haze`, `MIN_MEDIUM_EXPLAINED`) and the config and θ give none. Held at the
        estimate, the fox under the third generator's smog, which starts from a plane sweep, scored 14.78 dB (the
        restoration 13.96); at its points' fit, 20.37."""
        start = fog.airlight.detach().cpu()
        estimated = ", ".join(f"{float(a):.2f}" for a in start)
        if fog.config.airlight is not None or self.weather_theta(self.scene).fog.airlight_rgb is not None:
            return f"the airlight given ({estimated})"
        if (obs := self._medium_observations) is None:
            return f"the airlight estimated at the start ({estimated})"
        with self.status("fitting the airlight at the scene's points"):
            held = airlight_under_haze(start, obs, MIN_MEDIUM_EXPLAINED)
        if not bool((held < start).any()):
            return f"the airlight estimated at the start ({estimated}), which the scene's points leave as it is"
        fog.set_airlight(held)
        lowered = ", ".join(f"{float(a):.2f}" for a in held)
        return (
            f"the airlight ({lowered}) that the scene's points fit along with β, darker than the photos' brightest "
            f"haze ({estimated})"
        )

    def _build_gtn(self):
        from metegs.models.gtn import GaussianTransformationNetwork

        c = self.config
        if not (c.gtn.enabled and c.weather_branch):
            self.decide("gtn", "off" + ("" if c.weather_branch else ": no weather branch"))
            return None
        sharp = self._sharp_weather()
        if sharp is not None:
            self.decide("gtn", f"off: {sharp}, and per-view growth would only absorb the scene's detail")
            return None
        if not (self.use_clean or c.gtn.blind):
            self.decide(
                "gtn",
                "off: blind training (--gtn.blind adds it): no clean reference holds the scene's sharpness, so its "
                "per-view growth fits what the views disagree on, which the clean scene then lacks",
            )
            return None
        centre = self.dataset.cameras[self.dataset.train_indices].camera_to_worlds[:, :3, 3].mean(0)
        gtn = GaussianTransformationNetwork(c.gtn, centre, self.extent).to(self.device)
        self.decide("gtn", f"on: scale/rotation growth in [1, {c.gtn.max_factor}]")
        return gtn

    @property
    def has_medium(self) -> bool:
        """Whether a weather model with a medium (fog, rain veil) is on."""
        return self._with_medium(self.weather_models)

    @staticmethod
    def _with_medium(models: list[WeatherModel]) -> bool:
        """Whether one of ``models`` is a medium (fog, rain veil)."""
        return any(hasattr(m, "extinction_per_m") for m in models)

    def _sharp_weather(self, models: list[WeatherModel] | None = None) -> str | None:
        """Why nothing in this weather blurs the photos (light or no rain, and no medium among ``models``, the
        weather models that are on by default), or None."""
        rain = self.weather_theta(self.scene).rain
        medium = self._with_medium(self.weather_models if models is None else models)
        if rain.intensity_class in LIGHT_OR_NONE and not medium:
            return f"{rain_phrase(rain)} and no visible medium: nothing in this weather blurs the photos"
        return None

    def visible_weather(self) -> str | None:
        """The weather of θ a person would see in the photos: MeteGS takes its θ (the shipped storm record where
        none is stated) as the capture's weather."""
        return self._weather_of_theta()

    def _streaks_over_clear_air(self) -> str | None:
        """Why, blind, heavier rain blurs nothing of the scene (no medium is on: the photos show no veil, so the rain
        is streaks over a clear view, which the robust mask and the low-quantile fit take), or None. A third
        generator's heavy rain (streaks alpha-blended towards one radiance, no veil), 3000 steps: the Lund street
        15.40 ± 0.24 dB over three seeds against 15.08 ± 0.43 with the faint Gaussians kept, the fox 27.29 against
        26.80, the Ethiopian head 18.09 against 18.40; the independent family's heavy rain on the fox 18.18 against
        18.22."""
        rain = self.weather_theta(self.scene).rain
        if self.use_clean or self.has_medium or rain.intensity_class in LIGHT_OR_NONE:
            return None
        return f"{rain_phrase(rain)} with no visible medium: streaks over a clear view blur nothing of the scene"

    def _blind_sharp_weather(self, models: list[WeatherModel] | None = None) -> str | None:
        """`_sharp_weather` in blind training, None beside clean references: where the run leaves out the learnable
        streaks, the extra points, depth-aware pruning and the camera clearance (with references they pay even in light
        rain)."""
        return None if self.use_clean else self._sharp_weather(models)

    def _make_exposure(self):
        """3dgs's per-view tone, but with `view_exposure` auto off beside a fog model (its airlight and β set each
        view's tone too)."""
        if self.config.view_exposure == "auto" and self.has_medium:
            self.decide(
                "view_exposure",
                "off (a fog model is on: its airlight and β set each view's tone, which per-view gains would "
                "compete with; --view-exposure on|off)",
            )
            return None, None
        return super()._make_exposure()

    def _build_perceptual(self):
        c = self.config
        if not self.use_clean or c.weights.perceptual <= 0:
            why = "no clean references" if not self.use_clean else "weight 0"
            self.decide("perceptual", f"off: {why}")
            return None
        from metegs.losses.perceptual import try_load_perceptual

        loss, reason = try_load_perceptual(c.perceptual, self.device)
        if loss is None:
            self.decide("perceptual", f"off: {reason}", warn=True)
            return None
        self.decide("perceptual", f"on: {loss.backbone_name} features, weight {c.weights.perceptual}")
        return loss

    def _setup_extra_points(self) -> None:
        from metegs.densify.extra_points import ExtraPointCompensation

        c = self.config
        self.extra_points = None
        if c.extra_points and self.random_init:
            # Deblurring-3DGS fills the sparse regions of an SfM point cloud; random points have none, and on the
            # Ethiopian head (random init) the extra points cost 0.8 dB of test PSNR at 1000 steps.
            self.decide("extra points", "off: the Gaussians started from random points (no SfM cloud to compensate)")
        elif c.extra_points and (sharp := self._blind_sharp_weather()) is not None:
            self.decide("extra points", f"off: {sharp}, so, blind, no blur left the SfM cloud sparse to compensate")
        elif c.extra_points:
            points = self.model.params["means"].detach().clone()
            self.extra_points = ExtraPointCompensation(c.extra_points_options, c.max_steps, self.extent, points)
            self.decide("extra points", f"on at step {round(c.extra_points_options.at * c.max_steps)}")
        else:
            self.decide("extra points", "off")

    def _setup_camera_clearance(self) -> None:
        """`camera_clearance`: the Gaussians beside or behind a training camera go when training ends."""
        from metegs.densify.camera_clearance import DEPTH_SHARE, CameraClearance

        fraction, self.clearance = self.config.camera_clearance, None
        if fraction <= 0:
            self.decide("camera clearance", "off")
            return
        if (sharp := self._blind_sharp_weather()) is not None:
            self.decide("camera clearance", f"off: {sharp}, so, blind, the run is 3dgs's")
            return
        cameras = self.dataset.cameras[self.dataset.train_indices]
        clearance = CameraClearance(cameras, fraction, typical_depth_m(cameras, self.scene.points, 1.0))
        if clearance.radius <= 0:
            self.decide("camera clearance", "off: the training cameras stand at one place")
            return
        self.clearance = clearance
        self.decide(
            "camera clearance",
            f"on: Gaussians within {clearance.radius:.3g} (scene units: {fraction:g} of the median distance between "
            f"neighbouring training cameras, at most {DEPTH_SHARE:g} of the scene's typical depth) of a training camera "
            "that none of the cameras there sees are pruned when training ends",
        )

    def make_densifier(self):
        """The configured densification with depth-aware pruning (`depth_prune`) as its pruning rule where the weather
        blurs the photos, and, blind, without opacity resets where a visible medium dims the views with no rain to
        clear, or where the fog is dense over an SfM cloud (`DENSE_OPTICAL_DEPTH`): beside clean references the clean
        branch's undimmed gradients regrow what a reset takes."""
        from metegs.densify.depth_prune import DepthAwarePruning

        c, rule, sharp, blind_sharp = self.config, None, self._sharp_weather(), self._blind_sharp_weather()
        if c.depth_prune and blind_sharp is not None:
            self.decide(
                "depth pruning", f"off: {blind_sharp}, so, blind, 3dgs's opacity threshold holds the far Gaussians"
            )
        elif c.depth_prune:
            rule = DepthAwarePruning(c.depth_prune_options, self.dataset.cameras[self.dataset.train_indices]).thresholds
            self.decide("depth pruning", f"on ({c.depth_prune_options.depth_mode} depth)")
        else:
            self.decide("depth pruning", "off")

        def build(options):
            views = len(self.dataset.train_indices)
            return options.setup(max_steps=c.max_steps, extent=self.extent, num_train_views=views, prune_rule=rule)

        densify, unblurred = c.densify, sharp or self._streaks_over_clear_air()
        if unblurred is not None and densify.prune_opacity == BLURRED_PRUNE_OPACITY:
            densify = replace(densify, prune_opacity=SHARP_PRUNE_OPACITY)
            self.decide(
                "opacity pruning",
                f"{SHARP_PRUNE_OPACITY:g} (3dgs's): {unblurred}, so the {BLURRED_PRUNE_OPACITY:g} kept for blurred "
                "photos would only leave half-transparent Gaussians that fit single views",
            )
        densifier, rain = build(densify), self.weather_theta(self.scene).rain
        if not getattr(densifier, "reset_every", 0):
            return densifier
        if sharp is None and rain.intensity_class in LIGHT_OR_NONE:
            why = f"{rain_phrase(rain)} leaves no streaks for resets to clear, and under the fog a reset costs "
            why += "Gaussians that its dimmed gradients hardly regrow"
        elif (dense := self._dense_medium()) and not self.random_init:
            why = (
                f"{dense} (visibility under 3x that depth) and the Gaussians started from an SfM cloud: "
                "a reset would cost its geometry, which the fog-dimmed gradients hardly regrow, while what does regrow "
                "fits the rain"
            )
        else:
            return densifier
        if self.use_clean:
            self.decide(
                "opacity reset",
                "on: the clean references' gradients, which no fog dims, regrow what a reset takes (blind they would "
                f"be off: {why})",
            )
            return densifier
        self.decide("opacity reset", f"off: {why}")
        return build(replace(densify, reset_every=0.0))

    def _method_optimizers(self) -> dict[str, torch.optim.Optimizer]:
        optimizers = {}
        if self.gtn is not None:
            optimizers["gtn"] = adam(self.gtn.parameters(), lr=self.config.gtn.lr)
        groups = []
        for m in self.weather_models:
            if isinstance(m, LearnableTransients):
                groups += [g for g in m.param_groups() if g["params"]]
            else:
                params = [p for p in m.parameters() if p.requires_grad]
                if params:
                    groups.append({"params": params, "lr": self.config.weather_lr, "name": m.name})
        if groups:
            optimizers["weather"] = adam(groups, eps=1e-15)
        return optimizers

    def extra_metrics(self) -> dict:
        """The weather models' learned values next to θ's (e.g. fog β), under ``weather``."""
        learned = {m.name: s for m in self.weather_models if (s := m.summary()) is not None}
        return {"weather": learned} if learned else {}

    def background(self, training: bool) -> torch.Tensor:
        """[3] Where the clean scene is transparent a view looks into the distance, which the fog model shows as
        its airlight A (the weather branch composites A there): with a fog model, clean renders and references
        use A as background, so that blind training cannot leave the scene see-through. Else the configured one."""
        for m in getattr(self, "weather_models", ()):
            airlight = getattr(m, "airlight", None)
            if isinstance(airlight, torch.Tensor):
                return airlight.detach().to(self.device, torch.float32).clone()
        return super().background(training)

    # --- one step ----------------------------------------------------------------------------------
    def render_weather(self, index: int, background: torch.Tensor, training: bool):
        """Weather-branch render of view ``index`` (GTN only while training) -> WeatherRender."""
        settings = RenderSettings(background=background, sh_degree=self.model.active_sh_degree)
        camera = self.dataset.cameras[index]
        scene = self.step_gaussians() if training else self.model.activated()
        if training and self.gtn is not None:  # only where the view can see: the rest would stay unseen anyway
            only = may_be_visible(scene, camera, self.config.gtn.max_factor, settings.near)
            scene = self.gtn(scene, camera.camera_to_worlds[0, :3, 3], only)
        return render_with_weather(self.rasterizer, scene, self.weather_models, index, camera, settings)

    def photo_render(self, index: int, background: torch.Tensor) -> StepRender:
        """The weather branch: the scene through the GTN with the weather, as photographed, judged by the photo; and
        where clean references hold the scene, the clean branch's render of the same step. Densification reads both
        (weather Gaussians excluded): the weather branch's gradients alone, dimmed by the fog and pulled by the
        streaks, left a scene judged by clean references with too few Gaussians."""
        weather = self.render_weather(index, background, training=True)
        clean = self.render(index, training=True, background=background) if self._clean_loss_on else None
        return StepRender(self.as_photographed(weather.rgb, index), weather.out, weather.num_scene, clean)

    def step_loss(
        self, index: int, background: torch.Tensor, render: StepRender, target: torch.Tensor, stats: dict[str, float]
    ) -> torch.Tensor:
        """The weather branch's (trimmed) photometric loss, the weather models' priors and, with clean references,
        the clean branch's L1 and perceptual terms."""
        c = self.config
        weights, quantile, ssim_lambda, ssim_images = None, 0.5, None, None
        if self.robust_from is not None and self.step >= self.robust_from:
            weights = inlier_weights(target - render.rgb.detach(), c.robust, self._thin_strokes(index))
            if self._quantile_pending:
                self._choose_quantile()
            quantile = self.quantile
            if quantile < 0.5:
                ssim_lambda = c.robust.ssim_lambda  # None: the loss's own
                if self.stroke_width > 1:
                    ssim_images = without_bright_strokes(render.rgb, target, self.stroke_width, c.robust.min_excess)
            stats["inliers"] = float(weights.mean())
        loss = c.weights.photo * self.loss_fn(render.rgb, target, weights, quantile, ssim_lambda, ssim_images)
        for m in self.weather_models:
            prior = m.prior(index)
            if prior is not None:
                loss = loss + prior
        for m in self.dehazing:
            dehazed, valid = m.dehaze(target, render.out, index, c.dark_channel.min_transmission)
            dark = dark_channel_loss(dehazed, valid, c.dark_channel)
            stats["dark_channel"] = float(dark.detach())
            loss = loss + c.dark_channel.weight * dark
        if index in self.pseudo_references and c.weights.pseudo > 0:
            pseudo = box_detail(self._masked(index, self.pseudo_references[index], background), c.pseudo_detail_px)
            clean = box_detail(self.clean_branch(index, background), c.pseudo_detail_px)
            loss = loss + c.weights.pseudo * (clean - pseudo).abs().mean()
        if self._clean_loss_on:
            clean = self.as_photographed(render.clean.rgb, index)
            reference = self.reference(index, background)
            if c.weights.clean > 0:
                loss = loss + c.weights.clean * self.loss_fn(clean, reference)
            if self.perceptual is not None:
                loss = loss + c.weights.perceptual * self.perceptual(
                    clean, target_features=self._reference_features(index, reference)
                )
        return loss

    @property
    def _clean_loss_on(self) -> bool:
        """Whether clean references judge the clean branch this run (its L1 + SSIM or its perceptual term)."""
        return self.use_clean and (self.config.weights.clean > 0 or self.perceptual is not None)

    def clean_branch(self, index: int, background: torch.Tensor) -> torch.Tensor:
        """[H, W, 3] the scene alone in training view ``index``, in its photo's tone: the clean reference is that
        photo without the weather, taken with the same exposure (`view_exposure`)."""
        return self.as_photographed(self.render(index, training=True, background=background).rgb, index)

    def step_optimizers(self) -> list[torch.optim.Optimizer]:
        """The Gaussians' optimisers and the method's (GTN, weather)."""
        return [*super().step_optimizers(), *self.method_optimizers.values()]

    def densify_step(self) -> dict[str, int]:
        """The densification schedule, then the extra points once (`extra_points`), and at the last step the camera
        clearance (`camera_clearance`)."""
        changes = super().densify_step()
        if self.extra_points is not None:
            changes.update(self.extra_points.step(self.model, self.optimizers, self.step))
        if self.clearance is not None and self.step == self.config.max_steps - 1:
            changes["prune_near_cameras"] = self.clearance.prune(self.model, self.optimizers)
        return changes

    def _reference_features(self, index: int, reference: torch.Tensor) -> list[dict[str, torch.Tensor]]:
        """Perceptual features of a view's clean reference, kept while they fit in `PERCEPTUAL_CACHE_MB`
        (references are fixed unless masks composite them over a random background)."""
        cached = self._feature_cache.get(index)
        if cached is not None:
            return cached
        features = self.perceptual.target_features(reference)
        size_mb = sum(f.numel() * f.element_size() for d in features for f in d.values()) / 2**20
        fixed = self.dataset.masks is None or self.config.background != "random"
        if fixed and size_mb * len(self.dataset.train_indices) <= PERCEPTUAL_CACHE_MB:
            self._feature_cache[index] = features
        return features

    # --- outputs -----------------------------------------------------------------------------------
    def save_renders(self, indices: list[int], split: str) -> None:
        """Clean renders and, per view, [clean render | weather render | clean reference | photo] side by side."""
        from metegs.data.images import save_image

        super().save_renders(indices, split)
        folder = self.run_dir / "renders" / split
        bg = self.background(training=False)
        with torch.no_grad():
            for i in indices:
                name = Path(self.dataset.names[i]).stem
                clean = self.render(i, background=bg).rgb.clamp(0, 1)
                weather = self.render_weather(i, bg, training=False).rgb.clamp(0, 1)
                save_image(folder / f"{name}_weather.png", weather)
                row = [clean, weather, self.reference(i, bg), self.target(i, bg)]
                save_image(folder / f"{name}_compare.png", torch.cat(row, dim=1))

    # --- checkpoints -------------------------------------------------------------------------------
    def extra_state(self) -> dict:
        return {
            "gtn": None if self.gtn is None else self.gtn.state_dict(),
            "weather": {m.name: m.state_dict() for m in self.weather_models},
            "method_optimizers": {k: o.state_dict() for k, o in self.method_optimizers.items()},
            "extra_points": None if self.extra_points is None else self.extra_points.state_dict(),
            "quantile": None if self._quantile_pending else [self.quantile, self._quantile_reason],
        }

    def load_extra_state(self, ckpt: dict) -> None:
        if self._quantile_pending and ckpt.get("quantile") is not None:  # chosen before the checkpoint: keep it
            self._quantile_pending = False
            self._decide_quantile(*ckpt["quantile"])
        if self.gtn is not None and ckpt.get("gtn") is not None:
            saved = ckpt["gtn"].get("head_scale.weight")
            if saved is not None and saved.shape[1] != self.config.gtn.width:
                raise ConfigError(
                    f"{self.resumed_from}: its GTN is {saved.shape[1]} wide, this run's {self.config.gtn.width}; "
                    f"continue it with --gtn.width {saved.shape[1]} (or from its config.yml: --config RUN/config.yml)"
                )
            self.gtn.load_state_dict(ckpt["gtn"])
        for m in self.weather_models:
            state = ckpt.get("weather", {}).get(m.name)
            if state is not None:
                m.load_state_dict(state)
        for k, o in self.method_optimizers.items():
            state = ckpt.get("method_optimizers", {}).get(k)
            if state is None:
                continue
            saved = [len(g["params"]) for g in state.get("param_groups", [])]
            if saved != [len(g["params"]) for g in o.param_groups]:  # other parameters learn than when it was saved
                warnings.warn(
                    f"{self.resumed_from}: its {k} optimiser moments were saved for other learnable parameters "
                    f"(groups of {saved}); they start afresh",
                    stacklevel=2,
                )
                continue
            o.load_state_dict(state)
        if self.extra_points is not None and ckpt.get("extra_points") is not None:
            self.extra_points.load_state_dict(ckpt["extra_points"])
