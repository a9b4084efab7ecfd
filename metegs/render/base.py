"""What every rasteriser takes and returns (backend-independent; knows nothing of weather)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import torch

from metegs.cameras import Cameras
from metegs.gaussians.model import GaussianSet

ALPHA_MAX = 0.99
"""Per-Gaussian alpha clamp (3DGS): keeps 1 - alpha away from 0."""
ALPHA_MIN = 1.0 / 255.0
"""Contributions below this alpha are skipped."""
T_MIN = 1e-4
"""A pixel stops compositing once its transmittance would fall below this."""


@dataclass
class RenderSettings:
    """Per-call rendering options."""

    background: tuple[float, float, float] | torch.Tensor = (0.0, 0.0, 0.0)
    """Background colour behind the Gaussians (RGB in [0, 1])."""
    sh_degree: int | None = None
    """SH degree to evaluate; None uses all coefficients given."""
    near: float = 0.01
    """Near plane (world units); Gaussians closer are culled."""
    far: float = 1e10
    """Far plane (world units)."""
    eps2d: float = 0.3
    """Screen-space dilation added to the 2D covariance (px^2), as in 3DGS."""

    def background_tensor(self, like: torch.Tensor) -> torch.Tensor:
        return torch.as_tensor(self.background, dtype=like.dtype, device=like.device).reshape(3)


@dataclass
class RenderOutput:
    """A rendered view. Images are channels-last."""

    rgb: torch.Tensor
    """[H, W, 3] colour composited over the background."""
    alpha: torch.Tensor
    """[H, W] accumulated opacity."""
    depth: torch.Tensor
    """[H, W] expected depth sum(w z) / alpha (camera z)."""
    radii: torch.Tensor
    """[N] int32 screen radii; 0 = not drawn in this view."""
    means2d: torch.Tensor
    """[N, 2] projected means; after backward its ``.grad`` drives densification."""
    num_intersections: int
    """Number of (tile, Gaussian) pairs rasterised."""
    width: int
    height: int


class Rasterizer(Protocol):
    """A rasteriser backend (registry kind ``rasterizer``)."""

    name: str

    def render(self, gaussians: GaussianSet, camera: Cameras, settings: RenderSettings | None = None) -> RenderOutput:
        """Render ``gaussians`` seen from a single camera."""
        ...
