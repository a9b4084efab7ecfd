"""`fog-analytic`: the atmospheric scattering model applied from the rendered depth.

C = C_scene·t + A·(1 − α·t), t = exp(−β·d), with d the distance along the pixel's ray (metres; the
rendered z-depth times the ray's length per unit z) and α the rendered opacity: the part of a pixel
not covered by Gaussians looks into the distance (t = 0) and shows the airlight A. β per colour
channel comes from θ_fog (visibility by the 5 % rule, minus the rain's share, plus the rain veil);
β and A are learnable (log-β, logit-A) starting from θ. Where every view sees the scene at about the same
distance (forward-facing captures), a hazy scene under less fog fits the photos as well as the true fog over the
clean scene, and a free β drifts down while the scene takes the haze in: there (``record_prior`` auto, decided by
the trainer) a prior holds ln β near θ's; where the distances differ across views the photos measure β: beside
clean references it stays free; blind, where fog explains the photos' colours at the scene's points, it starts at,
and the prior holds it near, their measure there (`hold_at`, `metegs.weather.medium_fit`), since there too the scene
can take the haze in; unless heavy rain falls through dense fog: the light it adds drowns that measure, and θ's β is
held.

Where the photos measure the medium, the fog also learns how it thins with height above the ground, starting
uniform, or, blind, where the points' measure holds β and reads it thinning upwards, at their profile:
β(x) = β·exp(−k·h(x)), h the height in metres over the cameras' mean and k learnable, so the optical depth of a ray
from height h_c, rising u per metre, to distance d is β·d·exp(−k·h_c)·(1 − e^{−k·u·d})/(k·u·d), exact. Without the
profile, where the true fog is thinner than a uniform one the scene can only darken itself by moving Gaussians in front
of the fog, next to the camera: floaters in the clean render.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Annotated, Literal

import torch

from metegs.gaussians.sh import eval_sh, num_sh_bases
from metegs.meteo.mapping import Theta
from metegs.render.base import RenderOutput, RenderSettings
from metegs.validate import NON_NEGATIVE
from metegs.weather.base import SynthesisRequest, WeatherModel, WeatherModelConfig, WeatherScene
from metegs.weather.medium import choose_airlight, fog_called_for, fog_extinction_rgb


def camera_rays(camera, height: int, width: int) -> torch.Tensor:
    """[H, W, 3] each pixel's ray in camera axes per unit of camera z, ((x − cx)/fx, (y − cy)/fy, 1). camera: one
    view."""
    fx, fy, cx, cy = (float(v[0]) for v in (camera.fx, camera.fy, camera.cx, camera.cy))
    ys, xs = torch.meshgrid(torch.arange(height) + 0.5, torch.arange(width) + 0.5, indexing="ij")
    return torch.stack([(xs - cx) / fx, (ys - cy) / fy, torch.ones_like(xs)], dim=-1)


def ray_lengths(camera, height: int, width: int) -> torch.Tensor:
    """Length of each pixel ray per unit of camera z. camera: one view -> [H, W]."""
    rays = camera_rays(camera, height, width)
    return torch.sqrt(rays[..., 0] ** 2 + rays[..., 1] ** 2 + 1.0)


def fog_composite(
    color: torch.Tensor, alpha: torch.Tensor, distance_m: torch.Tensor, beta_rgb: torch.Tensor, airlight: torch.Tensor
) -> torch.Tensor:
    """Fogged image. color [H, W, 3] premultiplied (no background), alpha [H, W], distance_m [H, W],
    beta_rgb [3] 1/m, airlight [3] -> [H, W, 3]."""
    t = torch.exp(-distance_m[..., None] * beta_rgb)
    return color * t + airlight * (1.0 - alpha[..., None] * t)


def height_profile(
    k_per_m: torch.Tensor,
    camera_height: torch.Tensor,
    rise: torch.Tensor,
    distance_m: torch.Tensor,
    metres_per_unit: float = 1.0,
) -> torch.Tensor:
    """Optical depth of rays under β(h) = β·exp(−k·h) over that of a uniform β at the reference height h = 0:
    exp(−k·h_c)·(1 − e^{−x})/x with x = k·u·d (``camera_height`` h_c of each ray's camera over the reference, in
    units of ``metres_per_unit`` metres; ``rise`` u, metres of height per metre of ray; ``distance_m`` d). All
    broadcast to one shape -> that shape."""
    x = k_per_m * rise * distance_m
    small = x.abs() < 1e-4
    safe = torch.where(small, torch.ones_like(x), x)
    mean_along = torch.where(small, 1.0 - x / 2.0, -torch.expm1(-safe) / safe)
    return torch.exp((-k_per_m * camera_height * metres_per_unit).clamp(-20.0, 20.0)) * mean_along


@dataclass
class FogAnalyticConfig(WeatherModelConfig):
    """Analytic fog from the rendered depth (any rasteriser; no Gaussians)."""

    _target: type = field(default_factory=lambda: FogAnalytic, repr=False)
    airlight: tuple[float, float, float] | None = None
    """Airlight A in [0, 1] RGB; None: θ's, else estimated from the scene's images (dark channel prior)."""
    include_rain_veil: bool = True
    """Add the rain's extinction beyond the streaks (θ_fog.beta_rain_per_m) when it rains."""
    learnable: bool = True
    """Expose β and A as trainable parameters."""
    record_prior: Literal["auto", "on", "off"] = "auto"
    """Hold β near the met record's while training: auto = on where the photos cannot measure β (every view sees
    the scene from about the same distance, as in forward-facing captures, or, blind, heavy rain falls through dense
    fog), off where they can."""
    record_prior_weight: Annotated[float, NON_NEGATIVE] = 0.1
    """Weight of that prior, record_prior_weight · mean((ln β − ln β_θ)²)."""
    layered: bool = True
    """Where the photos measure β (the record prior off), also learn how β changes with height."""
    patches: Annotated[int, NON_NEGATIVE] = 4
    """Where the views cannot measure β (every view at one distance) and the dark-channel prior (blind) or clean
    references measure the fog instead, also learn per view a coarse grid of this many cells along the longer side
    that scales the optical depth: fog that varies in patches (0: off)."""
    patches_weight: Annotated[float, NON_NEGATIVE] = 0.01
    """Weight of the patches' prior, mean of their squared log-scales (they stay at 1 unless the photos pay)."""
    airlight_degree: Annotated[int, NON_NEGATIVE] = 0
    """Opt-in (e.g. 2): where the views measure the fog, the airlight also learns how it changes with the viewing
    direction (brighter towards the horizon or the sun), real spherical harmonics up to this degree in world axes
    (0: one airlight for every direction; benchmark.md, "The airlight along each direction")."""
    airlight_weight: Annotated[float, NON_NEGATIVE] = 0.001
    """Weight of that prior, mean of the squared coefficients (logit units; they stay at 0 unless the photos pay)."""

    def for_synthesis(self, request: SynthesisRequest) -> FogAnalyticConfig | None:
        """The medium of fog, and of rain beyond the streaks' reach (its veil, weather-physics.md) when it rains: fixed,
        with θ's airlight or the one estimated from the clean views."""
        rains = "rain" in request.kinds and request.theta.rain.active
        if "fog" not in request.kinds and not rains:
            return None
        airlight = self.airlight
        if airlight is None and request.theta.fog.airlight_rgb is None:
            airlight = request.airlight()
        return dataclasses.replace(self, airlight=airlight, include_rain_veil="rain" in request.kinds, learnable=False)


