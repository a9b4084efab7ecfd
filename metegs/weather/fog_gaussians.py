"""`fog-gaussians`: fog as a static medium of isotropic Gaussians rasterised with the scene (research §8.2).

The medium is a rotated cubic lattice of Gaussians (std σ = ``sigma_ratio``·h, colour = airlight A)
around the cameras, in nested cubes whose spacing doubles with each shell (h₀, 2h₀, 4h₀, ...) out to
where the fog is all but opaque (β·d ≥ ``optical_depth_limit``). Compositing sorts each Gaussian in
at its centre depth, so a surface at distance d is dimmed by the Gaussians centred in front of it.

Opacity rule with the rasteriser's alpha cutoff: a ray passing a Gaussian at distance r loses
−ln(1 − o·e^{−r²/2σ²}) where that alpha is ≥ α_min (smaller alphas are skipped). Integrated over the
cross-section and multiplied by the lattice density 1/h³, the optical depth per metre is
(2πσ²/h³)·(Li₂(o) − Li₂(α_min)); each shell's o solves that = β (exact, not the small-o form).
The finest spacing h₀ is the one at which o = ``opacity`` (well above α_min = 1/255), so no
Gaussian is so faint that the rasteriser drops it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from metegs.gaussians.model import GaussianSet
from metegs.gaussians.sh import rgb_to_sh
from metegs.meteo.mapping import Theta
from metegs.meteo.physics import dilogarithm
from metegs.render.base import ALPHA_MIN
from metegs.weather.base import WeatherModel, WeatherModelConfig, WeatherScene
from metegs.weather.medium import choose_airlight, fog_called_for, fog_extinction_rgb


def truncated_lattice_opacity(
    beta_per_m: float, spacing_m: float, sigma_m: float, alpha_min: float = ALPHA_MIN
) -> float:
    """Opacity o with (2πσ²/h³)·(Li₂(o) − Li₂(α_min)) = β; 0.99 when even that is not enough (opaque shell)."""
    target = beta_per_m * spacing_m**3 / (2.0 * math.pi * sigma_m**2) + dilogarithm(alpha_min)
    if beta_per_m <= 0:
        return 0.0
    if target >= dilogarithm(0.99):
        return 0.99
    lo, hi = alpha_min, 0.99
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if dilogarithm(mid) < target else (lo, mid)
    return 0.5 * (lo + hi)


def base_spacing_m(beta_per_m: float, opacity: float, sigma_ratio: float, alpha_min: float = ALPHA_MIN) -> float:
    """Spacing h at which the rule gives opacity ``opacity``: h = 2π·ratio²·(Li₂(o) − Li₂(α_min)) / β."""
    return 2.0 * math.pi * sigma_ratio**2 * (dilogarithm(opacity) - dilogarithm(alpha_min)) / beta_per_m


def random_rotation(gen: torch.Generator) -> torch.Tensor:
    """A random rotation matrix [3, 3] (QR of a Gaussian matrix)."""
    q, r = torch.linalg.qr(torch.randn(3, 3, generator=gen, dtype=torch.float64))
    q = q * torch.sign(torch.diagonal(r))
    return q if torch.det(q) > 0 else -q


@dataclass
class FogGaussiansConfig(WeatherModelConfig):
    """Fog as world-space Gaussians on a lattice that coarsens away from the cameras."""

    _target: type = field(default_factory=lambda: FogGaussians, repr=False)
    opacity: float = 0.02
    """Opacity of the finest shell's Gaussians (sets its spacing; must stay well above 1/255)."""
    sigma_ratio: float = 1.0
    """σ / h of every Gaussian (≥ 0.7 keeps the medium smooth)."""
    optical_depth_limit: float = 6.0
    """Shells stop once β·distance exceeds this (the fog transmits e^{−6} ≈ 0.25 % there)."""
    max_gaussians: int = 60_000
    """Upper bound on fog Gaussians; the finest spacing grows until the lattice fits."""
    airlight: tuple[float, float, float] | None = None
    """Airlight A in [0, 1]; None: θ's, else estimated from the scene's images (dark channel prior)."""
    include_rain_veil: bool = True
    """Add the rain's extinction beyond the streaks when it rains."""


