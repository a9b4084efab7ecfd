"""Extra-point compensation (Deblurring-3DGS, Lee et al. 2024): once, early in training, add Gaussians in the
sparse regions of the scene, coloured from their nearest existing neighbours.

What happens at step ``round(at · max_steps)`` (once; the first call at or after that step):

1. **Count**: ``V / (rate · extent)³`` where ``V`` is the volume of the robust box (below) of the *initial*
   points, capped by ``max_points`` and by ``max_relative ×`` the current number of Gaussians (default 1×:
   never more than doubles the model, so a short CPU run cannot be swamped by a huge sparse point cloud).
   The reference uses ``pts_rate = 1.1`` raw scene units; here the spacing is relative to the scene extent.
   ``rate <= 0`` asks for ``max_points`` directly (as the reference's ``pts_rate <= 0``), still capped.
2. **Sampling**: uniform in the robust box of the *current* means: per axis from the 10th smallest to the
   10th largest coordinate (the reference's ``pts_add_bound = 10``; for sets of fewer than 100 points the
   trim is at most 10% of the points, and at least the extreme ones).
3. **Neighbours**: the ``neighbours`` (K) nearest existing Gaussians of each new point (SciPy cKDTree on the
   CPU, chunked ``torch.cdist`` elsewhere, instead of the reference's per-point Python loop). Neighbours at a
   distance ``>= max_distance · extent`` are dropped, and so are new points left with none.
4. **New Gaussians**: all SH coefficients (``sh0`` and ``shN``) are the weighted mean of the kept neighbours'
   with **inverse-distance** weights ``w_k ∝ 1/d_k``; scale (isotropic) = RMS distance to the kept neighbours
   (3DGS's initial-scale rule), at most the mean spacing of the new points so that they do not overlap one
   another; identity rotation; opacity 0.1. They are appended with zero Adam moments; existing Gaussians
   and their moments are untouched.

``parity=True`` reproduces the reference code instead: distance-*proportional* colour weights
``w_k = d_k / Σ d`` (equal weights if all distances are 0), then a **global re-initialisation** of every
Gaussian, old and new: scale = ``log sqrt(mean of the squared distances to the 3 nearest other Gaussians)``,
identity rotation, opacity 0.1, and all optimiser state cleared (the reference builds a new Adam).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from metegs.config import InstantiateConfig
from metegs.densify.surgery import append_rows
from metegs.errors import ConfigError
from metegs.gaussians.model import GaussianModel, inverse_sigmoid

__all__ = ["ExtraPointCompensation", "ExtraPointsConfig", "knn", "robust_box"]

NEW_OPACITY = 0.1
BOX_TRIM = 10


@dataclass
class ExtraPointsConfig(InstantiateConfig):
    """Extra-point compensation of sparse regions (Deblurring-3DGS), run once early in training."""

    _target: type = field(default_factory=lambda: ExtraPointCompensation, repr=False)
    at: float = 2500 / 20000
    """Fraction of the run at which points are added, once (Deblurring-3DGS: step 2500 of 20k)."""
    rate: float = 0.02
    """Point spacing as a fraction of the scene extent: count = volume / (rate · extent)³ (<= 0: max_points)."""
    max_points: int = 200_000
    """At most this many new points."""
    max_relative: float = 1.0
    """At most this many times the current number of Gaussians."""
    neighbours: int = 4
    """K nearest existing Gaussians that colour a new point."""
    max_distance: float = 0.15
    """t_d as a fraction of the scene extent: farther neighbours are ignored; points with none are dropped."""
    parity: bool = False
    """Reproduce the reference: distance-proportional colour weights and a global re-initialisation of scales,
    rotations, opacities and the optimiser state."""
    seed: int = 0
    """Seed of the point sampling."""


def robust_box(points: torch.Tensor, trim: int = BOX_TRIM) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-axis box from the ``trim``-th smallest to the ``trim``-th largest coordinate of ``points`` [P, 3]
    (``trim`` lowered to 10% of P, at least 1, for small sets). Returns ``(low [3], high [3])``."""
    p = points.shape[0]
    if p == 0:
        raise ValueError("robust_box needs at least one point")
    k = max(1, min(trim, p // 10))
    s = points.sort(dim=0).values
    return s[k - 1], s[p - k]


def knn(
    query: torch.Tensor,
    ref: torch.Tensor,
    k: int,
    max_distance: float = math.inf,
    method: str = "auto",
    chunk: int = 4096,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The ``k`` nearest ``ref`` points [N, 3] of each ``query`` point [M, 3], nearest first.

    Neighbours at a distance ``>= max_distance`` (and missing ones when ``N < k``) come back with distance
    ``inf`` and index 0. ``method``: ``"kdtree"`` (SciPy cKDTree, CPU), ``"torch"`` (chunked ``torch.cdist``,
    any device) or ``"auto"`` (kdtree for CPU tensors).

    Returns:
        distances [M, k] and indices [M, k] (int64), on ``query.device``.
    """
    m, n = query.shape[0], ref.shape[0]
    dist = torch.full((m, k), math.inf, dtype=query.dtype, device=query.device)
    idx = torch.zeros((m, k), dtype=torch.int64, device=query.device)
    kk = min(k, n)
    if m == 0 or kk == 0:
        return dist, idx
    if method == "auto":
        method = "kdtree" if query.device.type == "cpu" else "torch"
    if method == "kdtree":
        from scipy.spatial import cKDTree

        tree = cKDTree(ref.detach().cpu().double().numpy())
        bound = max_distance if math.isfinite(max_distance) else np.inf
        d, i = tree.query(query.detach().cpu().double().numpy(), k=kk, distance_upper_bound=bound)
        d, i = np.asarray(d).reshape(m, kk), np.asarray(i).reshape(m, kk)
        i[~np.isfinite(d)] = 0
        dist[:, :kk] = torch.from_numpy(d).to(dist)
        idx[:, :kk] = torch.from_numpy(i).to(idx)
    elif method == "torch":
        for start in range(0, m, chunk):
            d = torch.cdist(query[start : start + chunk].double(), ref.double())
            top = d.topk(kk, dim=1, largest=False)
            dist[start : start + chunk, :kk] = top.values.to(dist)
            idx[start : start + chunk, :kk] = top.indices
    else:
        raise ValueError(f"knn method must be 'auto', 'kdtree' or 'torch', got {method!r}")
    far = dist >= max_distance
    dist[far] = math.inf
    idx[far] = 0
    return dist, idx


class ExtraPointCompensation:
    """Adds points in sparse regions once (see the module docstring); a densifier with ``step`` and state.

    Attributes:
        step_at: the step at which the points are added.
        volume: volume of the robust box of the initial points.
        done: whether the points were added already.
        last: ``{"requested": sampled points, "added": kept ones}`` after the run.
    """

    def __init__(self, config: ExtraPointsConfig, max_steps: int, extent: float, initial_points: torch.Tensor):
        if config.neighbours < 1 or config.max_distance <= 0 or config.max_points < 0 or config.max_relative < 0:
            raise ConfigError(
                "extra_points: neighbours must be >= 1, max_distance > 0, max_points and "
                f"max_relative >= 0 (got {config})"
            )
        self.config = config
        self.extent = float(extent)
        self.step_at = int(round(config.at * max_steps))
        pts = torch.as_tensor(np.asarray(initial_points) if not torch.is_tensor(initial_points) else initial_points)
        pts = pts.detach().reshape(-1, 3).double().cpu()
        pts = pts[torch.isfinite(pts).all(dim=1)]
        if pts.shape[0]:
            low, high = robust_box(pts)
            self.volume = float((high - low).clamp_min(0).prod())
        else:
            self.volume = 0.0
        self.done = False
        self.last: dict[str, int] = {}

    def planned_count(self, current: int) -> int:
        """How many points to sample when the model holds ``current`` Gaussians."""
        c = self.config
        wanted = c.max_points if c.rate <= 0 else self.volume / (c.rate * self.extent) ** 3
        return int(round(max(0.0, min(wanted, c.max_points, c.max_relative * current))))

    def step(self, model: GaussianModel, optimizers: dict, step: int) -> dict[str, int]:
        """Add the points at ``step_at`` (once): ``{"extra_points": n}`` then, ``{}`` otherwise."""
        if self.done or step < self.step_at:
            return {}
        self.done = True
        return {"extra_points": self.add_points(model, optimizers)}

    @torch.no_grad()
    def add_points(self, model: GaussianModel, optimizers: dict) -> int:
        """Sample, colour and append the new points now; returns how many were added."""
        c = self.config
        params = model.params
        means = params["means"].detach()
        n = means.shape[0]
        count = self.planned_count(n)
        self.last = {"requested": count, "added": 0}
        if count == 0 or n == 0:
            return 0
        low, high = robust_box(means)
        g = torch.Generator().manual_seed(c.seed)
        new = (low.cpu() + (high - low).cpu() * torch.rand(count, 3, generator=g, dtype=means.dtype)).to(means.device)
        t_d = c.max_distance * self.extent
        dist, idx = knn(new, means, c.neighbours, max_distance=t_d)
        valid = torch.isfinite(dist)
        keep = valid.any(dim=1)
        new, dist, idx, valid = new[keep], dist[keep], idx[keep], valid[keep]
        m = new.shape[0]
        self.last["added"] = m
        if m == 0:
            return 0
        d0 = torch.where(valid, dist, torch.zeros_like(dist))
        if c.parity:  # the reference: w_k = d_k / sum d (equal weights when all distances are 0)
            w = d0
            total = w.sum(dim=1, keepdim=True)
            w = torch.where(total > 0, w / total.clamp_min(1e-30), valid.to(w) / valid.sum(1, keepdim=True))
        else:  # inverse distance; a neighbour at distance 0 takes all the weight
            w = torch.where(valid, 1.0 / d0.clamp_min(1e-12 * max(self.extent, 1e-12)), torch.zeros_like(d0))
            w = w / w.sum(dim=1, keepdim=True)
        rows = {}
        for name in ("sh0", "shN"):
            p = params[name].detach()
            rows[name] = torch.einsum("mk,mk...->m...", w.to(p), p[idx])
        spacing = ((high - low).clamp_min(0).prod() / m) ** (1.0 / 3.0)
        rms = ((d0**2).sum(1) / valid.sum(1)).sqrt()
        scale = rms.clamp(min=1e-7, max=float(spacing) if spacing > 0 else math.inf)
        rows["means"] = new
        rows["scales"] = torch.log(scale)[:, None].repeat(1, 3)
        rows["quats"] = torch.tensor([1.0, 0.0, 0.0, 0.0], device=means.device).repeat(m, 1)
        rows["opacities"] = inverse_sigmoid(torch.full((m,), NEW_OPACITY, device=means.device))
        append_rows(params, optimizers, {k: rows[k].to(params[k]) for k in params.keys()})
        if c.parity:
            self._reinitialise_all(model, optimizers)
        return m

    def _reinitialise_all(self, model: GaussianModel, optimizers: dict) -> None:
        """The reference's global reset: every scale from its 3 nearest neighbours, identity rotation, opacity
        0.1, optimiser state cleared."""
        params = model.params
        means = params["means"].detach()
        dist, _ = knn(means, means, 4)  # the point itself comes first
        d = dist[:, 1:]
        d = torch.where(torch.isfinite(d), d, torch.nan)
        mean_sq = (d**2).nanmean(dim=1).nan_to_num(1.0).clamp_min(1e-14)
        params["scales"].data = (0.5 * torch.log(mean_sq))[:, None].repeat(1, 3).to(params["scales"])
        params["quats"].data = torch.tensor([1.0, 0.0, 0.0, 0.0]).to(params["quats"]).repeat(len(model), 1)
        params["opacities"].data = inverse_sigmoid(torch.full((len(model),), NEW_OPACITY)).to(params["opacities"])
        for opt in optimizers.values():
            opt.state.clear()

    def state_dict(self) -> dict:
        return {"done": self.done, "volume": self.volume}

    def load_state_dict(self, d: dict) -> None:
        """A resumed run's compensator: the volume of the run's initial points, not of the checkpoint's."""
        self.done = bool(d.get("done", False))
        self.volume = float(d.get("volume", self.volume))