def world_directions(camera, height: int, width: int) -> torch.Tensor:
    """[H, W, 3] unit world direction of each pixel's ray. camera: one view."""
    rays = camera_rays(camera, height, width) @ camera.camera_to_worlds[0, :3, :3].float().T
    return rays / rays.norm(dim=-1, keepdim=True)


def direction_basis(degree: int, directions: torch.Tensor) -> torch.Tensor:
    """Real spherical harmonics of degrees 1..``degree`` (the 3DGS convention) at unit ``directions`` [..., 3] ->
    [..., (degree + 1)² − 1]; the constant one is left out (the airlight's own level)."""
    count = num_sh_bases(degree)
    flat = directions.reshape(-1, 3)
    unit = torch.eye(count, dtype=flat.dtype, device=flat.device)[1:, :, None]  # [K-1, K, 1]: one basis each
    columns = [eval_sh(degree, unit[k : k + 1], flat)[:, 0] - 0.5 for k in range(count - 1)]
    return torch.stack(columns, dim=-1).reshape(*directions.shape[:-1], count - 1)


def airlight_logit(airlight: torch.Tensor) -> torch.Tensor:
    """[3] the learnable logit of an airlight [3], kept off 0 and 1 (where the logit is infinite)."""
    return torch.logit(airlight.float().clamp(1e-3, 1 - 1e-3))


