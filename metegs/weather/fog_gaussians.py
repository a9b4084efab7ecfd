"""`fog-gaussians`: fog as a static medium of isotropic Gaussians rasterised with the scene (research §8.2).

The medium is an octree of cubic cells (randomly rotated and shifted, shared by every view) that refines
towards the cameras; every leaf cell holds one Gaussian at its centre, colour = airlight A. With ρ the
distance of a cell to the nearest camera, h its edge and k = ``distance_sigmas``:

* **Accuracy**: σ = ρ/k. The rasteriser projects a Gaussian by linearising the perspective at its
  centre (EWA). That keeps each footprint's integral right, but footprints whose size is comparable to
  their distance spread far too wide (the old lattice, σ ≈ h ≈ the distance near the cameras, rendered
  2.3× the optical depth at 20 m), and even at σ = ρ/10 footprints that widen across the image pile
  up ~5 % too much optical depth; that remainder is corrected below.
* **Smoothness**: a cell splits while h > σ/``sigma_ratio``, so σ/h lies in [ratio, 2·ratio).
* **Visibility**: the rasteriser skips alphas below α_min = 1/255, so a cell splits only while its
  children keep opacity ≥ ``opacity``. Near the cameras, where the fog is thin, the cells stay coarser
  than σ (a lumpier but still unbiased medium) and the count grows only linearly with distance there.
* **Tails**: a cell also splits while its opacity would exceed 0.5 (long-tailed footprints).

Opacity: a ray passing a Gaussian at distance r loses −ln(1 − o·e^{−r²/2σ²}) where that alpha is ≥ α_min.
Over the cross-section that is 2πσ²·(Li₂(o) − Li₂(α_min)), which must equal β times the cell's volume
(exact, not the small-o form), divided by how much the rasteriser over-renders the Gaussian in the views
that see it largest: the screen-space dilation's wider footprint, and the second-order EWA excess of
`LatticeViews.projection_excess`. Compositing sorts each Gaussian in at its centre depth, so a surface
is dimmed by the Gaussians centred in front of it, which over a rotated lattice is the optical depth of
the path in front of it (cells of h ≤ 2ρ/k quantise that by up to ±β·h/2 per column, averaged over the image).

Gaussians nearer than ρ_min = ``near_optical_depth``/β to a camera are left out (they would be tiny
and faint); the cells beyond carry that path with weight 1 + (ρ_min/ρ)², whose excess integrates to
ρ_min along any ray from the camera (a surface at distance d sees β·(d − ρ_min²/d)). The octree stops
where every camera sees the fog as all but opaque (β·ρ ≥ ``optical_depth_limit``).

Count: ~19 000 Gaussians around one camera (any β; the lattice scales with 1/β), ~50 000 for the 4-view
synthetic scene and ~141 000 for its 48 views at 300 m visibility; over ``max_gaussians``, k is lowered
(coarser, less accurate: k = 8 still keeps the transmittance within ~1 %, k ≤ 6 errs by several %).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from metegs.gaussians.model import GaussianSet
from metegs.gaussians.sh import rgb_to_sh
from metegs.meteo.mapping import Theta
from metegs.meteo.physics import dilogarithm
from metegs.render.base import ALPHA_MAX, ALPHA_MIN, RenderSettings
from metegs.weather.base import SynthesisRequest, WeatherModel, WeatherModelConfig, WeatherScene
from metegs.weather.medium import choose_airlight, fog_called_for, fog_extinction_rgb


def dilogarithm_tensor(x: torch.Tensor) -> torch.Tensor:
    """Li₂(x) elementwise for 0 ≤ x < 1 (float64): the series below 1/2, the reflection formula above."""
    x = x.double().clamp(0.0, 1.0 - 1e-12)
    high = x > 0.5
    y = torch.where(high, 1.0 - x, x)  # y ≤ 1/2: 48 terms reach 1e-17
    series = torch.zeros_like(y)
    for k in range(48, 0, -1):  # Horner: Σ y^k/k²
        series = series * y + 1.0 / k**2
    series = series * y
    reflected = math.pi**2 / 6.0 - torch.log(x.clamp_min(1e-300)) * torch.log1p(-x) - series
    return torch.where(high, reflected, series)


def truncated_opacity(load: torch.Tensor, alpha_min: float = ALPHA_MIN, alpha_max: float = ALPHA_MAX) -> torch.Tensor:
    """Opacity o with Li₂(o) − Li₂(α_min) = load (elementwise, float64); ``alpha_max`` where that is not enough."""
    load = load.double()
    target = load + dilogarithm(alpha_min)
    o = (load + alpha_min).clamp(alpha_min, alpha_max)  # Li₂(x) ≈ x
    for _ in range(12):  # Newton on the convex, increasing Li₂ (Li₂'(o) = −ln(1 − o)/o)
        step = (dilogarithm_tensor(o) - target) * o / -torch.log1p(-o)
        o = (o - step).clamp(alpha_min, alpha_max)
    o = torch.where(target >= dilogarithm(alpha_max), torch.full_like(o, alpha_max), o)
    return torch.where(load > 0, o, torch.zeros_like(o))


def truncated_lattice_opacity(
    beta_per_m: float, spacing_m: float, sigma_m: float, alpha_min: float = ALPHA_MIN
) -> float:
    """Opacity o with (2πσ²/h³)·(Li₂(o) − Li₂(α_min)) = β; 0.99 when even that is not enough (opaque shell)."""
    if beta_per_m <= 0:
        return 0.0
    load = beta_per_m * spacing_m**3 / (2.0 * math.pi * sigma_m**2)
    return float(truncated_opacity(torch.tensor([load]), alpha_min)[0])


def base_spacing_m(beta_per_m: float, opacity: float, sigma_ratio: float, alpha_min: float = ALPHA_MIN) -> float:
    """Spacing h at which the rule gives opacity ``opacity``: h = 2π·ratio²·(Li₂(o) − Li₂(α_min)) / β."""
    return 2.0 * math.pi * sigma_ratio**2 * (dilogarithm(opacity) - dilogarithm(alpha_min)) / beta_per_m


def random_rotation(gen: torch.Generator) -> torch.Tensor:
    """A random rotation matrix [3, 3] (QR of a Gaussian matrix)."""
    q, r = torch.linalg.qr(torch.randn(3, 3, generator=gen, dtype=torch.float64))
    q = q * torch.sign(torch.diagonal(r))
    return q if torch.det(q) > 0 else -q


def nearest_camera(
    points: torch.Tensor, centres: torch.Tensor, chunk: int = 65536
) -> tuple[torch.Tensor, torch.Tensor]:
    """(distance [N], index [N]) of the nearest of ``centres`` [C, 3] to each of ``points`` [N, 3]."""
    dist, idx = [], []
    for part in points.split(chunk):
        d, i = torch.cdist(part, centres).min(dim=1)
        dist.append(d)
        idx.append(i)
    if not dist:
        return points.new_zeros(0), torch.zeros(0, dtype=torch.long)
    return torch.cat(dist), torch.cat(idx)


def truncated_spread(opacity: torch.Tensor, alpha_min: float = ALPHA_MIN, steps: int = 64) -> torch.Tensor:
    """κ(o): second moment of a Gaussian's optical-depth footprint −ln(1 − o·e^{−q/2}) (cut where alpha < α_min)
    relative to the untruncated small-o Gaussian's (1). Elementwise, float64."""
    o = opacity.double().clamp(alpha_min * (1 + 1e-9), ALPHA_MAX)
    q_cut = 2.0 * torch.log(o / alpha_min)
    t = (torch.arange(steps, dtype=torch.float64) + 0.5) / steps  # midpoint rule on [0, q_cut] (area ∝ dq in 2D)
    q = q_cut[..., None] * t
    profile = -torch.log1p(-o[..., None] * torch.exp(-0.5 * q))
    return 0.5 * (q * profile).sum(-1) / profile.sum(-1)


