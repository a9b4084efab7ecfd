"""The rasterisation pipeline every tile backend shares: project, bin, colour, composite, background.

A backend only supplies the compositing function (torch reference, compiled CPU kernel, ...).
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from metegs.cameras import Cameras
from metegs.gaussians.model import GaussianSet
from metegs.gaussians.sh import SH_C0, eval_sh
from metegs.render.base import RenderOutput, RenderSettings
from metegs.render.projection import project_gaussians
from metegs.render.tiles import TileBins, bin_gaussians

CompositeFn = Callable[..., tuple[torch.Tensor, torch.Tensor, torch.Tensor]]
"""(means2d [N,2], conics [N,3], opacities [N], colors [N,D], depths [N], bins, width, height)
-> (color [H,W,D], alpha [H,W], depth_sum [H,W])."""


def gaussian_colors(g: GaussianSet, campos: torch.Tensor, sh_degree: int) -> torch.Tensor:
    """View-dependent colours. campos: [3] -> [N, 3], clamped at 0 (as 3DGS)."""
    if g.sh.shape[1] == 1 or sh_degree == 0:
        return (SH_C0 * g.sh[:, 0] + 0.5).clamp_min(0.0)
    d = g.means - campos
    d = torch.where(torch.isfinite(d).all(dim=1, keepdim=True), d, torch.zeros_like(d))  # NaN means stay local
    d = d / d.norm(dim=1, keepdim=True).clamp_min(1e-12)
    return eval_sh(sh_degree, g.sh, d).clamp_min(0.0)


def resolve_sh_degree(g: GaussianSet, settings: RenderSettings) -> int:
    """The SH degree to evaluate: the settings' (at most what the coefficients hold), else all of them."""
    available = int(round(g.sh.shape[1] ** 0.5)) - 1
    return available if settings.sh_degree is None else min(settings.sh_degree, available)


def finish_render(
    color: torch.Tensor,
    alpha: torch.Tensor,
    depth_sum: torch.Tensor,
    settings: RenderSettings,
    radii: torch.Tensor,
    means2d: torch.Tensor,
    num_intersections: int,
) -> RenderOutput:
    """Background and expected depth. color [H, W, 3], alpha [H, W], depth_sum [H, W] -> RenderOutput."""
    rgb = color + (1.0 - alpha)[..., None] * settings.background_tensor(color)
    depth = depth_sum / alpha.clamp_min(1e-10)
    height, width = alpha.shape
    return RenderOutput(
        rgb=rgb,
        alpha=alpha,
        depth=depth,
        radii=radii,
        means2d=means2d,
        num_intersections=num_intersections,
        width=width,
        height=height,
    )


def rasterize(
    gaussians: GaussianSet, camera: Cameras, settings: RenderSettings | None, composite: CompositeFn
) -> RenderOutput:
    """Render one view (camera of len 1) with the torch projection and the given compositing function."""
    s = settings or RenderSettings()
    width, height = int(camera.width[0]), int(camera.height[0])
    viewmat = camera.world_to_cameras()[0].to(gaussians.means)
    K = camera.intrinsics()[0].to(gaussians.means)
    proj = project_gaussians(
        gaussians.means,
        gaussians.quats,
        gaussians.scales,
        viewmat,
        K,
        width,
        height,
        near=s.near,
        far=s.far,
        eps2d=s.eps2d,
        opacities=gaussians.opacities,
    )
    means2d = proj.means2d
    if means2d.requires_grad:
        means2d.retain_grad()
    bins: TileBins = bin_gaussians(means2d.detach(), proj.extents, proj.depths.detach(), width, height)
    colors = gaussian_colors(gaussians, camera.centers[0].to(gaussians.means), resolve_sh_degree(gaussians, s))
    color, alpha, depth_sum = composite(
        means2d, proj.conics, gaussians.opacities, colors, proj.depths, bins, width, height
    )
    return finish_render(color, alpha, depth_sum, s, proj.radii, means2d, bins.num_intersections)
