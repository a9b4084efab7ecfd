"""`fog-analytic`: the atmospheric scattering model applied from the rendered depth.

C = C_scene·t + A·(1 − α·t), t = exp(−β·d), with d the distance along the pixel's ray (metres; the
rendered z-depth times the ray's length per unit z) and α the rendered opacity: the part of a pixel
not covered by Gaussians looks into the distance (t = 0) and shows the airlight A. β per colour
channel comes from θ_fog (visibility by the 5 % rule, minus the rain's share, plus the rain veil);
β and A are learnable (log-β, logit-A) starting from θ. Where every view sees the scene at about the same
distance (forward-facing captures), a hazy scene under less fog fits the photos as well as the true fog over the
clean scene, and a free β drifts down while the scene takes the haze in: there (``record_prior`` auto, decided by
the trainer) a prior holds ln β near θ's; where the distances differ across views the photos measure β, and it
stays free.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated, Literal

import torch

from metegs.meteo.mapping import Theta
from metegs.render.base import RenderOutput, RenderSettings
from metegs.validate import NON_NEGATIVE
from metegs.weather.base import WeatherModel, WeatherModelConfig, WeatherScene
from metegs.weather.medium import choose_airlight, fog_called_for, fog_extinction_rgb


def ray_lengths(camera, height: int, width: int) -> torch.Tensor:
    """Length of each pixel ray per unit of camera z. camera: one view -> [H, W]."""
    fx, fy, cx, cy = (float(v[0]) for v in (camera.fx, camera.fy, camera.cx, camera.cy))
    ys, xs = torch.meshgrid(torch.arange(height) + 0.5, torch.arange(width) + 0.5, indexing="ij")
    return torch.sqrt(((xs - cx) / fx) ** 2 + ((ys - cy) / fy) ** 2 + 1.0)


def fog_composite(
    color: torch.Tensor, alpha: torch.Tensor, distance_m: torch.Tensor, beta_rgb: torch.Tensor, airlight: torch.Tensor
) -> torch.Tensor:
    """Fogged image. color [H, W, 3] premultiplied (no background), alpha [H, W], distance_m [H, W],
    beta_rgb [3] 1/m, airlight [3] -> [H, W, 3]."""
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
    record_prior: Literal["auto", "on", "off"] = "auto"
    """Hold β near the met record's while training: auto = on where the photos cannot measure β (every view sees
    the scene from about the same distance, as in forward-facing captures), off where they can."""
    record_prior_weight: Annotated[float, NON_NEGATIVE] = 0.1
    """Weight of that prior, record_prior_weight · mean((ln β − ln β_θ)²)."""


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
        # θ's β for the prior: moves with the model, stays out of checkpoints (their keys are unchanged)
        self.register_buffer("record_log_beta", self.log_beta.detach().clone(), persistent=False)
        self.use_record_prior = config.record_prior == "on"
        """Whether `prior` holds β near θ's (the trainer decides ``auto`` from the views' distances)."""
        self.airlight_logit = torch.nn.Parameter(torch.logit(a), requires_grad=config.learnable)
        self._rays: dict[int, torch.Tensor] = {}

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
        if view not in self._rays:  # the cameras are fixed: one ray-length map per view
            self._rays[view] = ray_lengths(self.scene.cameras[view], out.height, out.width)
        rays = self._rays[view].to(rgb)
        distance = out.depth * rays * self.scene.metres_per_unit
        distance = torch.where(out.alpha > 1e-6, distance, torch.zeros_like(distance))
        return fog_composite(color, out.alpha, distance, self.beta_rgb.to(rgb), self.airlight.to(rgb))

    def prior(self, view: int) -> torch.Tensor | None:
        """record_prior_weight · mean((ln β − ln β_θ)²), or None when β is fixed or the prior is off."""
        if not (self.use_record_prior and self.log_beta.requires_grad and self.config.record_prior_weight > 0):
            return None
        gap = self.log_beta - self.record_log_beta
        return self.config.record_prior_weight * (gap**2).mean()

    def summary(self) -> dict:
        """Learned β (1/m, RGB) and airlight next to θ's β."""
        return {
            "beta_per_m": [round(float(b), 6) for b in self.beta_rgb.detach()],
            "record_beta_per_m": [round(float(b), 6) for b in self.record_log_beta.exp()],
            "airlight": [round(float(a), 4) for a in self.airlight.detach()],
        }

    def transmittance(self, points: torch.Tensor, view: int) -> torch.Tensor:
        """[N] exp(−β·d) of world points [N, 3] seen from view ``view``, averaged over R, G, B."""
        return torch.exp(-self.scene.distance_m(points, view)[:, None] * self.beta_rgb.detach().to(points)).mean(-1)
