"""`fog-analytic`: the atmospheric scattering model applied from the rendered depth.

C = C_scene·t + A·(1 − α·t), t = exp(−β·d), with d the distance along the pixel's ray (metres; the
rendered z-depth times the ray's length per unit z) and α the rendered opacity: the part of a pixel
not covered by Gaussians looks into the distance (t = 0) and shows the airlight A. β per colour
channel comes from θ_fog (visibility by the 5 % rule, minus the rain's share, plus the rain veil);
β and A are learnable (log-β, logit-A) starting from θ.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from metegs.meteo.mapping import Theta
from metegs.render.base import RenderOutput, RenderSettings
from metegs.weather.base import WeatherModel, WeatherModelConfig, WeatherScene
from metegs.weather.medium import choose_airlight, fog_called_for, fog_extinction_rgb


def ray_lengths(camera, height: int, width: int) -> torch.Tensor:
    """Length of each pixel ray per unit of camera z. camera: one view -> [H, W]."""
    fx, fy, cx, cy = (float(v[0]) for v in (camera.fx, camera.fy, camera.cx, camera.cy))
    ys, xs = torch.meshgrid(torch.arange(height) + 0.5, torch.arange(width) + 0.5, indexing="ij")
    return torch.sqrt(((xs - cx) / fx) ** 2 + ((ys - cy) / fy) ** 2 + 1.0)


def ray_directions(camera, height: int, width: int) -> torch.Tensor:
    """Unit world direction of each pixel ray. camera: one view -> [H, W, 3]."""
    fx, fy, cx, cy = (float(v[0]) for v in (camera.fx, camera.fy, camera.cx, camera.cy))
    ys, xs = torch.meshgrid(torch.arange(height) + 0.5, torch.arange(width) + 0.5, indexing="ij")
    d = torch.stack([(xs - cx) / fx, (ys - cy) / fy, torch.ones_like(xs)], dim=-1)
    d = d @ camera.camera_to_worlds[0, :3, :3].float().T
    return d / d.norm(dim=-1, keepdim=True)


def fog_composite(
    color: torch.Tensor, alpha: torch.Tensor, distance_m: torch.Tensor, beta_rgb: torch.Tensor, airlight: torch.Tensor
) -> torch.Tensor:
    """Fogged image. color [H, W, 3] premultiplied (no background), alpha [H, W], distance_m [H, W],
    beta_rgb [3] 1/m, airlight [3] or per pixel [H, W, 3] -> [H, W, 3]."""
    t = torch.exp(-distance_m[..., None] * beta_rgb)
    return color * t + airlight * (1.0 - alpha[..., None] * t)


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
    directional_airlight: bool = True
    """Let the airlight vary with the ray's direction (a learnable first-order term, zero at the start): real fog
    is brighter towards the horizon and the sun, and one colour for every direction leaves the difference to the
    scene (over-contrasted clean renders)."""


class FogAnalytic(WeatherModel):
    """Exponential fog from depth: ``apply`` turns the rendered view into the foggy one."""

    stage = "medium"
    name = "fog-analytic"

    def __init__(self, config: FogAnalyticConfig, theta: Theta, scene: WeatherScene):
        super().__init__(theta, scene)
        self.config = config
        beta = fog_extinction_rgb(theta, config.include_rain_veil).float()
        self._active = fog_called_for(theta, config.include_rain_veil)
        a = choose_airlight(config.airlight, theta, scene).clamp(1e-3, 1 - 1e-3)
        self.log_beta = torch.nn.Parameter(torch.log(beta.clamp_min(1e-12)), requires_grad=config.learnable)
        self.airlight_logit = torch.nn.Parameter(torch.logit(a), requires_grad=config.learnable)
        self.airlight_dir = torch.nn.Parameter(
            torch.zeros(3, 3), requires_grad=config.learnable and config.directional_airlight
        )
        """[3 (RGB), 3 (world xyz)] change of the airlight logit per unit of ray direction."""
        self._rays: dict[int, torch.Tensor] = {}
        self._dirs: dict[int, torch.Tensor] = {}
        self._register_load_state_dict_pre_hook(_without_direction_term)

    @property
    def active(self) -> bool:
        return self._active

    @property
    def beta_rgb(self) -> torch.Tensor:
        """[3] extinction per metre."""
        return torch.exp(self.log_beta)

    @property
    def airlight(self) -> torch.Tensor:
        """[3] airlight in (0, 1) (for a direction-dependent one: its value where the direction term is 0)."""
        return torch.sigmoid(self.airlight_logit)

    def airlight_of(self, view: int, height: int, width: int) -> torch.Tensor:
        """[3] or [H, W, 3] airlight along the rays of view ``view``."""
        if not self.config.directional_airlight:
            return self.airlight
        if view not in self._dirs:
            self._dirs[view] = ray_directions(self.scene.cameras[view], height, width)
        dirs = self._dirs[view].to(self.airlight_dir)
        return torch.sigmoid(self.airlight_logit + dirs @ self.airlight_dir.T)

    def apply(self, rgb: torch.Tensor, out: RenderOutput, view: int, settings: RenderSettings) -> torch.Tensor:
        background = settings.background_tensor(rgb)
        color = rgb - (1.0 - out.alpha)[..., None] * background  # premultiplied scene colour
        if view not in self._rays:  # the cameras are fixed: one ray-length map per view
            self._rays[view] = ray_lengths(self.scene.cameras[view], out.height, out.width)
        rays = self._rays[view].to(rgb)
        distance = out.depth * rays * self.scene.metres_per_unit
        distance = torch.where(out.alpha > 1e-6, distance, torch.zeros_like(distance))
        airlight = self.airlight_of(view, out.height, out.width).to(rgb)
        return fog_composite(color, out.alpha, distance, self.beta_rgb.to(rgb), airlight)

    def transmittance(self, points: torch.Tensor, view: int) -> torch.Tensor:
        """[N] exp(−β·d) of world points [N, 3] seen from view ``view``, averaged over R, G, B."""
        return torch.exp(-self.scene.distance_m(points, view)[:, None] * self.beta_rgb.detach().to(points)).mean(-1)


def _without_direction_term(state_dict, prefix, *args) -> None:
    """Checkpoints from before the direction term load with it at 0 (a constant airlight, as they had)."""
    state_dict.setdefault(prefix + "airlight_dir", torch.zeros(3, 3))
