"""The trainer: sets a run up from a `TrainConfig`, optimises, evaluates and writes the run folder."""

from __future__ import annotations

import contextlib
import functools
import json
import math
import random
import time
from dataclasses import dataclass, replace
from datetime import datetime
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from metegs import __version__
from metegs.config import absolute_paths, save_yaml
from metegs.data.config import auto_max_side
from metegs.data.dataset import Dataset
from metegs.data.parsers.base import parse_scene
from metegs.data.scene import SceneData
from metegs.engine.allocator import keep_freed_memory
from metegs.engine.checkpoint import (
    check_compatible,
    load_checkpoint,
    resolve_checkpoint,
    save_checkpoint,
    scene_signature,
)
from metegs.engine.config import TrainConfig
from metegs.engine.init import random_points_in_view_overlap, scene_extent
from metegs.engine.optim import adam, make_optimizers, means_lr_at
from metegs.engine.progress import TrainProgress
from metegs.errors import ConfigError, DataError, Interrupted
from metegs.files import atomic_write_text, write_result
from metegs.gaussians.dropout import drop_gaussians, drop_rate_at
from metegs.gaussians.model import GaussianModel, GaussianSet
from metegs.meteo import Theta
from metegs.models.exposure import ViewExposure, nearest_training_rows
from metegs.render import RenderOutput, RenderSettings, make_rasterizer
from metegs.render.cpu_backend import thread_split, thread_split_counts
from metegs.render.select import resolve_backend

if TYPE_CHECKING:
    from metegs.data.triangulate import TriangulatedPoints


def resolve_device(name: str) -> torch.device:
    """``auto`` -> cuda if available else cpu; an unavailable CUDA device is a clear error."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    device = torch.device(name)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"--device {name}: CUDA is not available on this machine (use --device cpu)")
    return device


def non_finite_params(model: GaussianModel) -> list[str]:
    """Names of the model's parameters that hold a NaN or an infinity."""
    with torch.no_grad():
        # one pass and one sync: a sum is finite exactly when every element is (barring an overflow of the sum,
        # which only parameters beyond 1e32 could cause); the per-element test runs only then
        sums = torch.stack([p.detach().sum(dtype=torch.float64) for p in model.params.values()])
        if bool(torch.isfinite(sums).all()):
            return []
        return [name for name, p in model.params.items() if not bool(torch.isfinite(p).all())]


@dataclass
class StepRender:
    """What a training step rendered for its photo."""

    rgb: torch.Tensor
    """[H, W, 3] the image the photometric loss compares with the photo."""
    out: RenderOutput
    """The rasterisation behind it, whose screen-space gradients densification reads."""
    num_scene: int | None = None
    """How many of ``out``'s Gaussians are scene Gaussians, the first ones (None: all)."""
    clean: RenderOutput | None = None
    """The scene alone in the same view where a clean reference judges it too (MeteGS's clean branch), whose
    screen-space gradients densification also reads."""


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


