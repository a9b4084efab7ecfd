"""Depth-aware opacity pruning (Deblurring-3DGS, Lee et al. 2024): far Gaussians get a lower opacity threshold.

A Gaussian ``j`` is pruned when ``sigmoid(o_j) < t_p / d̂_j`` where ``d̂_j ∈ [1, w_p]`` is its normalised depth:
near Gaussians keep the base threshold ``t_p``, the farthest get ``t_p / w_p``. Far Gaussians cover few pixels
and receive weak gradients, so a uniform threshold removes them before they can grow opaque.

Two depth definitions (``depth_mode``):

- ``"camera"`` (default): ``d_j`` = median camera-space depth (OpenCV z) over the training cameras that see
  the Gaussian's mean (in front of the camera, beyond ``NEAR``, projecting inside the image), normalised
  with the 1st and 99th percentiles over the Gaussians seen by at least one camera::

      d̂_j = 1 + (w_p − 1) · clamp((d_j − p1) / (p99 − p1), 0, 1)

  This follows the viewing direction of every camera, so it works for 360° captures as well as for
  forward-facing ones, and the percentiles make it insensitive to a few stray far Gaussians.
  A Gaussian **seen by no training camera** gets ``d̂ = 1``, i.e. the full base threshold ``t_p``: no view
  constrains it, so the depth rule gives it no protection. When every seen Gaussian has the same depth
  (``p99 == p1``) all get ``d̂ = 1``.
- ``"world_z"``: the reference code, ``d_j`` = world z of the mean, min–max normalised over all Gaussians::

      d̂_j = 1 + (w_p − 1) · (z_j − min z) / (max z − min z)

  (meaningful only when world z follows the viewing axis, as in LLFF-style forward-facing scenes; when
  ``max z == min z`` every ``d̂`` is 1 instead of the reference's division by zero).

Use it as the ``prune_rule`` of `metegs.densify.adc.AdaptiveDensityControl`::

    adc.prune_rule = DepthPruneConfig().setup(cameras=train_cameras)

The camera projection is vectorised over cameras and chunked over Gaussians (about 4M Gaussian-camera
pairs per chunk), so 100k Gaussians × 50 cameras takes a fraction of a second on a CPU.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import torch

from metegs.cameras import Cameras
from metegs.config import InstantiateConfig
from metegs.errors import ConfigError
from metegs.gaussians.model import GaussianModel

__all__ = ["DepthAwarePruning", "DepthPruneConfig", "camera_depths", "median_camera_depth"]

NEAR = 0.01
"""Camera-space depth below which a camera does not see a Gaussian (the rasteriser's default near plane)."""
_PAIRS_PER_CHUNK = 1 << 22


@dataclass
class DepthPruneConfig(InstantiateConfig):
    """Depth-aware opacity thresholds for pruning (Deblurring-3DGS), used as ADC's ``prune_rule``."""

    _target: type = field(default_factory=lambda: DepthAwarePruning, repr=False)
    depth_mode: Literal["camera", "world_z"] = "camera"
    """camera: median camera-space depth over the training cameras that see the Gaussian, normalised by the
    1st-99th percentiles; world_z: the Deblurring-3DGS reference (min-max of world z)."""
    weight: float = 3.0
    """w_p: thresholds range from t_p (near) to t_p / w_p (far)."""


@torch.no_grad()
def median_camera_depth(points: torch.Tensor, cameras: Cameras, near: float = NEAR) -> torch.Tensor:
    """Median camera-space depth of each point over the cameras that see it; NaN where none does.

    Args:
        points: [N, 3] world positions.
        cameras: the cameras (moved to ``points.device``).

    Returns:
        [N] depths (the lower median for an even number of cameras, as ``torch.median``).
    """
    cams = cameras.to(points.device)
    n, c = points.shape[0], len(cams)
    out = torch.full((n,), float("nan"), dtype=points.dtype, device=points.device)
    chunk = max(1, _PAIRS_PER_CHUNK // max(c, 1))
    for start in range(0, n, chunk):
        z, seen = camera_depths(points[start : start + chunk], cams, near)
        out[start : start + chunk] = torch.where(seen, z, torch.nan).nanmedian(dim=0).values
    return out


def camera_depths(points: torch.Tensor, cameras: Cameras, near: float = NEAR) -> tuple[torch.Tensor, torch.Tensor]:
    """Camera-space depth (OpenCV z) of ``points`` [N, 3] in each of ``cameras`` (on the points' device) -> (z [C, N],
    seen [C, N] bool: in front beyond ``near`` and projecting inside the image)."""
    w2c = cameras.world_to_cameras().to(points.dtype)
    R, t = w2c[:, :3, :3], w2c[:, :3, 3]
    fx, fy, cx, cy = (getattr(cameras, k).to(points.dtype)[:, None] for k in ("fx", "fy", "cx", "cy"))
    width, height = cameras.width.to(points.dtype)[:, None], cameras.height.to(points.dtype)[:, None]
    p = torch.einsum("cij,nj->cni", R, points) + t[:, None, :]  # [C, N, 3]
    z = p[..., 2]
    zs = z.clamp_min(near)
    u = fx * p[..., 0] / zs + cx
    v = fy * p[..., 1] / zs + cy
    return z, (z > near) & (u >= 0) & (u < width) & (v >= 0) & (v < height)


def _percentile(x: torch.Tensor, q: float) -> torch.Tensor:
    """Linear-interpolation percentile (``q`` in [0, 1]) of a 1-D tensor, for any length."""
    s = x.sort().values
    pos = q * (s.numel() - 1)
    lo = int(pos)
    hi = min(lo + 1, s.numel() - 1)
    return s[lo] + (s[hi] - s[lo]) * (pos - lo)


class DepthAwarePruning:
    """Per-Gaussian opacity thresholds ``base / d̂`` (see the module docstring); callable as ``(model, base)``.

    Attributes:
        last_stats: after each call, ``{"seen": Gaussians seen by a training camera, "far": those at d̂ > 1}``
            (camera mode; ``seen`` is every Gaussian in world_z mode).
    """

    def __init__(self, config: DepthPruneConfig, cameras: Cameras):
        if config.weight < 1:
            raise ConfigError(f"depth_prune.weight (w_p) must be >= 1, got {config.weight}")
        if config.depth_mode not in ("camera", "world_z"):
            raise ConfigError(f"depth_prune.depth_mode must be 'camera' or 'world_z', got {config.depth_mode!r}")
        self.config = config
        self.cameras = cameras
        self.last_stats: dict[str, int] = {}

    @torch.no_grad()
    def normalised_depth(self, means: torch.Tensor) -> torch.Tensor:
        """d̂ ∈ [1, w_p] of each mean [N, 3] -> [N]."""
        w = self.config.weight
        ones = torch.ones(means.shape[0], dtype=means.dtype, device=means.device)
        if means.shape[0] == 0:
            return ones
        if self.config.depth_mode == "world_z":
            z = means[:, 2]
            span = z.max() - z.min()
            self.last_stats = {"seen": int(z.numel())}
            if not span > 0:
                return ones
            return 1 + (w - 1) * (z - z.min()) / span
        depth = median_camera_depth(means, self.cameras)
        seen = ~torch.isnan(depth)
        self.last_stats = {"seen": int(seen.sum())}
        if not seen.any():
            return ones
        lo, hi = _percentile(depth[seen], 0.01), _percentile(depth[seen], 0.99)
        if not hi > lo:
            return ones
        t = ((depth - lo) / (hi - lo)).clamp(0, 1)
        return torch.where(seen, 1 + (w - 1) * t, ones)

    @torch.no_grad()
    def thresholds(self, model: GaussianModel, base: float) -> torch.Tensor:
        """[N] opacity thresholds ``base / d̂`` for the model's Gaussians."""
        d = self.normalised_depth(model.params["means"].detach())
        self.last_stats["far"] = int((d > 1).sum())
        return base / d

    __call__ = thresholds