def uniform_spread_excess(u2: torch.Tensor) -> torch.Tensor:
    """A(|u|²)/m: ∂ᵢ∂ⱼ(m·(δᵢⱼ + uᵢuⱼ))/m with m = √(1+|u|²) (normalised image coordinates u)."""
    s = u2
    f = torch.sqrt(1.0 + s)
    f1 = 0.5 / f
    f2 = -0.25 / (1.0 + s) ** 1.5
    g = 2.0 * f1 * s + 3.0 * f
    g1 = 2.0 * f2 * s + 5.0 * f1
    return (4.0 * f1 + 4.0 * s * f2 + 2.0 * g + 2.0 * g1 * s) / f


@dataclass
class LatticeViews:
    """The cameras in the lattice frame (metres), for the per-Gaussian projection corrections."""

    rotations: torch.Tensor
    """[C, 3, 3] float64 world-to-camera rotations (OpenCV axes)."""
    centres_m: torch.Tensor
    """[C, 3] float64 camera centres."""
    fx: torch.Tensor
    fy: torch.Tensor
    cx: torch.Tensor
    cy: torch.Tensor
    width: torch.Tensor
    height: torch.Tensor
    near_m: float = 0.0
    """Gaussians nearer than this (camera z) are culled by the rasteriser."""

    @staticmethod
    def from_cameras(cameras, origin: torch.Tensor, metres_per_unit: float, near_m: float = 0.0) -> LatticeViews:
        """Cameras (world units) -> views in the frame (world − origin)·metres_per_unit."""
        c2w = cameras.camera_to_worlds.double().cpu()
        d = lambda t: t.double().cpu().reshape(-1)  # noqa: E731
        return LatticeViews(
            c2w[:, :3, :3].transpose(1, 2), (c2w[:, :3, 3] - origin) * metres_per_unit,
            d(cameras.fx), d(cameras.fy), d(cameras.cx), d(cameras.cy), d(cameras.width), d(cameras.height), near_m,
        )  # fmt: skip

    def projection_excess(
        self,
        points_m: torch.Tensor,
        sigma_m: torch.Tensor,
        distance_sigmas: float,
        rho_min: float,
        eps2d: float,
        top: int = 4,
        chunk: int = 4096,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(D, S), each [N]: the rasteriser over-renders a Gaussian's optical depth by the factor D + κ·S, with
        κ = ``truncated_spread(o)``: the screen-space dilation's larger footprint times the EWA excess, averaged
        (weights (σ/z)²) over the ``top`` views that see the Gaussian largest. (1, 0) where no view sees it.

        EWA excess: in a slab at camera depth z the medium's mass per unit of normalised image area is
        M ∝ w·m (m = √(1+|u|²) the ray length, w the near-camera weight) and each footprint has covariance
        κ·h·(I + uu^T) with h = (σ/z)² (κ: the truncated profile's spread). Footprints whose spread varies
        with u pile optical depth up: to second order the slab renders M + ½·κ·∂ᵢ∂ⱼ(M·h·(δᵢⱼ + uᵢuⱼ)), i.e.
        the relative excess ½·κ·(h̃·A/m + 8·u·∇h̃ + ∇²h̃ + uᵀ(∇∇h̃)u)/w with h̃ = w·h. The field h (σ = distance
        to the nearest camera / k) is differentiated numerically over a stencil of one footprint width,
        which smooths its kinks where the nearest camera changes. For one camera h = (1+|u|²)/k²: 12/k² at
        the image centre.
        """
        # The projection clamps the linearisation point to the frustum widened by 30 % of the half field of view.
        lim_xp = (self.width - self.cx) / self.fx + 0.15 * self.width / self.fx
        lim_xn = self.cx / self.fx + 0.15 * self.width / self.fx
        lim_yp = (self.height - self.cy) / self.fy + 0.15 * self.height / self.fy
        lim_yn = self.cy / self.fy + 0.15 * self.height / self.fy
        stencil = torch.tensor(
            [[0, 0], [1, 0], [-1, 0], [0, 1], [0, -1], [1, 1], [1, -1], [-1, 1], [-1, -1]], dtype=torch.float64
        )
        k = min(top, len(self.centres_m))
        out_d, out_s = [], []
        for pts, sig in zip(points_m.split(chunk), sigma_m.split(chunk)):
            cam = torch.einsum("cij,ncj->nci", self.rotations, pts[:, None, :] - self.centres_m[None])
            z = cam[..., 2]
            front = z > max(self.near_m, 1e-9)
            zs = torch.where(front, z, torch.ones_like(z))
            ux, uy = cam[..., 0] / zs, cam[..., 1] / zs
            seen = front & (ux <= lim_xp) & (ux >= -lim_xn) & (uy <= lim_yp) & (uy >= -lim_yn)
            eps = torch.where(seen, sig[:, None] / zs, torch.zeros_like(zs))
            e, best = eps.topk(k, dim=1)  # [n, k]
            bz, bx, by = zs.gather(1, best), ux.gather(1, best), uy.gather(1, best)
            # The sigma field around each Gaussian, in each chosen view's slab: z·(u + e·offset, 1).
            su = torch.stack([bx, by], -1)[:, :, None, :] + e[..., None, None].clamp_min(1e-6) * stencil
            q = torch.cat([su, torch.ones_like(su[..., :1])], -1) * bz[..., None, None]
            world = torch.einsum("nkji,nksj->nksi", self.rotations[best], q) + self.centres_m[best][:, :, None, :]
            rho, _ = nearest_camera(world.reshape(-1, 3), self.centres_m)
            rho = rho.reshape(world.shape[:-1]).clamp_min(rho_min)
            w = 1.0 + (rho_min / rho) ** 2
            hw = w * (rho / (distance_sigmas * bz[..., None])) ** 2
            step = e.clamp_min(1e-6)
            h0, hxp, hxn, hyp, hyn = hw[..., 0], hw[..., 1], hw[..., 2], hw[..., 3], hw[..., 4]
            hx, hy = (hxp - hxn) / (2 * step), (hyp - hyn) / (2 * step)
            hxx, hyy = (hxp - 2 * h0 + hxn) / step**2, (hyp - 2 * h0 + hyn) / step**2
            hxy = (hw[..., 5] - hw[..., 6] - hw[..., 7] + hw[..., 8]) / (4 * step**2)
            u2 = bx**2 + by**2
            spread = (
                h0 * uniform_spread_excess(u2) + 8 * (bx * hx + by * hy) + hxx + hyy
                + bx**2 * hxx + 2 * bx * by * hxy + by**2 * hyy
            )  # fmt: skip
            # Screen footprint covariance f²(σ/z)²(I + uu^T) (fx ≈ fy): its eigenvalues a(1 + |u|²) and a.
            a = (self.fx[best] * self.fy[best]) * e**2
            dilation = torch.sqrt((a * (1 + u2) + eps2d) * (a + eps2d) / (a * a * (1 + u2)).clamp_min(1e-300))
            weight = e**2
            total = weight.sum(1).clamp_min(1e-300)
            seen_any = weight.sum(1) > 0
            d = (weight * dilation).sum(1) / total
            s = (weight * dilation * 0.5 * spread / w[..., 0]).sum(1) / total
            out_d.append(torch.where(seen_any, d, torch.ones_like(d)))
            out_s.append(torch.where(seen_any, s, torch.zeros_like(s)))
        if not out_d:
            return points_m.new_zeros(0), points_m.new_zeros(0)
        return torch.cat(out_d), torch.cat(out_s)


@dataclass
class FogLattice:
    """The fog medium's Gaussians in metres, in the frame of the cameras' centroid."""

    centres_m: torch.Tensor
    """[N, 3] float64 Gaussian centres."""
    sigma_m: torch.Tensor
    """[N] float64 standard deviations."""
    cell_m: torch.Tensor
    """[N] float64 edge of each Gaussian's cell."""
    load: torch.Tensor
    """[N] float64 Li₂(o) − Li₂(α_min) each Gaussian carries."""
    opacity: torch.Tensor
    """[N] float64 opacities."""


MAX_LATTICE_OPACITY = 0.5
"""Cells split while their Gaussian would need a larger opacity (long footprint tails project badly)."""
MIN_NEAR_OPTICAL_DEPTH = 1e-4
"""Least β·ρ_min: the octree needs a hole around each camera to end."""


def fog_octree(
    cameras_m: torch.Tensor,
    beta_per_m: float,
    *,
    rotation: torch.Tensor | None = None,
    offset: torch.Tensor | None = None,
    distance_sigmas: float = 10.0,
    sigma_ratio: float = 0.5,
    min_opacity: float = 0.01,
    near_optical_depth: float = 0.01,
    optical_depth_limit: float = 6.0,
    alpha_min: float = ALPHA_MIN,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Leaf cells of the medium's octree (rules in the module docstring) around cameras at ``cameras_m`` [C, 3]
    (metres) -> (centres [N, 3], distance to the nearest camera [N], edge [N]), float64 metres.

    rotation [3, 3]: orientation of the octree's axes (None: the frame's).
    offset [3]: in [0, 1)³, shifts the octree's cells against the cameras (None: a cell corner at their centre).
    """
    rot = torch.eye(3, dtype=torch.float64) if rotation is None else rotation.double()
    cams = cameras_m.double() @ rot  # camera centres in the octree's axes
    reach = optical_depth_limit / beta_per_m
    rho_min = max(near_optical_depth, MIN_NEAR_OPTICAL_DEPTH) / beta_per_m
    min_load = dilogarithm(min_opacity) - dilogarithm(alpha_min)
    max_load = dilogarithm(MAX_LATTICE_OPACITY) - dilogarithm(alpha_min)
    k = distance_sigmas
    centre = 0.5 * (cams.amax(0) + cams.amin(0))
    size = 4.0 * (float((cams - centre).abs().max()) + reach)
    if offset is not None:  # shifts every level's cells against the cameras (the root still covers them)
        centre = centre + 0.25 * size * (offset.double() - 0.5)
    cells = centre[None]
    leaves: list[tuple[torch.Tensor, torch.Tensor, float]] = []
    corners = torch.tensor([[i, j, m] for i in (-1, 1) for j in (-1, 1) for m in (-1, 1)], dtype=torch.float64)
    half_diag = 0.5 * math.sqrt(3.0)
    for _ in range(64):  # levels (a cell splits only while it is coarser than rho_min/k: this ends far sooner)
        if not len(cells):
            break
        rho, _ = nearest_camera(cells, cams)
        # A cell matters if part of it lies within reach of a camera and beyond rho_min of the nearest one.
        keep = (rho - half_diag * size <= reach) & (rho + half_diag * size >= rho_min)
        cells, rho = cells[keep], rho[keep]
        sigma = (rho / k).clamp_min(1e-12)
        near = 1.0 + (rho_min / rho.clamp_min(rho_min)) ** 2
        load = beta_per_m * size**3 * near / (2.0 * math.pi * sigma**2)
        split = ((sigma_ratio * size > sigma) | (load > max_load)) & (load / 8.0 >= min_load)
        leaf = ~split & (rho >= rho_min) & (rho <= reach)
        leaves.append((cells[leaf], rho[leaf], size))
        child = 0.5 * size
        cells = (cells[split][:, None, :] + 0.5 * child * corners).reshape(-1, 3)
        size = child
    pts = torch.cat([c for c, _, _ in leaves]) @ rot.T
    rho = torch.cat([d for _, d, _ in leaves])
    cell = torch.cat([torch.full((len(c),), s, dtype=torch.float64) for c, _, s in leaves])
    return pts, rho, cell


def build_fog_lattice(
    cameras_m: torch.Tensor,
    beta_per_m: float,
    *,
    views: LatticeViews | None = None,
    rotation: torch.Tensor | None = None,
    offset: torch.Tensor | None = None,
    distance_sigmas: float = 10.0,
    sigma_ratio: float = 0.5,
    min_opacity: float = 0.01,
    near_optical_depth: float = 0.01,
    optical_depth_limit: float = 6.0,
    eps2d: float = 0.3,
    alpha_min: float = ALPHA_MIN,
) -> FogLattice:
    """The medium around cameras at ``cameras_m`` [C, 3] (metres): `fog_octree`'s cells, σ and opacities.

    views: the cameras' orientations and intrinsics (same frame), for the projection corrections (None: none).
    """
    pts, rho, cell = fog_octree(
        cameras_m, beta_per_m, rotation=rotation, offset=offset, distance_sigmas=distance_sigmas,
        sigma_ratio=sigma_ratio, min_opacity=min_opacity, near_optical_depth=near_optical_depth,
        optical_depth_limit=optical_depth_limit, alpha_min=alpha_min,
    )  # fmt: skip
    rho_min = max(near_optical_depth, MIN_NEAR_OPTICAL_DEPTH) / beta_per_m
    sigma = rho / distance_sigmas
    near = 1.0 + (rho_min / rho) ** 2  # carries the path left out within rho_min of the camera
    base = beta_per_m * cell**3 * near / (2.0 * math.pi * sigma**2)
    load, opacity = base, truncated_opacity(base, alpha_min)
    if views is not None:
        dilation, spread = views.projection_excess(pts, sigma, distance_sigmas, rho_min, eps2d)
        for _ in range(3):  # the EWA excess depends on the opacity (its footprint's truncation): iterate
            load = base / (dilation + truncated_spread(opacity, alpha_min) * spread)
            opacity = truncated_opacity(load, alpha_min)
    return FogLattice(pts, sigma, cell, load, opacity)


@dataclass
class FogGaussiansConfig(WeatherModelConfig):
    """Fog as world-space Gaussians in an octree that refines towards the cameras."""

    _target: type = field(default_factory=lambda: FogGaussians, repr=False)
    opacity: float = 0.01
    """Least opacity of a fog Gaussian (above the rasteriser's 1/255 cutoff); sets how coarse cells near the cameras stay."""
    sigma_ratio: float = 0.5
    """Cells split while σ/h < this, so σ/h lies in [ratio, 2·ratio) (≥ 0.5 keeps the medium smooth)."""
    distance_sigmas: float = 10.0
    """k: σ = distance to the nearest camera / k (keeps the EWA projection accurate; cost grows as k³)."""
    near_optical_depth: float = 0.01
    """No Gaussians within β·ρ < this of a camera; the cells beyond carry that path."""
    correct_projection: bool = True
    """Lower each opacity by the dilation and EWA excess of the views that see the Gaussian largest."""
    optical_depth_limit: float = 6.0
    """The medium stops once β·distance exceeds this (the fog transmits e^{−6} ≈ 0.25 % there)."""
    max_gaussians: int = 150_000
    """Upper bound on fog Gaussians; ``distance_sigmas`` is lowered until the octree fits."""
    airlight: tuple[float, float, float] | None = None
    """Airlight A in [0, 1]; None: θ's, else estimated from the scene's images (dark channel prior)."""
    include_rain_veil: bool = True
    """Add the rain's extinction beyond the streaks when it rains."""

    def for_synthesis(self, request: SynthesisRequest) -> None:
        """Never: `fog-analytic` synthesises the same medium exactly, from each view's depth."""
        return None


class FogGaussians(WeatherModel):
    """A static fog medium (the same Gaussians in every view)."""

    stage = "gaussians"
    name = "fog-gaussians"
    kind = "fog"

    def __init__(self, config: FogGaussiansConfig, theta: Theta, scene: WeatherScene):
        super().__init__(theta, scene)
        self.config = config
        self.beta_per_m = float(fog_extinction_rgb(theta, config.include_rain_veil).mean())
        """Grey extinction of the medium (the mean over R, G, B), 1/m."""
        self._active = fog_called_for(theta, config.include_rain_veil) and self.beta_per_m > 0
        self.airlight = choose_airlight(config.airlight, theta, scene).clamp(0.0, 1.0)
        self.distance_sigmas = config.distance_sigmas
        """k used (lower than the config's when ``max_gaussians`` forced it)."""
        self.lattice: FogLattice | None = None
        """The medium in metres (centres relative to the cameras' centroid), for inspection."""
        self._gaussians = self._build() if self._active else None

    @property
    def active(self) -> bool:
        return self._active

    @property
    def extinction_per_m(self) -> float:
        """β of the medium (1/m): how strongly it veils the scene."""
        return self.beta_per_m

    def _build(self) -> GaussianSet:
        c, scene = self.config, self.scene
        centroid = scene.cameras.centers.double().cpu().mean(0)
        settings = RenderSettings()
        views = LatticeViews.from_cameras(
            scene.cameras, centroid, scene.metres_per_unit, near_m=settings.near * scene.metres_per_unit
        )
        gen = torch.Generator().manual_seed(int(scene.seed) + 4242)
        options = dict(
            rotation=random_rotation(gen), offset=torch.rand(3, generator=gen, dtype=torch.float64),
            sigma_ratio=c.sigma_ratio, min_opacity=c.opacity, near_optical_depth=c.near_optical_depth,
            optical_depth_limit=c.optical_depth_limit,
        )  # fmt: skip
        k = c.distance_sigmas
        for _ in range(20):  # the count grows about as k³: shrink k until the octree fits
            count = len(fog_octree(views.centres_m, self.beta_per_m, distance_sigmas=k, **options)[0])
            if count <= c.max_gaussians or k <= 2.0:
                break
            k = max(2.0, k * min(0.95, (c.max_gaussians / count) ** (1 / 3)))
        self.distance_sigmas = k
        self.lattice = build_fog_lattice(
            views.centres_m, self.beta_per_m, views=views if c.correct_projection else None, distance_sigmas=k,
            eps2d=settings.eps2d, **options,
        )  # fmt: skip
        lattice = self.lattice
        means = centroid + lattice.centres_m / scene.metres_per_unit
        sig_u = lattice.sigma_m / scene.metres_per_unit
        n = len(means)
        device = scene.cameras.camera_to_worlds.device
        return GaussianSet(
            means.float().to(device),
            torch.tensor([1.0, 0.0, 0.0, 0.0]).expand(n, 4).contiguous().to(device),
            sig_u[:, None].expand(n, 3).float().contiguous().to(device),
            lattice.opacity.float().to(device),
            rgb_to_sh(self.airlight).expand(n, 1, 3).contiguous().to(device),
        )

    def gaussians_for(self, view: int) -> GaussianSet | None:
        return self._gaussians

    def transmittance(self, points: torch.Tensor, view: int) -> torch.Tensor:
        """[N] exp(−β·d) of world points [N, 3] seen from view ``view`` (the medium the octree approximates)."""
        return torch.exp(-self.beta_per_m * self.scene.distance_m(points, view))
