"""The fog medium measured at a scene's points: β and airlight from the photos' colours where the views see them.

A scene point of colour J seen through fog at distance d shows I = J·t + A·(1 − t), t = exp(−τ(d)). Where the views
see a point from distances far apart, I changes from view to view by the medium alone, so the photos' colours at the
points' projections measure β (and its fall with height) and the airlight A, with one unknown J per point. Training
measures the same through the scene's Gaussians, which can take the haze in themselves (Gaussians near the
cameras, colours that change with the view); this fit has no such freedom. Rain streaks over a point are outliers of
its robust loss. Views in which another point hides it are left out (`unoccluded`): with the airlight fitted, a nearer,
darker occluder reads as fog towards a dark airlight (the built-in scene's clean photos read 8.3e-3/m at its spread
points with them, 1.2e-3 without, nothing under the photos' own airlight either way; its synthetic depth maps show
that 47 % of all those views do not see their point).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import torch
import torch.nn.functional as F

from metegs.cameras import Cameras
from metegs.weather.fog_analytic import height_profile
from metegs.weather.medium import nearest_and_farthest

FIT_STEPS = 1500
"""Adam steps of the fit."""

CHARBONNIER_EPS = 1e-4
"""ε² of the robust loss √(r² + ε²): residuals well over 0.01 (streaks, occlusion) count linearly."""

OCCLUSION_TOLERANCE = 0.15
"""How much deeper than the nearest point around it a point may lie and still be seen (fraction of that depth).
On the built-in scene's spread points, against its depth maps: 86 % of the views kept see their point, and 83 % of
those that do are kept (0.05: 97 % and 54 %, half the observations for the same β within 15 %)."""


@dataclass
class PointObservations:
    """Colours the photos show at scene points, with the geometry of each observation (one row each)."""

    point: torch.Tensor
    """[N] long, index of the observed point."""
    colour: torch.Tensor
    """[N, 3] the photo's colour at the point's projection (median of 3×3 pixels)."""
    distance_m: torch.Tensor
    """[N] camera-to-point distance, metres."""
    camera_height_m: torch.Tensor
    """[N] the camera's height over the cameras' mean, metres."""
    rise: torch.Tensor
    """[N] height gained per metre along the ray to the point."""

    def __len__(self) -> int:
        return len(self.point)

    def spread(self, min_ratio: float) -> PointObservations:
        """The observations of points seen from distances at least ``min_ratio`` times apart (farthest over nearest):
        a point seen from about one distance shows one veil in every view, which its own colour explains at any β."""
        if len(self) == 0:
            return self
        near, far = nearest_and_farthest(self.point, self.distance_m, int(self.point.max()) + 1)
        keep = (far >= min_ratio * near)[self.point]
        return PointObservations(*(getattr(self, f.name)[keep] for f in fields(self)))


@dataclass
class MediumFit:
    """β at the cameras' mean height, its height rate and the airlight that explain the photos at the points."""

    beta_per_m: float
    height_rate: float
    """100·k, ln β's fall per 100 m of height (`FogAnalytic.height_rate`)."""
    airlight: tuple[float, float, float]
    observations: int
    points: int
    explained: float = float("nan")
    """Share of the robust loss of clear air (each point's colour alone) that the medium explains: 0.4-0.6 % on the
    built-in scene's clean or rain-streaked photos, 36-49 % in its fog, but also only 1.4-2.4 % on the fox's photos
    under a real thin veil, so it cannot tell that there is none (`fit_uniform_medium`; NaN: not measured);
    `veil_evidence` asks instead whether a given β explains them."""

    def describe(self) -> str:
        k = self.height_rate / 100.0
        height = "uniform" if abs(k) < 1e-6 else f"scale height {1.0 / k:.0f} m"
        a = ", ".join(f"{v:.2f}" for v in self.airlight)
        explained = "" if math.isnan(self.explained) else f", explaining {self.explained:.1%} of clear air's loss"
        return (
            f"β {self.beta_per_m:.2e}/m ({height}), airlight ({a}), fitted to {self.observations} observations of "
            f"{self.points} points{explained}"
        )