class Trainer:
    """Plain 3DGS training of scene Gaussians on the training views."""

    def __init__(
        self,
        config: TrainConfig,
        run_dir: Path | None = None,
        console=None,
        scene: SceneData | None = None,
        model: GaussianModel | None = None,
    ):
        """``model``: Gaussians that replace the configured initialisation (a PLY reopened for viewing or
        evaluation). With ``config.load_checkpoint`` the checkpoint's Gaussians do, and neither case builds the
        initial model (triangulating a scene without points takes about half a minute when its cache is gone)."""
        self._created = time.perf_counter()
        self.device = resolve_device(config.device)
        backend = resolve_backend(config.backend, self.device)
        # the image size chosen for this device is recorded, so evaluation on another device loads the same (a
        # budget chooses its own, below)
        dataset = config.dataset
        if config.budget_minutes is None:
            dataset = replace(dataset, auto_max_side=auto_max_side(dataset, self.device.type))
        self.config = config = replace(config, backend=backend, device=str(self.device), dataset=dataset)
        if config.threads > 0:
            torch.set_num_threads(config.threads)
        torch.set_flush_denormal(True)  # tiny transmittances/gradients otherwise slow CPU arithmetic ~30x
        if self.device.type == "cpu":
            keep_freed_memory()  # no page faults for the memory each step frees and allocates again
        self.console = console
        seed_everything(config.seed)
        self.decisions: dict[str, str] = {}
        """What the run chose to do or skip, and why (printed once, saved as decisions.json)."""
        self.theta: Theta | None = None
        self.scene = (
            scene if scene is not None else self.prepare_scene(parse_scene(config.data, config.parser, config.dataset))
        )
        if config.budget_minutes is not None:
            from metegs.engine.budget import plan_budget

            plan = plan_budget(type(self), config, self.scene, spent_s=time.perf_counter() - self._created)
            self.config = config = plan.config
            seed_everything(config.seed)  # the run is the one its recorded flags reproduce
            self.decide("budget", plan.text)
        self.dataset = Dataset(self.scene, config.dataset, device=self.device)
        if config.dataset.downscale is None:
            w, h = self.dataset.sizes[0]
            self.decide(
                "image size",
                f"{w}x{h} px: the longer side at most {config.dataset.auto_max_side} px on {self.device.type} "
                f"(downscale {self.dataset.downscale}; --dataset.auto-max-side or --dataset.downscale choose another)",
            )
        if len(self.dataset.train_indices) < 2:
            raise ConfigError(
                f"{self.scene.source or 'the scene'}: {len(self.dataset.train_indices)} training view(s); 3D Gaussian "
                "Splatting needs at least 2 views from different positions (check --dataset.test-every)"
            )
        self.rasterizer = make_rasterizer(backend, self.device)
        self.extent = scene_extent(self.dataset.cameras[self.dataset.train_indices])
        self._random_init: bool | None = None
        self.swept_init = False
        """True when the Gaussians start from a plane sweep's points (`initial_points`)."""
        self.triangulated_points: np.ndarray | None = None
        """[P, 3] points triangulated from the training views where the Gaussians start from the sweep
        (``model.sweep_init``) and triangulation works too: where the weather models measure the scene's geometry."""
        self.resumed_from: Path | None = None
        """The checkpoint file this run continues (``load_checkpoint``), else None."""
        ckpt = None
        if config.load_checkpoint is not None:
            self.resumed_from = resolve_checkpoint(config.load_checkpoint)
            ckpt = load_checkpoint(self.resumed_from, self.device)
            check_compatible(ckpt, self.resumed_from, config.method, self.scene_signature())
        if ckpt is not None:
            self.model = self._checkpoint_model(ckpt)
            if "random_init" in ckpt:  # older checkpoints: found again from the scene (cached triangulation)
                self._random_init = bool(ckpt["random_init"])
            self.swept_init = bool(ckpt.get("swept_init", False))
            if (measured := ckpt.get("triangulated_points")) is not None:
                self.triangulated_points = measured.cpu().numpy()
        elif model is not None:
            self.model = model.to(self.device)
            self._random_init = False
            self.decide("init", "Gaussians given (not initialised by this run)")
        else:
            self.model = self._initial_model()
        self.optimizers = make_optimizers(self.model.params, config.optim, self.extent)
        self.loss_fn = config.loss.setup()
        self.step = 0
        self.history: list[dict] = []
        self.train_seconds = 0.0
        self.step_hooks: list = []
        """Called as ``hook(trainer, stats)`` after every training step (the live viewer; a hook may block to pause)."""
        self._claim_run_dir = run_dir is None
        self.run_dir = Path(run_dir) if run_dir is not None else self._default_run_dir()
        """The run folder; a default one is claimed (made new, never reused) when training starts."""
        self.setup_method()
        self.drop_rate = self._decide_drop_rate()
        """The share of Gaussians `step_gaussians` leaves out by the last step."""
        self.exposure, self.exposure_optimizer = self._make_exposure()  # after the method: it may decide
        self.densifier = self.make_densifier()
        self._decide_densify_horizon()
        if ckpt is not None:
            self._restore_state(ckpt)

    # --- setup -------------------------------------------------------------------------------------
    def status(self, text: str):
        """A context that shows ``text`` as a live status line while it lasts (the console's; nothing without one);
        ``as`` gives the status to update, or None."""
        return self.console.status(text) if self.console is not None else contextlib.nullcontext()

    def decide(self, key: str, text: str, warn: bool = False) -> None:
        """Record (and print once) a choice the run made about what to do or skip; ``warn``: as a warning (a part
        the user asked for is off)."""
        self.decisions[key] = text
        if self.console is not None:
            self.console.print(f"{'[yellow]warning:[/] ' if warn else ''}[dim]{key}:[/] {text}")

    def visible_weather(self) -> str | None:
        """The weather a person would see in the training photos (`weather.medium.visible_weather`), or None: θ says
        where the run degrades its scene or the conditions state the capture's weather; else the photos are taken
        as clear (the shipped storm record only stands in for a method that models weather)."""
        if not (self.degrade_kinds(self.scene) or self.config.conditions.stated):
            return None
        return self._weather_of_theta()

    def _weather_of_theta(self) -> str | None:
        """`weather.medium.visible_weather` of the run's θ at the scene's typical depth."""
        from metegs.weather.conditions import scene_metres_per_unit
        from metegs.weather.medium import typical_depth_m, visible_weather

        mpu = scene_metres_per_unit(self.config.conditions, self.scene.metric_scale)
        depth_m = typical_depth_m(self.dataset.cameras, self.scene.points, mpu)
        return visible_weather(self.weather_theta(self.scene), depth_m)

    def _decide_drop_rate(self) -> float:
        """`drop_gaussians` where the photos are clear; 0 where they show weather (`visible_weather`)."""
        rate = self.config.drop_gaussians
        if rate <= 0:
            self.decide("drop gaussians", "off (--drop-gaussians 0.1 turns it on)")
            return 0.0
        weather = self.visible_weather()
        if weather is not None:
            self.decide(
                "drop gaussians",
                f"off: {weather}: on photos with weather it lost more than it gained (3dgs and restoration + 3dgs "
                "on the Lund street under fog or rain + fog: -0.2 to -0.7 dB; blind MeteGS on the built-in scene: "
                "-1.0 dB)",
            )
            return 0.0
        self.decide(
            "drop gaussians",
            f"on: each training render leaves out a random share of the Gaussians, rising to {rate:.0%} by the "
            "last step",
        )
        return rate

    def weather_kinds(self) -> set[str]:
        """Weather kinds the method models (``degrade=auto`` synthesises these); plain 3DGS models none."""
        return {"rain", "fog"}

    def degrade_kinds(self, scene: SceneData) -> set[str]:
        """Kinds to synthesise on this scene (empty: train on its photos as they are)."""
        mode = self.config.degrade
        if mode == "off":
            return set()
        if mode == "auto":
            return self.weather_kinds() if scene.parser == "synthetic" else set()
        from metegs.weather.kinds import parse_kinds

        return set(parse_kinds(mode, "--degrade"))

    def weather_theta(self, scene: SceneData) -> Theta:
        """θ of the configured conditions for this scene's cameras (computed once)."""
        from metegs.weather.conditions import scene_metres_per_unit, theta_for_cameras

        if self.theta is None:
            mpu = scene_metres_per_unit(self.config.conditions, scene.metric_scale)
            self.theta = theta_for_cameras(self.config.conditions, scene.cameras, mpu)
        return self.theta

    def prepare_scene(self, scene: SceneData) -> SceneData:
        """The scene to train on: as parsed, or degraded in memory with the run's weather (``degrade``)."""
        kinds = self.degrade_kinds(scene)
        if not kinds:
            return scene
        from metegs.weather.conditions import describe, describe_conditions, scene_metres_per_unit
        from metegs.weather.degrade import degrade_scene
        from metegs.weather.kinds import join_kinds

        if scene.images is None and scene.image_paths is None:
            raise ConfigError("--degrade needs the scene's images")
        theta = self.weather_theta(scene)
        degraded, _ = degrade_scene(
            scene,
            theta,
            kinds=join_kinds(kinds),
            seed=self.config.seed,
            metres_per_unit=scene_metres_per_unit(self.config.conditions, scene.metric_scale),
            family=self.config.degrade_family,
        )
        self.decide(
            "degrade",
            f"{join_kinds(kinds)} synthesised on the clean views "
            f"({self.config.degrade_family} family): "
            + (describe(theta) if self.config.degrade_family == "physical" else describe_conditions(theta)),
        )
        return degraded

    def _default_run_dir(self) -> Path:
        c = self.config
        scene_name = Path(c.data).resolve().name if c.data is not None else "synthetic"
        name = c.experiment_name or datetime.now().strftime("%Y-%m-%d_%H%M%S")
        return Path(c.output_dir) / scene_name / c.method / name

    def scene_signature(self) -> dict:
        """What this run's checkpoints record of the scene (`check_compatible` compares it on resume): of all its
        cameras, so that another split or image size of the same scene is still recognised."""
        return scene_signature(self.scene.parser, len(self.dataset.cameras), scene_extent(self.dataset.cameras))

    def claim_run_dir(self) -> Path:
        """Create the default run folder, never reusing one: a folder that exists is an earlier run's. A resumed run
        continues in the folder of its checkpoint when that is the one named; a timestamp already taken (two runs
        started in the same second) gets the next free ``-2``, ``-3`` ... suffix; a taken ``--experiment-name`` is
        refused. ``os.mkdir`` makes each claim atomic between processes."""
        base = self.run_dir
        if self.resumed_from is not None and base.resolve() in self.resumed_from.resolve().parents:
            return base
        base.parent.mkdir(parents=True, exist_ok=True)
        for n in range(1, 1000):
            folder = base if n == 1 else base.with_name(f"{base.name}-{n}")
            try:
                folder.mkdir()
                return folder
            except FileExistsError:
                if self.config.experiment_name:
                    raise ConfigError(
                        f"{folder}: the run folder exists (an earlier run); choose another --experiment-name, or "
                        "continue that run with --load-checkpoint (its checkpoints/ folder)"
                    ) from None
        raise ConfigError(f"{base}: 999 run folders of this name exist; choose an --experiment-name")

    @functools.cached_property
    def initial_points(self) -> tuple[np.ndarray, np.ndarray] | None:
        """([P, 3] points, [P, 3] colours) the Gaussians start from: the scene's, else (photos and poses but no
        points) the points triangulated at their known poses (``model.triangulate``) where they cover enough of the
        training views (``model.sweep_below_coverage``), else a plane sweep of those views (``model.sweep_init``),
        beside which the triangulated points measure the scene's geometry (`triangulated_points`); either alone where
        the other is off or finds too few; None means random initialisation."""
        mc = self.config.model
        if mc.random_init:
            self.decide("init", "random Gaussians: --model.random-init")
            return None
        if self.scene.points is not None and len(self.scene.points) > 0:
            return self.scene.points, self.scene.point_colors
        photos, images, whose = self._triangulation_photos()
        if photos is None:
            return None
        if not mc.triangulate and not mc.sweep_init:
            self.decide("init", "random Gaussians: --model.no-triangulate --model.no-sweep-init")
            return None
        from metegs.config import scene_cache
        from metegs.data.triangulate import CACHE_DIR

        source = self.scene.source
        folder = None if source is None else (source if source.is_dir() else source.parent)
        cache = None if folder is None else scene_cache(folder, CACHE_DIR, "points")
        found, found_text = (
            self._triangulated(images, photos, whose, cache) if mc.triangulate else (None, "--model.no-triangulate")
        )
        if found is not None and not mc.sweep_init:
            self.decide("init", found_text)
            return found.points, found.colors
        from metegs.data.plane_sweep import view_coverage

        train_cameras = self.dataset.cameras[self.dataset.train_indices]
        covered = None  # the share of the training views that the triangulated points cover, where it decides
        if found is not None and mc.sweep_below_coverage < 1:
            covered = view_coverage(found.points, train_cameras)
            if covered >= mc.sweep_below_coverage:
                self.decide(
                    "init",
                    f"{found_text}; they cover {covered:.2f} of the training views (at least "
                    f"--model.sweep-below-coverage {mc.sweep_below_coverage:g}): dense enough to start from, no sweep",
                )
                return found.points, found.colors
        swept, swept_text = self._swept(images, photos, whose, cache)
        if swept is None and found is not None:
            self.decide("init", f"{found_text}; the plane sweep found too few: {swept_text}")
            return found.points, found.colors
        thin = ""
        if swept is not None and covered is not None:
            swept_covers = view_coverage(swept.points, train_cameras)
            if swept_covers <= covered:
                self.decide(
                    "init",
                    f"{found_text}; they cover {covered:.2f} of the training views, the plane sweep's "
                    f"{len(swept.points)} points no more ({swept_covers:.2f}): no gain in starting from it",
                )
                return found.points, found.colors
            thin = (
                f", covering {covered:.2f} of the training views (under {mc.sweep_below_coverage:g}; the sweep's "
                f"{swept_covers:.2f}),"
            )
        if swept is None:
            self.decide("init", f"random Gaussians: {found_text}; {swept_text}", warn=found_text.startswith("pycolmap"))
            return None
        self.swept_init = True
        why = found_text
        if found is not None:
            self.triangulated_points = found.points
            why = (
                f"the start of captures without points{' where triangulation covers too little' if thin else ''}; "
                f"the {len(found.points)} points triangulated from them{thin} measure the scene's geometry, "
                "--model.no-sweep-init starts from those"
            )
        self.decide(
            "init",
            f"{len(swept.points)} points from a plane sweep of {swept.num_views} training views' {whose} at their "
            f"known poses ({why}; cache {swept.cache})",
        )
        return swept.points, swept.colors

    def _triangulated(
        self, images: list[torch.Tensor], paths: list[Path], whose: str, cache: Path | None
    ) -> tuple[TriangulatedPoints | None, str]:
        """(points triangulated from the training views of ``images`` (one per view, read from ``paths``) at their
        known poses, or None; what they are, or why there are none: rain streaks and drops take SIFT's features, no
        pycolmap)."""
        from metegs.data.sfm import CLEAR_CONTRAST, SIFT_PEAK_THRESHOLD, photo_contrast
        from metegs.data.triangulate import contrast_options, triangulate_known_poses

        try:
            import pycolmap  # noqa: F401 - triangulation's one dependency that a trimmed install may lack
        except ImportError:
            return None, "pycolmap is not installed to triangulate points from the views (pip install pycolmap)"
        views = self.dataset.train_indices
        contrast = photo_contrast([images[i] for i in views])
        opts = contrast_options(contrast)
        try:
            with self.status(f"triangulating points from {len(views)} training views' {whose} (pycolmap)"):
                found = triangulate_known_poses([paths[i] for i in views], self.scene.cameras[views], cache, opts)
        except (RuntimeError, ValueError, OSError) as exc:
            return None, f"triangulation failed: {exc}"
        return found, (
            f"{len(found.points)} points triangulated from {found.num_views} training views' {whose} at their known "
            f"poses (mean reprojection error {found.reprojection_error_px:.2f} px; cache {found.cache})"
            + (
                f"; SIFT's contrast threshold {opts.peak_threshold:.2g}, COLMAP's times {opts.peak_threshold / SIFT_PEAK_THRESHOLD:.2f}: "
                f"the photos' brightness spans {contrast:.2f}, a clear photo's about {CLEAR_CONTRAST:g}"
                if opts.peak_threshold > 0
                else ""
            )
        )

    def _swept(
        self, images: list[torch.Tensor], paths: list[Path], whose: str, cache: Path | None
    ) -> tuple[TriangulatedPoints | None, str]:
        """(points of a plane sweep of the training views of ``images`` (one per view, read from ``paths``;
        `data.plane_sweep`), or None; why there are none)."""
        from metegs.data.plane_sweep import sweep_known_poses

        views = self.dataset.train_indices
        try:
            with self.status(f"sweeping depths in {len(views)} training views' {whose}"):
                found = sweep_known_poses(
                    [images[i] for i in views],
                    [paths[i] for i in views],
                    self.dataset.cameras[views],
                    cache,
                    max_points=self.config.model.init_random_points,
                    seed=self.config.seed,
                )
        except (RuntimeError, ValueError, OSError) as exc:
            return None, str(exc)
        return found, ""

    def _triangulation_photos(self) -> tuple[list[Path] | None, list[torch.Tensor], str]:
        """(the image files, one per view, that `initial_points` triangulates from, or None; the same images as
        loaded [H, W, 3]; what they are)."""
        return self.scene.image_paths, self.dataset.images, "photos"

    @property
    def random_init(self) -> bool:
        """True when the Gaussians start from random points (no scene or triangulated points, or ``model.random_init``);
        a resumed run keeps what its checkpoint says."""
        if self._random_init is None:
            self._random_init = self.initial_points is None
        return self._random_init

    def _initial_model(self) -> GaussianModel:
        mc = self.config.model
        if self.random_init:
            train_cams = self.dataset.cameras[self.dataset.train_indices]
            points = random_points_in_view_overlap(train_cams, mc.init_random_points, seed=self.config.seed)
            colors = np.random.default_rng(self.config.seed).random((len(points), 3), dtype=np.float32)
        else:
            points, colors = self.initial_points
        model = GaussianModel.from_points(
            points,
            colors,
            sh_degree=mc.sh_degree,
            init_opacity=mc.init_opacity,
            scale_multiplier=mc.init_scale_multiplier,
            device=self.device,
        )
        bad = non_finite_params(model)  # checkpoints and PLYs are checked where they are read; points are not
        if bad:
            raise DataError(self.scene.source, f"the initial Gaussians hold non-finite (NaN/Inf) {', '.join(bad)}")
        return model

    def _make_exposure(self) -> tuple[ViewExposure | None, torch.optim.Optimizer | None]:
        """The training views' gains and offsets and their optimiser, or (None, None) (`view_exposure`)."""
        choice = self.config.view_exposure
        rendered = self.scene.rendered
        if choice == "auto":
            why = "a rendered scene: its views share one exposure" if rendered else "photos may differ in exposure"
            self.decide("view_exposure", f"{'off' if rendered else 'on'} ({why}; --view-exposure on|off)")
        if choice == "off" or (choice == "auto" and rendered):
            return None, None
        train, cameras = self.dataset.train_indices, self.dataset.cameras
        # clean references too are photos, each exposed where its camera stood; where the weather varies more from
        # photo to photo than the exposure does, the learned tones say so and the test views keep the average
        nearest = nearest_training_rows(cameras, train)
        exposure = ViewExposure(train, len(cameras), self.device, nearest=nearest)
        return exposure, adam(exposure.parameters(), lr=self.config.optim.exposure_lr, eps=self.config.optim.eps)

    # --- one step ----------------------------------------------------------------------------------
    def background(self, training: bool) -> torch.Tensor:
        bg = self.config.background
        if bg == "random" and training:
            return torch.rand(3, device=self.device)
        return torch.ones(3, device=self.device) if bg == "white" else torch.zeros(3, device=self.device)

    def sh_degree_at(self, step: int) -> int:
        every = max(1, int(round(self.config.model.sh_degree_every * self.config.max_steps)))
        return min(step // every, self.model.max_sh_degree)

    def render(self, index: int, training: bool = False, background: torch.Tensor | None = None):
        """Render dataset view ``index`` with the current model (``training``: the step's Gaussians,
        `step_gaussians`)."""
        bg = self.background(training) if background is None else background
        settings = RenderSettings(background=bg, sh_degree=self.model.active_sh_degree)
        scene = self.step_gaussians() if training else self.model.activated()
        return self.rasterizer.render(scene, self.dataset.cameras[index], settings)

    def step_gaussians(self) -> GaussianSet:
        """The Gaussians every render of the current training step draws: all of them, less a random share that
        grows to `drop_gaussians` over the run (one draw per step, from the seed and the step, so a resumed run
        draws the same)."""
        gaussians = self.model.activated()
        rate = drop_rate_at(self.step, self.config.max_steps, self.drop_rate)
        if rate <= 0:
            return gaussians
        generator = torch.Generator().manual_seed(self.config.seed * 1_000_003 + self.step)
        return drop_gaussians(gaussians, rate, generator)

    def target(self, index: int, background: torch.Tensor) -> torch.Tensor:
        """The photo of view ``index`` [H, W, 3]; with masks, masked-out pixels take the background colour."""
        return self._masked(index, self.dataset.images[index], background)

    def reference(self, index: int, background: torch.Tensor) -> torch.Tensor:
        """What a render of view ``index`` is judged against [H, W, 3]: the clean image when the scene has one
        (weather-degraded datasets), else the photo; masked like `target`."""
        clean = self.dataset.clean_images
        return self._masked(index, self.dataset.images[index] if clean is None else clean[index], background)

    def _masked(self, index: int, image: torch.Tensor, background: torch.Tensor) -> torch.Tensor:
        """``image`` [H, W, 3] with view ``index``'s masked-out pixels set to ``background`` (no masks: as is)."""
        if self.dataset.masks is None:
            return image
        m = self.dataset.masks[index][..., None]
        return image * m + background * (1.0 - m)

    def setup_method(self) -> None:
        """Build what a method adds to plain 3DGS (weather, networks, extra losses); nothing here."""

    def make_densifier(self):
        """The run's densification strategy, built after `setup_method` (methods configure it through its options,
        never by changing it afterwards)."""
        return self.config.densify.setup(
            max_steps=self.config.max_steps, extent=self.extent, num_train_views=len(self.dataset.train_indices)
        )

    def _decide_densify_horizon(self) -> None:
        """Say so where `densify.horizon` keeps a longer run on a shorter run's densification schedule."""
        horizon = getattr(self.config.densify, "horizon", 0)
        schedule = getattr(self.densifier, "schedule", None)
        if 0 < horizon < self.config.max_steps and schedule is not None:
            at = schedule()
            self.decide(
                "densification horizon",
                f"{horizon} steps: refines from step {at['start']} to {at['stop']} as a {horizon}-step run does, "
                "then only optimises what it grew",
            )

    def schedule_step(self) -> None:
        """SH degree and position learning rate for the current step."""
        self.model.active_sh_degree = self.sh_degree_at(self.step)
        self.optimizers["means"].param_groups[0]["lr"] = means_lr_at(
            self.step, self.config.max_steps, self.config.optim, self.extent
        )

    def train_step(self, index: int) -> dict[str, float]:
        """One training step on view ``index``: schedule, render, losses, backward, densification statistics,
        optimisers, densification, stats. Methods fill its hooks (`photo_render`, `step_loss`, `step_optimizers`,
        `densify_step`) instead of repeating it."""
        self.schedule_step()
        bg = self.background(training=True)
        target = self.target(index, bg)
        render = self.photo_render(index, bg)
        stats: dict[str, float] = {}
        loss = self.step_loss(index, bg, render, target, stats)
        loss.backward()
        self.densifier.update_stats(self.model, render.out, render.num_scene)
        if render.clean is not None:
            self.densifier.update_stats(self.model, render.clean)
        for opt in self.step_optimizers():
            opt.step()
            opt.zero_grad(set_to_none=True)
        changes = self.densify_step()
        with torch.no_grad():
            mse = float(((render.rgb.clamp(0, 1) - target) ** 2).mean())
        stats.update({"loss": float(loss.detach()), "psnr": -10 * math.log10(max(mse, 1e-10))})
        return {**stats, **changes}

    def photo_render(self, index: int, background: torch.Tensor) -> StepRender:
        """The render of training view ``index`` that its photo judges: the scene's, as photographed."""
        out = self.render(index, training=True, background=background)
        return StepRender(self.as_photographed(out.rgb, index), out)

    def as_photographed(self, rgb: torch.Tensor, index: int) -> torch.Tensor:
        """A render [H, W, 3] of training view ``index`` in its photo's tone (`view_exposure`; else as it is)."""
        return rgb if self.exposure is None else self.exposure(rgb, index)

    def step_loss(
        self, index: int, background: torch.Tensor, render: StepRender, target: torch.Tensor, stats: dict[str, float]
    ) -> torch.Tensor:
        """The step's scalar loss (``stats`` takes what a method reports besides loss and PSNR): the photometric
        loss of the render against the photo here."""
        return self.loss_fn(render.rgb, target)

    def step_optimizers(self) -> list[torch.optim.Optimizer]:
        """Every optimiser a step updates: the Gaussians' and the views' exposure here."""
        extra = [] if self.exposure_optimizer is None else [self.exposure_optimizer]
        return [*self.optimizers.values(), *extra]

    def densify_step(self) -> dict[str, int]:
        """Densification after the optimisers (counts of what changed): the strategy's schedule here."""
        return self.densifier.step(self.model, self.optimizers, self.step)

    # --- the loop ----------------------------------------------------------------------------------
    def train(self) -> dict:
        """Run to ``max_steps``, evaluating and checkpointing on schedule; returns the final metrics."""
        c = self.config
        if self._claim_run_dir:
            self.run_dir = self.claim_run_dir()
            self._claim_run_dir = False
            if self.console is not None:
                self.console.print(f"[dim]run folder:[/] {self.run_dir}")
        else:
            self.run_dir.mkdir(parents=True, exist_ok=True)
        save_yaml(self.saved_config(), self.run_dir / "config.yml", header={"metegs_version": __version__})
        split = thread_split_counts(c.backend, c.torch_threads)
        if split is not None:
            self.decide("threads", f"torch's own ops on {split[0]}, the cpu kernels on {split[1]} (torch_threads)")
        self.save_decisions()
        eval_every = int(round(c.eval_every * c.max_steps)) if c.eval_every > 0 else 0
        order = self._view_order()
        last_good = self.resumed_from or self.save()
        try:
            with (
                TrainProgress(c.max_steps, start=self.step, enabled=c.progress, console=self.console) as progress,
                thread_split(c.backend, c.torch_threads),
            ):
                while self.step < c.max_steps:
                    t0 = time.perf_counter()
                    stats = self.train_step(next(order))
                    self.train_seconds += time.perf_counter() - t0
                    self.step += 1
                    self._check_finite(stats, last_good)
                    progress.update(self.step, stats, len(self.model))
                    for hook in self.step_hooks:
                        hook(self, stats)
                    if eval_every and self.step % eval_every == 0 and self.step < c.max_steps:
                        self.record_eval(quick=True)
                    if c.checkpoint_every and self.step % c.checkpoint_every == 0:
                        last_good = self.save()
        except KeyboardInterrupt:
            raise self._interrupted(last_good) from None
        self.save()
        return self.finish()

    def _interrupted(self, last_good: Path) -> Interrupted:
        """The error of a run stopped by Ctrl-C, after saving where it stood (if finite) to resume from."""
        if not non_finite_params(self.model):
            try:
                last_good = self.save()
            except KeyboardInterrupt:  # a second Ctrl-C while saving: the last scheduled checkpoint stands
                pass
        return Interrupted(
            f"training interrupted at step {self.step} of {self.config.max_steps}; continue it with "
            f"`--load-checkpoint {last_good}` (same method and scene)"
        )

    def _check_finite(self, stats: dict, last_good: Path) -> None:
        """Stop with the cause and a checkpoint to resume from when the loss or a parameter is no longer finite."""
        bad = non_finite_params(self.model)
        loss = stats.get("loss", 0.0)
        if not bad and np.isfinite(loss):
            return
        from metegs.errors import TrainingDiverged

        what = f"non-finite (NaN/Inf) {', '.join(bad)}" if bad else f"a non-finite loss ({loss})"
        fix = "lower learning rates (--optim.*-lr) or another --backend"
        if last_good == self.resumed_from or last_good.name != self._checkpoint_name(0):
            advice = f"Resume from {last_good} (--load-checkpoint) with {fix}."
        else:  # nothing learnt is worth resuming: the start itself is the checkpoint
            advice = f"No checkpoint after the start to resume from: train again with {fix}."
        raise TrainingDiverged(f"training diverged at step {self.step}: {what}. {advice}")

    def saved_config(self):
        """The config written to config.yml: every path absolute, so the run reopens from any folder."""
        return absolute_paths(self.config)

    def save_decisions(self) -> None:
        """decisions.json: what the run chose to do or skip and why, with the weather θ when there is one."""
        record = {"decisions": self.decisions, "theta": None if self.theta is None else self.theta.to_dict()}
        atomic_write_text(self.run_dir / "decisions.json", json.dumps(record, indent=2, default=str))

    def _view_order(self):
        rng = np.random.default_rng(self.config.seed + self.step)
        while True:
            yield from rng.permutation(self.dataset.train_indices).tolist()

    # --- evaluation and outputs --------------------------------------------------------------------
    @torch.no_grad()
    def render_views(self, indices: list[int]) -> list[torch.Tensor]:
        """Renders [H, W, 3] of dataset views ``indices`` as their photos would show them (`ViewExposure`)."""
        return [self.as_photographed(self.render(i).rgb, i).clamp(0, 1) for i in indices]

    def record_eval(self, quick: bool) -> dict:
        """Evaluate the test views (PSNR/SSIM; LPIPS too unless ``quick``) and append to the history."""
        from metegs.eval.metrics import evaluate_images

        idx = self.dataset.test_indices or self.dataset.train_indices
        preds = self.render_views(idx)
        bg = self.background(training=False)
        lpips_model, reason = (None, "skipped during training") if quick else self._lpips()
        m = evaluate_images(preds, [self.reference(i, bg) for i in idx], lpips_model=lpips_model, lpips_reason=reason)
        entry = {
            "step": self.step,
            "train_seconds": round(self.train_seconds, 3),
            "num_gaussians": len(self.model),
            "psnr": m["psnr"],
            "ssim": m["ssim"],
        }
        self.history.append(entry)
        return m

    def _lpips(self):
        from metegs.eval.lpips import try_load_lpips

        return try_load_lpips(self.config.lpips_net, allow_download=self.config.lpips_download, device=self.device)

    def finish(self) -> dict:
        """Final evaluation; writes metrics.json (first: a full disk later loses no score), test renders and
        scene.ply. Returns the metrics."""
        from metegs.gaussians.ply import save_ply

        if self.exposure is not None:
            self._decide_test_tone()
        self.save_decisions()  # with those made while training (MeteGS's `low-quantile fit`)
        m = self.record_eval(quick=False)
        idx = self.dataset.test_indices or self.dataset.train_indices
        split = "test" if self.dataset.test_indices else "train"
        metrics = {
            "method": self.config.method,
            "scene": str(self.config.data or "synthetic"),
            "backend": self.config.backend,
            "device": str(self.device),
            "split": split,
            "reference": "clean" if self.dataset.clean_images is not None else "photo",
            "num_views": len(idx),
            "psnr": m["psnr"],
            "ssim": m["ssim"],
            "lpips": m["lpips"],
            "lpips_net": m.get("lpips_net"),
            "lpips_reason": m.get("lpips_reason"),
            "streak_energy": m["streak_energy"],
            "contrast_ratio": m["contrast_ratio"],
            "num_gaussians": len(self.model),
            "steps": self.step,
            "train_seconds": round(self.train_seconds, 2),
            "wall_seconds": round(time.perf_counter() - self._created, 2),
            "image_size": [int(self.dataset.cameras.width[0]), int(self.dataset.cameras.height[0])],
            "test_tone": self.test_tone(),
            **self.extra_metrics(),
            "per_view": m.get("per_view"),
            "history": self.history,
        }
        write_result(self.run_dir / "metrics.json", json.dumps(metrics, indent=2))
        if self.config.save_renders:
            self.save_renders(idx, split)
        save_ply(self.model, self.run_dir / "scene.ply", **self.ply_layout())
        return metrics

    def test_tone(self) -> str | None:
        """The tone test views are scored in: "nearest" (their nearest training photo's), "average", or None where
        the run learns no per-photo exposure."""
        if self.exposure is None:
            return None
        return "nearest" if self.exposure.tones_from_nearest() else "average"

    def _decide_test_tone(self) -> None:
        """Record which tone the test views are scored in (`ViewExposure.tones_from_nearest`)."""
        near, average = self.exposure.tone_errors()
        chosen = "their nearest training photo's" if near < average else "the photos' average"
        self.decide(
            "test_tone",
            f"{chosen} (each training photo's tone from its nearest other photo's: {near:.4f} RMS; from the "
            f"others' average: {average:.4f})",
        )

    def extra_metrics(self) -> dict:
        """Method-specific entries of metrics.json (none for plain 3DGS)."""
        return {}

    def ply_layout(self) -> dict:
        """How the scene's PLY files are written (`save_ply` keywords): turned so that splat viewers show the scene
        upright (`metegs.gaussians.rotate`; `load_ply` turns it back), with header comments saying so."""
        from metegs.gaussians.rotate import upright_rotation

        rotation = upright_rotation(self.scene.up)
        up = rotation @ np.asarray(self.scene.up, np.float64)
        axis = "xyz"[int(np.argmax(np.abs(up)))]
        return {"comments": [f"Vertical Axis: {axis}", "SplatRenderMode: default"], "world_to_file": rotation}

    def save_renders(self, indices: list[int], split: str) -> None:
        from metegs.data.images import save_image

        folder = self.run_dir / "renders" / split
        for i, img in zip(indices, self.render_views(indices)):
            name = Path(self.dataset.names[i]).stem
            save_image(folder / f"{name}.png", img)
            save_image(folder / f"{name}_gt.png", self.reference(i, self.background(training=False)))

    # --- checkpoints -------------------------------------------------------------------------------
    def save(self) -> Path:
        payload = {
            "step": self.step,
            "params": self.model.state_tensors(),
            "sh_degree": self.model.max_sh_degree,
            "optimizers": {k: o.state_dict() for k, o in self.optimizers.items()},
            "densifier": self.densifier.state_dict(),
            "exposure": None
            if self.exposure is None
            else {"state": self.exposure.state_dict(), "optimizer": self.exposure_optimizer.state_dict()},
            "history": self.history,
            "train_seconds": self.train_seconds,
            "random_init": self.random_init,
            "swept_init": self.swept_init,
            "triangulated_points": None
            if self.triangulated_points is None
            else torch.as_tensor(self.triangulated_points, dtype=torch.float32),
            "metegs_version": __version__,
            "method": self.config.method,
            "scene": self.scene_signature(),
            **self.extra_state(),
        }
        return save_checkpoint(self.run_dir / "checkpoints" / self._checkpoint_name(self.step), payload)

    @staticmethod
    def _checkpoint_name(step: int) -> str:
        return f"step-{step:06d}.ckpt"

    def load(self, path: Path) -> None:
        """Resume from a checkpoint: parameters (any count), optimiser moments, statistics, step."""
        path = resolve_checkpoint(path)
        ckpt = load_checkpoint(path, self.device)
        check_compatible(ckpt, path, self.config.method, self.scene_signature())
        self.model = self._checkpoint_model(ckpt)
        self.optimizers = make_optimizers(self.model.params, self.config.optim, self.extent)
        self._restore_state(ckpt)

    def _checkpoint_model(self, ckpt: dict) -> GaussianModel:
        """The scene Gaussians of a loaded checkpoint, on the run's device."""
        return GaussianModel.from_state(ckpt["params"], ckpt["sh_degree"]).to(self.device)

    def _restore_state(self, ckpt: dict) -> None:
        """Everything of a loaded checkpoint but the Gaussians (already `_checkpoint_model`'s, with fresh optimisers)."""
        for k, o in self.optimizers.items():
            o.load_state_dict(ckpt["optimizers"][k])
        self.densifier.load_state_dict(ckpt.get("densifier", {}))
        saved = ckpt.get("exposure")
        if self.exposure is not None and saved is not None:
            self.exposure.load_state_dict(saved["state"])
            self.exposure_optimizer.load_state_dict(saved["optimizer"])
        self.step = int(ckpt["step"])
        # the degree the last step rendered with: a run resumed at its end evaluates as it did (0 before a step)
        self.model.active_sh_degree = self.sh_degree_at(max(self.step - 1, 0))
        self.history = list(ckpt.get("history", []))
        self.train_seconds = float(ckpt.get("train_seconds", 0.0))
        self.load_extra_state(ckpt)

    def extra_state(self) -> dict:
        """What a method adds to a checkpoint besides the scene Gaussians (none for plain 3DGS)."""
        return {}

    def load_extra_state(self, ckpt: dict) -> None:
        """Restore what `extra_state` saved."""