class FogGaussians(WeatherModel):
    """A static fog medium (the same Gaussians in every view)."""

    stage = "gaussians"
    name = "fog-gaussians"

    def __init__(self, config: FogGaussiansConfig, theta: Theta, scene: WeatherScene):
        super().__init__(theta, scene)
        self.config = config
        self.beta_per_m = float(fog_extinction_rgb(theta, config.include_rain_veil).mean())
        """Grey extinction of the medium (the mean over R, G, B), 1/m."""
        self._active = fog_called_for(theta, config.include_rain_veil) and self.beta_per_m > 0
        self.airlight = choose_airlight(config.airlight, theta, scene).clamp(0.0, 1.0)
        self._gaussians = self._build() if self._active else None

    @property
    def active(self) -> bool:
        return self._active

    def _build(self) -> GaussianSet:
        c, scene = self.config, self.scene
        centres = scene.cameras.centers.double().cpu()
        centre = centres.mean(0)
        spread_m = float(scene.to_metres(float((centres - centre).norm(dim=1).max()))) if len(centres) > 1 else 0.0
        reach_m = c.optical_depth_limit / self.beta_per_m
        h0 = base_spacing_m(self.beta_per_m, c.opacity, c.sigma_ratio)
        while True:
            shells = self._shells(h0, max(spread_m + 2 * h0, 4 * h0), reach_m)
            total = sum(s[0] for s in shells)
            if total <= c.max_gaussians:
                break
            h0 *= 1.25
        gen = torch.Generator().manual_seed(int(scene.seed) + 4242)
        rot = random_rotation(gen)
        points, sigmas, opacities = [], [], []
        for _, inner_m, outer_m, h in shells:
            n = int(math.ceil(outer_m / h))
            ax = (
                torch.arange(-n, n + 1, dtype=torch.float64)
                + 0.5 * (torch.rand(1, generator=gen, dtype=torch.float64) - 0.5)
            ) * h
            grid = torch.stack(torch.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
            inf_norm = grid.abs().amax(dim=1)
            grid = grid[(inf_norm >= inner_m) & (inf_norm < outer_m)] if inner_m > 0 else grid[inf_norm < outer_m]
            sigma = c.sigma_ratio * h
            points.append(grid)
            sigmas.append(torch.full((len(grid),), sigma, dtype=torch.float64))
            opacities.append(
                torch.full((len(grid),), truncated_lattice_opacity(self.beta_per_m, h, sigma), dtype=torch.float64)
            )
        pts_m = torch.cat(points) @ rot.T
        means = centre + pts_m / scene.metres_per_unit
        sig_u = torch.cat(sigmas) / scene.metres_per_unit
        n = len(means)
        device = scene.cameras.camera_to_worlds.device
        self.spacing_m = h0
        """Finest lattice spacing used, m."""
        return GaussianSet(
            means.float().to(device),
            torch.tensor([1.0, 0.0, 0.0, 0.0]).expand(n, 4).contiguous().to(device),
            sig_u[:, None].expand(n, 3).float().contiguous().to(device),
            torch.cat(opacities).float().to(device),
            rgb_to_sh(self.airlight).expand(n, 1, 3).contiguous().to(device),
        )

    @staticmethod
    def _shells(h0: float, inner_half_m: float, reach_m: float) -> list[tuple[int, float, float, float]]:
        """(count, inner half-size, outer half-size, spacing) of the inner cube and the doubling shells."""
        shells = [(int((2 * math.ceil(inner_half_m / h0) + 1) ** 3), 0.0, inner_half_m, h0)]
        inner, h = inner_half_m, h0
        while inner < reach_m:
            h *= 2
            outer = 2 * inner
            n_side = 2 * math.ceil(outer / h) + 1
            shells.append((int(n_side**3 * 7 / 8), inner, outer, h))
            inner = outer
        return shells

    def gaussians_for(self, view: int) -> GaussianSet | None:
        return self._gaussians