def sample_median3(image: torch.Tensor, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Median over the 3×3 pixels around integer pixels (x [N], y [N]) of image [H, W, 3] -> [N, 3]."""
    h, w = image.shape[:2]
    offsets = torch.tensor([-1, 0, 1], device=image.device)
    xs = (x[:, None, None] + offsets[None, None, :]).clamp(0, w - 1)
    ys = (y[:, None, None] + offsets[None, :, None]).clamp(0, h - 1)
    patch = image[ys, xs].reshape(len(x), 9, 3)
    return patch.median(dim=1).values


def unoccluded(x: torch.Tensor, y: torch.Tensor, z: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """Which of P points at pixels (x [P], y [P]) inside a ``width``×``height`` frame, at depths z [P] > 0, no other of
    them hides -> [P] bool. A z-buffer of the points themselves: cells of side √(width·height / P), so that a cell
    holds about one point of a surface seen face on, each holding its nearest depth; a point is seen where it lies
    within `OCCLUSION_TOLERANCE` of the nearest depth over its cell and the 8 around it."""
    if len(z) == 0:
        return torch.zeros(0, dtype=torch.bool)
    cell = max(1.0, math.sqrt(width * height / len(z)))
    cols, rows = math.ceil(width / cell), math.ceil(height / cell)
    ix = (x / cell).long().clamp(0, cols - 1)
    iy = (y / cell).long().clamp(0, rows - 1)
    flat = iy * cols + ix
    nearest = torch.full((rows * cols,), float("inf")).scatter_reduce(0, flat, z.float(), "amin")
    nearest = -F.max_pool2d(-nearest.view(1, 1, rows, cols), 3, stride=1, padding=1).view(-1)
    return z <= nearest[flat] * (1.0 + OCCLUSION_TOLERANCE)


def point_observations(
    cameras: Cameras,
    images: list[torch.Tensor],
    points: torch.Tensor,
    up: torch.Tensor,
    metres_per_unit: float,
    max_points: int = 4096,
) -> PointObservations:
    """Every projection of ``points`` [P, 3] (at most ``max_points`` of them, evenly spread) inside the frame of each
    view of ``cameras`` (images [H, W, 3] at the cameras' sizes), in front of it and hidden there by none of the
    ``points`` (`unoccluded`: all P are the occluders). ``up`` [3] world up."""
    cloud = torch.as_tensor(points, dtype=torch.float32).cpu()
    observed = torch.arange(0, len(cloud), max(1, len(cloud) // max_points))
    pts = cloud[observed]
    cameras = cameras.to("cpu")
    up = (up.float() / up.float().norm()).cpu()
    centres = cameras.centers.float()
    reference = (centres @ up).mean()
    rows: dict[str, list[torch.Tensor]] = {k: [] for k in ("point", "colour", "distance", "height", "rise")}
    for v, image in enumerate(images):
        x, y, z = cameras[v].project(cloud)[0].unbind(-1)
        h, w = image.shape[:2]
        inside = (z > 1e-6) & (x >= 0) & (x < w) & (y >= 0) & (y < h)
        seen = torch.zeros(len(cloud), dtype=torch.bool)
        seen[inside] = unoccluded(x[inside], y[inside], z[inside], w, h)
        idx = torch.nonzero(seen[observed]).squeeze(1)
        if len(idx) == 0:
            continue
        x, y = x[observed], y[observed]
        offset = pts[idx] - centres[v]
        distance = offset.norm(dim=-1).clamp_min(1e-12)
        rows["point"].append(idx)
        rows["colour"].append(sample_median3(image.detach().float().cpu(), x[idx].long(), y[idx].long()))
        rows["distance"].append(distance * metres_per_unit)
        rows["height"].append(torch.full_like(distance, float(centres[v] @ up - reference) * metres_per_unit))
        rows["rise"].append((offset @ up) / distance)
    cat = {k: torch.cat(v) if v else torch.zeros(0) for k, v in rows.items()}
    return PointObservations(
        point=cat["point"].long(),
        colour=cat["colour"].reshape(-1, 3),
        distance_m=cat["distance"],
        camera_height_m=cat["height"],
        rise=cat["rise"],
    )


@torch.enable_grad()  # a run loaded for inference (`load_run` under no_grad) fits its medium all the same
def fit_medium(
    obs: PointObservations,
    beta_start: float,
    layered: bool = True,
    steps: int = FIT_STEPS,
    airlight: torch.Tensor | None = None,
) -> MediumFit:
    """Robust least squares (Charbonnier) of I = J·t + A·(1 − t) over ``obs``, t = exp(−β·d·`height_profile`), for β
    (from ``beta_start``), the height rate (0 unless ``layered``), A (held where ``airlight`` [3] is given) and one J
    per point."""
    points = int(obs.point.max()) + 1 if len(obs) else 0
    log_beta = torch.tensor(math.log(beta_start), requires_grad=True)
    height_rate = torch.zeros((), requires_grad=layered)
    held = airlight is not None
    start = torch.logit(airlight.float().clamp(1e-4, 1 - 1e-4)) if held else torch.full((3,), 1.5)
    airlight_logit = start.clone().requires_grad_(not held)
    scene_logit = torch.zeros((points, 3), requires_grad=True)
    params = [log_beta, scene_logit] + ([] if held else [airlight_logit]) + ([height_rate] if layered else [])
    opt = torch.optim.Adam(params, lr=0.02)
    for _ in range(steps):
        k = height_rate / 100.0
        tau = log_beta.exp() * obs.distance_m * height_profile(k, obs.camera_height_m, obs.rise, obs.distance_m)
        t = torch.exp(-tau)[:, None]
        predicted = torch.sigmoid(scene_logit[obs.point]) * t + torch.sigmoid(airlight_logit) * (1.0 - t)
        loss = torch.sqrt((predicted - obs.colour) ** 2 + CHARBONNIER_EPS).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    fitted = airlight.float() if held else torch.sigmoid(airlight_logit.detach())
    return MediumFit(
        beta_per_m=float(log_beta.detach().exp()),
        height_rate=float(height_rate.detach()),
        airlight=(float(fitted[0]), float(fitted[1]), float(fitted[2])),
        observations=len(obs),
        points=len(torch.unique(obs.point)) if len(obs) else 0,
    )


def _losses_at(
    obs: PointObservations, beta: float, points: int, iterations: int, airlight: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Robust loss (Charbonnier, summed over the channels) of each observation under the best uniform medium of
    extinction ``beta`` (1/m) -> (losses [N] float64, airlight [3]). I = J·t + A·(1 − t) is linear in the points' J
    and A: reweighted least squares alternates the two in closed form, with weights 1/√(r² + ε²) of the Charbonnier
    loss that `fit_medium` minimises. A given ``airlight`` [3] stays as it is."""
    t = torch.exp(-beta * obs.distance_m.double())[:, None]
    colour = obs.colour.double()
    weight = torch.ones_like(colour)
    fixed = airlight is not None
    airlight = airlight.double() if fixed else colour.quantile(0.9, dim=0)
    for _ in range(iterations):
        wt = weight * t
        num = torch.zeros(points, 3, dtype=torch.float64).index_add_(0, obs.point, wt * (colour - airlight * (1 - t)))
        den = torch.zeros(points, 3, dtype=torch.float64).index_add_(0, obs.point, wt * t)
        scene = (num / den.clamp_min(1e-12)).clamp(0.0, 1.0)[obs.point]
        if not fixed:
            veil = weight * (1 - t)
            airlight = ((veil * (colour - scene * t)).sum(0) / (veil * (1 - t)).sum(0).clamp_min(1e-12)).clamp(0, 1)
        residual = scene * t + airlight * (1 - t) - colour
        weight = 1.0 / torch.sqrt(residual**2 + CHARBONNIER_EPS)
    residual = scene * t + airlight * (1 - t) - colour
    return torch.sqrt(residual**2 + CHARBONNIER_EPS).sum(-1), airlight.float()


def _fit_at(
    obs: PointObservations, beta: float, points: int, iterations: int, airlight: torch.Tensor | None = None
) -> tuple[float, torch.Tensor]:
    """Mean Charbonnier loss per channel of the best uniform medium of extinction ``beta`` (1/m) -> (loss, airlight
    [3]) (`_losses_at`; a given ``airlight`` [3] stays as it is)."""
    losses, airlight = _losses_at(obs, beta, points, iterations, airlight)
    return float(losses.mean()) / 3.0, airlight


@dataclass
class VeilEvidence:
    """How much better a uniform medium of a given β explains the photos at the points than clear air does."""

    explained: float
    """Share of clear air's robust loss that the medium takes away (negative: it explains them worse)."""
    z: float
    """That gain over its standard error, the points taken as independent samples."""
    brighter: float
    """Share of the observed colours (mean over the channels) that the medium's fitted airlight outshines."""


def veil_evidence(obs: PointObservations, beta_per_m: float, iterations: int = 30) -> VeilEvidence:
    """Whether ``obs`` show a uniform medium of extinction ``beta_per_m`` (its airlight and the points' colours
    fitted, `_losses_at`) rather than clear air: the loss each point's observations lose, summed, against its spread
    over the points. A veil that is there lowers most points' loss (metegs's own heavy rain, a veil of 2.5e-3/m: z 31
    on the built-in scene, 7.0 on the instant-ngp fox); where there is none, the medium fits worse (the fox's clean
    photos at that β: z −16) or no better than what each point's colour alone absorbs (the built-in scene under
    streaks without a veil: z −0.2), though the best β there still explains 0.4 % (`fit_uniform_medium`). What a
    medium without a veil explains (colours that far views mix towards their surroundings, exposures that differ
    from photo to photo: z 4.8 there under ±15 %) it explains with the scene's middle grey for airlight, which
    outshines 59-74 % of the colours, where a real veil's outshines 98-100 %."""
    points = int(obs.point.max()) + 1 if len(obs) else 0
    if points == 0:
        raise ValueError("no observations to test the medium on")
    clear = _losses_at(obs, 0.0, points, iterations)[0]
    veiled, airlight = _losses_at(obs, beta_per_m, points, iterations)
    gain = torch.zeros(points, dtype=torch.float64).index_add_(0, obs.point, clear - veiled)
    gain = gain[torch.unique(obs.point)]
    spread = math.sqrt(len(gain)) * float(gain.std()) if len(gain) > 1 else 0.0
    total, clear_total = float(gain.sum()), float(clear.sum())
    return VeilEvidence(
        explained=total / clear_total if clear_total > 0 else 0.0,
        z=total / spread if spread > 0 else 0.0,
        brighter=float((obs.colour.mean(-1) < float(airlight.mean())).float().mean()),
    )


def fit_uniform_medium(
    obs: PointObservations,
    beta_range: tuple[float, float] = (1e-4, 0.3),
    iterations: int = 30,
    airlight: torch.Tensor | None = None,
) -> MediumFit:
    """The uniform medium (one β, A and one J per point) that explains ``obs`` best under the Charbonnier loss of
    `fit_medium`, without gradient steps: a scan of ln β over ``beta_range`` (1/m), then a golden-section search
    around the best; `MediumFit.explained` compares its loss with clear air's. Seconds for 10⁵ observations where
    `fit_medium`'s 1500 Adam steps take minutes. A given ``airlight`` [3] is held, not fitted."""
    points = int(obs.point.max()) + 1 if len(obs) else 0
    if points == 0:
        raise ValueError("no observations to fit the medium to")

    def loss_at(beta: float) -> float:
        return _fit_at(obs, beta, points, iterations, airlight)[0]

    grid = torch.logspace(math.log10(beta_range[0]), math.log10(beta_range[1]), 24, dtype=torch.float64)
    losses = [loss_at(float(b)) for b in grid]
    best = min(range(len(grid)), key=losses.__getitem__)
    lo, hi = math.log(float(grid[max(best - 1, 0)])), math.log(float(grid[min(best + 1, len(grid) - 1)]))
    golden = (math.sqrt(5.0) - 1.0) / 2.0
    a, b = hi - golden * (hi - lo), lo + golden * (hi - lo)
    fa, fb = loss_at(math.exp(a)), loss_at(math.exp(b))
    for _ in range(12):
        if fa <= fb:
            hi, b, fb = b, a, fa
            a = hi - golden * (hi - lo)
            fa = loss_at(math.exp(a))
        else:
            lo, a, fa = a, b, fb
            b = lo + golden * (hi - lo)
            fb = loss_at(math.exp(b))
    beta = math.exp((lo + hi) / 2.0)
    loss, fitted = _fit_at(obs, beta, points, iterations, airlight)
    clear = loss_at(0.0)
    return MediumFit(
        beta_per_m=beta,
        height_rate=0.0,
        airlight=(float(fitted[0]), float(fitted[1]), float(fitted[2])),
        observations=len(obs),
        points=len(torch.unique(obs.point)),
        explained=max(0.0, 1.0 - loss / clear) if clear > 0 else 0.0,
    )


def airlight_under_haze(
    brightest_haze: torch.Tensor, obs: PointObservations | None, min_explained: float
) -> torch.Tensor:
    """``brightest_haze`` [3] (the photos' dark-channel estimate) lowered channel by channel to the airlight that
    ``obs`` fit along with β (`fit_uniform_medium`) where that is darker and the fitted medium explains at least
    ``min_explained`` of the colour differences that clear air leaves (`MediumFit.explained`), else as given -> [3].
    A surface brighter than the airlight only raises the brightest haze, He et al.'s estimate: the fox under the third
    generator's smog (airlight (0.72, 0.70, 0.62), no sky in view, white wallpaper) reads (0.79, 0.78, 0.74), its
    plane sweep's points (0.74, 0.72, 0.65) and β 1.96e-2/m, the generator's, explaining 8.6 %. Brighter than that haze
    the fit only trades the airlight against β (metegs's own fog on the fox, whose airlight is that wallpaper: (0.93,
    0.95, 0.94) against (0.92, 0.94, 0.93), β 13 % under), so it never raises it; and where a uniform medium explains
    next to nothing, its airlight is unconstrained (the fox under the independent rain + fog, whose height fog no
    uniform medium fits: 0.1 % explained, (0.81, 0.83, 0.83), 2.4 dB lost against the haze's (0.94, 0.95, 0.95))."""
    if obs is None or len(obs) == 0:
        return brightest_haze
    fit = fit_uniform_medium(obs)
    if fit.explained < min_explained:
        return brightest_haze
    fitted = torch.tensor(fit.airlight, dtype=brightest_haze.dtype)
    return torch.minimum(brightest_haze, fitted.to(brightest_haze.device))