def patch_grid(cameras, cells: int) -> tuple[int, int, int]:
    """(views, rows, columns) of a per-view grid with ``cells`` along the longer image side (0: an empty grid)."""
    if cells <= 0:
        return (len(cameras), 0, 0)
    w, h = float(cameras.width.max()), float(cameras.height.max())
    short = max(1, round(cells * min(w, h) / max(w, h)))
    return (len(cameras), short, cells) if w >= h else (len(cameras), cells, short)


class FogAnalytic(WeatherModel):
    """Exponential fog from depth: ``apply`` turns the rendered view into the foggy one."""

    stage = "medium"
    name = "fog-analytic"
    kind = "fog"

    def __init__(self, config: FogAnalyticConfig, theta: Theta, scene: WeatherScene):
        super().__init__(theta, scene)
        self.config = config
        beta = fog_extinction_rgb(theta, config.include_rain_veil).float()
        self._active = fog_called_for(theta, config.include_rain_veil)
        a = choose_airlight(config.airlight, theta, scene)
        self.log_beta = torch.nn.Parameter(torch.log(beta.clamp_min(1e-12)), requires_grad=config.learnable)
        # θ's β for the prior: moves with the model, stays out of checkpoints (their keys are unchanged)
        self.register_buffer("record_log_beta", self.log_beta.detach().clone(), persistent=False)
        self.register_buffer("prior_log_beta", self.log_beta.detach().clone(), persistent=False)
        """ln β the prior holds it near: θ's, or the photos' measure at the scene's points (`hold_at`)."""
        self.measured_beta: float | None = None
        """β (1/m) the photos show at the scene's points, where the trainer measured it (`hold_at`)."""
        self.use_record_prior = config.record_prior == "on"
        """Whether `prior` holds β near θ's (the trainer decides ``auto`` from the views' distances)."""
        self.airlight_logit = torch.nn.Parameter(airlight_logit(a), requires_grad=config.learnable)
        self.height_rate = torch.nn.Parameter(torch.zeros(()), requires_grad=False)
        """100·k: ln β falls by this much per 100 m of height (0: uniform; learned by `learn_layers`; per 100 m so
        that an optimiser's steps of ~0.01 move it by a small fraction of a realistic 0.01-0.1 per metre)."""
        self.patch_log_scale = torch.nn.Parameter(torch.zeros(patch_grid(scene.cameras, config.patches)), False)
        """[V, gh, gw] per view, ln of the factor on the optical depth in each cell of a coarse grid (`patches`)."""
        directional = max(0, num_sh_bases(config.airlight_degree) - 1)
        self.airlight_sh = torch.nn.Parameter(torch.zeros(directional, 3), requires_grad=False)
        """[K, 3] coefficients of the airlight's logit on the spherical harmonics of degree 1..``airlight_degree``
        of the world direction (learned by `learn_directions`)."""
        self._directions: dict[int, torch.Tensor] = {}
        up = scene.up.float() / scene.up.float().norm().clamp_min(1e-12)
        self.register_buffer("up", up, persistent=False)
        self.register_buffer("reference_height", (scene.cameras.centers.float() @ up).mean(), persistent=False)
        self._rays: dict[int, torch.Tensor] = {}

    def hold_at(self, beta_per_m: float, height_rate: float = 0.0) -> None:
        """Start β at ``beta_per_m`` (1/m at the cameras' mean height, the photos' measure) and centre the prior there,
        θ's ratios between the colour channels kept; the height profile starts at ``height_rate`` (100·k)."""
        shift = math.log(beta_per_m) - float(self.record_log_beta.mean())
        with torch.no_grad():
            self.log_beta.copy_(self.record_log_beta + shift)
            self.prior_log_beta.copy_(self.record_log_beta + shift)
            self.height_rate.fill_(height_rate)
        self.measured_beta = beta_per_m

    def set_airlight(self, airlight: torch.Tensor) -> None:
        """Put the airlight at ``airlight`` [3] in (0, 1) (whether it learns on is left as it is)."""
        with torch.no_grad():
            self.airlight_logit.copy_(airlight_logit(airlight).to(self.airlight_logit))

    def learn_layers(self) -> bool:
        """Let β change with height from now on, when ``layered`` and ``learnable`` allow it -> whether it does."""
        if not (self.config.layered and self.config.learnable):
            return False
        self.height_rate.requires_grad_(True)
        return True

    def learn_patches(self) -> bool:
        """Let the optical depth vary in patches per view from now on (`patches` > 0, learnable) -> whether it does."""
        if not (self.config.patches > 0 and self.config.learnable):
            return False
        self.patch_log_scale.requires_grad_(True)
        return True

    def learn_directions(self) -> bool:
        """Let the airlight change with the viewing direction from now on (`airlight_degree` > 0, learnable) ->
        whether it does."""
        if not (self.config.airlight_degree > 0 and self.config.learnable):
            return False
        self.airlight_sh.requires_grad_(True)
        return True

    @property
    def directional(self) -> bool:
        """Whether the airlight changes with the viewing direction (learned, or loaded non-zero)."""
        return self.airlight_sh.requires_grad or bool(self.airlight_sh.detach().any())

    def airlight_toward(self, view: int, height: int, width: int) -> torch.Tensor:
        """The airlight each pixel of view ``view`` looks into: [H, W, 3] where it changes with the direction, else
        the one airlight [3]."""
        if not self.directional:
            return self.airlight
        basis = self._directions.get(view)
        if basis is None or basis.shape[:2] != (height, width):  # the cameras are fixed: one basis per view
            directions = world_directions(self.scene.cameras[view], height, width)
            basis = direction_basis(self.config.airlight_degree, directions)
            self._directions[view] = basis
        return torch.sigmoid(self.airlight_logit + basis.to(self.airlight_sh) @ self.airlight_sh)

    @property
    def patchy(self) -> bool:
        """Whether the optical depth varies in patches per view (learned, or loaded non-zero)."""
        return self.patch_log_scale.requires_grad or bool(self.patch_log_scale.detach().any())

    @property
    def layered(self) -> bool:
        """Whether β may change with height (learned, or loaded non-zero)."""
        return self.height_rate.requires_grad or bool(self.height_rate.detach() != 0)

    @property
    def active(self) -> bool:
        return self._active

    @property
    def beta_rgb(self) -> torch.Tensor:
        """[3] extinction per metre."""
        return torch.exp(self.log_beta)

    @property
    def extinction_per_m(self) -> float:
        """The largest of the three β (1/m): how strongly the medium veils the scene."""
        return float(self.beta_rgb.detach().max())

    @property
    def airlight(self) -> torch.Tensor:
        """[3] airlight in (0, 1)."""
        return torch.sigmoid(self.airlight_logit)

    def apply(self, rgb: torch.Tensor, out: RenderOutput, view: int, settings: RenderSettings) -> torch.Tensor:
        background = settings.background_tensor(rgb)
        color = rgb - (1.0 - out.alpha)[..., None] * background  # premultiplied scene colour
        distance = self.optical_distance(out.depth, out.alpha, view)
        airlight = self.airlight_toward(view, *distance.shape)
        return fog_composite(color, out.alpha, distance, self.beta_rgb.to(rgb), airlight.to(rgb))

    def optical_distance(self, depth: torch.Tensor, alpha: torch.Tensor, view: int) -> torch.Tensor:
        """[H, W] metres along each pixel's ray to the rendered surface, times the height profile's factor (0 where
        nothing is rendered). depth [H, W] rendered z-depth (scene units), alpha [H, W] rendered opacity."""
        if view not in self._rays:  # the cameras are fixed: one ray-length map per view
            self._rays[view] = ray_lengths(self.scene.cameras[view], depth.shape[0], depth.shape[1])
        rays = self._rays[view].to(depth)
        distance = depth * rays * self.scene.metres_per_unit
        distance = torch.where(alpha > 1e-6, distance, torch.zeros_like(distance))
        if self.layered:
            distance = distance * self.height_factor(self.rise(view, rays), distance, view)
        if self.patchy:
            grid = self.patch_log_scale[view].to(distance)[None, None]
            scale = torch.nn.functional.interpolate(grid, size=distance.shape, mode="bilinear", align_corners=False)
            distance = distance * torch.exp(scale[0, 0])
        return distance

    def dehaze(
        self, photo: torch.Tensor, out: RenderOutput, view: int, min_transmission: float
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The photo with this medium taken out along the rendered (detached) depth, J = (I − A)/t + A, and where
        that is meaningful: the surface rendered (opacity > 0.5) and seen through at least ``min_transmission``.
        photo [H, W, 3] -> (J [H, W, 3], valid [H, W] bool). Only β's level carries gradients, all three channels
        together: a dark channel is one channel's in each patch, so it cannot tell β's colour, which is the photos'
        to fit like the airlight (dehazing estimates A before the transmission) and the geometry."""
        alpha = out.alpha.detach()
        distance = self.optical_distance(out.depth.detach(), alpha, view)
        level = self.log_beta.mean()
        beta = torch.exp(level + (self.log_beta - level).detach())
        t = torch.exp(-distance[..., None] * beta.to(photo))
        valid = (alpha > 0.5) & (t.detach().amin(-1) >= min_transmission)
        airlight = self.airlight_toward(view, *distance.shape).detach().to(photo)
        return (photo - airlight) / t.clamp_min(min_transmission) + airlight, valid

    def seen_through(self, colour: torch.Tensor, alpha: torch.Tensor, depth: torch.Tensor, view: int) -> torch.Tensor:
        """``colour·t + A·α·(1 − t)``, t = exp(−β·d) along each pixel's ray to ``depth`` (see `WeatherModel`)."""
        H, W = depth.shape
        rays = self._rays.get(view)
        if rays is None or rays.shape != (H, W):
            rays = ray_lengths(self.scene.cameras[view], H, W)
        distance = depth * rays.to(depth) * self.scene.metres_per_unit
        if self.layered:
            distance = distance * self.height_factor(self.rise(view, rays), distance, view)
        t = torch.exp(-distance[..., None] * self.beta_rgb.detach().to(colour))
        airlight = self.airlight_toward(view, H, W).detach().to(colour)
        return colour * t + airlight * alpha[..., None] * (1.0 - t)

    def rise(self, view: int, rays: torch.Tensor) -> torch.Tensor:
        """[H, W] height gained per metre along each pixel's ray of view ``view``, from its ray lengths per unit of
        camera z ``rays`` [H, W] (`ray_lengths`): the up vector in camera axes dotted with the unit ray."""
        cam = self.scene.cameras[view]
        h, w = rays.shape
        up = cam.camera_to_worlds[0, :3, :3].T.to(rays) @ self.up.to(rays)  # up in camera axes
        fx, fy, cx, cy = (float(v[0]) for v in (cam.fx, cam.fy, cam.cx, cam.cy))
        a = (torch.arange(w, device=rays.device, dtype=rays.dtype) + 0.5 - cx) / fx
        b = (torch.arange(h, device=rays.device, dtype=rays.dtype) + 0.5 - cy) / fy
        return (up[0] * a[None, :] + up[1] * b[:, None] + up[2]) / rays

    def height_factor(self, rise: torch.Tensor, distance_m: torch.Tensor, view: int) -> torch.Tensor:
        """[H, W] `height_profile` of view ``view``'s rays (u ``rise`` [H, W], d ``distance_m`` [H, W])."""
        camera_height = (
            self.scene.cameras.centers[view].to(distance_m) @ self.up.to(distance_m)
        ) - self.reference_height
        k = self.height_rate.to(distance_m) / 100.0
        return height_profile(k, camera_height, rise, distance_m, self.scene.metres_per_unit)

    def prior(self, view: int) -> torch.Tensor | None:
        """record_prior_weight · mean((ln β − ln β_θ)²) when the record prior is on (β_θ the photos' measure where
        `hold_at` set one), plus patches_weight · mean of the
        view's squared patch log-scales when they learn; None when neither."""
        terms = []
        if self.use_record_prior and self.log_beta.requires_grad and self.config.record_prior_weight > 0:
            terms.append(self.config.record_prior_weight * ((self.log_beta - self.prior_log_beta) ** 2).mean())
        if self.patch_log_scale.requires_grad and self.config.patches_weight > 0:
            terms.append(self.config.patches_weight * (self.patch_log_scale[view] ** 2).mean())
        if self.airlight_sh.requires_grad and self.config.airlight_weight > 0:
            terms.append(self.config.airlight_weight * (self.airlight_sh**2).mean())
        return sum(terms) if terms else None

    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        """As torch's; a checkpoint saved before β could change with height loads as a uniform medium, and one whose
        patches never learned loads into any grid."""
        state = dict(state_dict)
        state.setdefault("height_rate", torch.zeros_like(self.height_rate))
        saved_sh = state.get("airlight_sh")
        if saved_sh is None or (saved_sh.shape != self.airlight_sh.shape and not saved_sh.any()):  # one airlight
            state["airlight_sh"] = torch.zeros_like(self.airlight_sh)
        saved = state.get("patch_log_scale")
        if saved is None or (saved.shape != self.patch_log_scale.shape and not saved.any()):  # unlearned: any grid
            state["patch_log_scale"] = torch.zeros_like(self.patch_log_scale)
        return super().load_state_dict(state, strict, assign)

    def summary(self) -> dict:
        """Learned β (1/m, RGB at the cameras' mean height) and airlight next to θ's β; with layers, β's scale
        height (m; negative: denser upwards)."""
        out = {
            "beta_per_m": [round(float(b), 6) for b in self.beta_rgb.detach()],
            "record_beta_per_m": [round(float(b), 6) for b in self.record_log_beta.exp()],
            "airlight": [round(float(a), 4) for a in self.airlight.detach()],
        }
        if self.measured_beta is not None:
            out["measured_beta_per_m"] = round(self.measured_beta, 6)
        if self.layered:
            k = float(self.height_rate.detach()) / 100.0
            out["scale_height_m"] = None if k == 0 else round(1.0 / k, 1)
        if self.directional:
            seen = self.airlight_over_sphere()
            out["airlight_range"] = [
                [round(float(a), 4) for a in seen.amin(0)],
                [round(float(a), 4) for a in seen.amax(0)],
            ]
        return out

    def airlight_over_sphere(self, count: int = 256) -> torch.Tensor:
        """[count, 3] the airlight towards ``count`` directions spread evenly over the sphere (a Fibonacci lattice)."""
        i = torch.arange(count, dtype=torch.float64) + 0.5
        z = 1.0 - 2.0 * i / count
        phi = i * math.pi * (3.0 - math.sqrt(5.0))
        r = torch.sqrt(1.0 - z**2)
        directions = torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], dim=-1)
        basis = direction_basis(self.config.airlight_degree, directions).to(self.airlight_sh)
        return torch.sigmoid(self.airlight_logit + basis @ self.airlight_sh).detach()

    def transmittance(self, points: torch.Tensor, view: int) -> torch.Tensor:
        """[N] transmittance of the fog between view ``view``'s camera and world points [N, 3] (exp(−β·d) scaled by
        the height profile when layered), averaged over R, G, B."""
        distance = self.scene.distance_m(points, view)
        if self.layered:
            offset = points - self.scene.cameras.centers[view].to(points)
            rise = (offset @ self.up.to(points)) / offset.norm(dim=-1).clamp_min(1e-12)
            distance = distance * self.height_factor(rise, distance, view).detach()
        return torch.exp(-distance[:, None] * self.beta_rgb.detach().to(points)).mean(-1)
