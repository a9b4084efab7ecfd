"""EWA projection of 3D Gaussians to screen space (pure torch, differentiable, NaN-safe for culled Gaussians)."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from metegs.cameras import quat_wxyz_to_rotmat


@dataclass
class Projected:
    """Screen-space Gaussians of one view. N is the number of input Gaussians (culled ones have radius 0)."""

    means2d: torch.Tensor
    """[N, 2] pixel coordinates of the projected means (x right, y down; pixel centres at +0.5)."""
    conics: torch.Tensor
    """[N, 3] inverse 2D covariance (a, b, c) of [[a, b], [b, c]]."""
    depths: torch.Tensor
    """[N] camera-space z of the means."""
    radii: torch.Tensor
    """[N] int32 screen radius in pixels (3 sigma); 0 for culled Gaussians."""
    extents: torch.Tensor
    """[N, 2] half-width and half-height (px) of the box where alpha can reach 1/255 (used for tile binning)."""


def covariance_3d(quats: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
    """World covariance R S S^T R^T. quats: [N, 4] wxyz, scales: [N, 3] linear -> [N, 3, 3]."""
    R = quat_wxyz_to_rotmat(quats)
    M = R * scales[:, None, :]
    return M @ M.transpose(1, 2)


def project_gaussians(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    viewmat: torch.Tensor,
    K: torch.Tensor,
    width: int,
    height: int,
    near: float = 0.01,
    far: float = 1e10,
    eps2d: float = 0.3,
    opacities: torch.Tensor | None = None,
) -> Projected:
    """Project Gaussians with the EWA linearisation (as in 3DGS).

    means [N, 3], quats [N, 4] (wxyz), scales [N, 3], viewmat [4, 4] world-to-camera (OpenCV), K [3, 3].
    Gaussians in front of ``near``, behind ``far``, with a non-positive 2D determinant, non-finite
    values, or whose 3-sigma box misses the image get radius 0. With ``opacities`` [N], the binning
    extents are exactly the box where alpha = o exp(-q/2) can still reach 1/255 (k = sqrt(2 ln(255 o))
    sigma, at most 3.33 sigma), so tile binning drops no contribution; without them the box is 3 sigma. Their outputs are finite placeholders
    and their gradients are zero (``torch.where`` keeps NaNs/Infs out of the backward pass).
    """
    R, T = viewmat[:3, :3], viewmat[:3, 3]
    p = means @ R.T + T
    tz = p[:, 2]
    finite = torch.isfinite(p).all(dim=1) & torch.isfinite(scales).all(dim=1) & torch.isfinite(quats).all(dim=1)
    in_depth = (tz > near) & (tz < far) & finite
    one = torch.ones_like(tz)
    tz_safe = torch.where(in_depth, tz, one)
    p_safe = torch.where(in_depth[:, None], p, torch.zeros_like(p))
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]

    # Clamp the linearisation point to the view frustum widened by 30 % of the half field of view (as 3DGS
    # and gsplat do): keeps J bounded for Gaussians far outside the image.
    lim_x_pos = (width - cx) / fx + 0.3 * (0.5 * width / fx)
    lim_x_neg = cx / fx + 0.3 * (0.5 * width / fx)
    lim_y_pos = (height - cy) / fy + 0.3 * (0.5 * height / fy)
    lim_y_neg = cy / fy + 0.3 * (0.5 * height / fy)
    tx = tz_safe * torch.minimum(torch.maximum(p_safe[:, 0] / tz_safe, -lim_x_neg), lim_x_pos)
    ty = tz_safe * torch.minimum(torch.maximum(p_safe[:, 1] / tz_safe, -lim_y_neg), lim_y_pos)
    zero = torch.zeros_like(tz)
    J = torch.stack(
        [fx / tz_safe, zero, -fx * tx / tz_safe**2, zero, fy / tz_safe, -fy * ty / tz_safe**2], dim=-1
    ).reshape(-1, 2, 3)

    scales_safe = torch.where(finite[:, None], scales, torch.ones_like(scales))
    quats_safe = torch.where(
        finite[:, None], quats, torch.tensor([1.0, 0, 0, 0], dtype=quats.dtype, device=quats.device)
    )
    cov3d = covariance_3d(quats_safe, scales_safe)
    JW = J @ R
    cov2 = JW @ cov3d @ JW.transpose(1, 2)
    overflow = ~torch.isfinite(cov2).all(dim=2).all(dim=1)
    if bool(overflow.any()):  # covariances beyond the float range (scales ~1e19): culled, with zero (not NaN) gradients
        in_depth = in_depth & ~overflow
        scales_safe = torch.where(overflow[:, None], torch.ones_like(scales_safe), scales_safe)
        cov3d = covariance_3d(quats_safe, scales_safe)
        cov2 = JW @ cov3d @ JW.transpose(1, 2)
    a = cov2[:, 0, 0] + eps2d
    b = cov2[:, 0, 1]
    c = cov2[:, 1, 1] + eps2d
    det = a * c - b * b
    ok = in_depth & (det > 0) & torch.isfinite(det)
    det_safe = torch.where(ok, det, one)
    conics = torch.stack([c / det_safe, -b / det_safe, a / det_safe], dim=-1)

    mx = fx * p_safe[:, 0] / tz_safe + cx
    my = fy * p_safe[:, 1] / tz_safe + cy
    means2d = torch.stack([mx, my], dim=-1)

    with torch.no_grad():
        mid = 0.5 * (a + c)
        lam = mid + torch.sqrt((mid * mid - det).clamp_min(0.1))
        radius = torch.ceil(3.0 * torch.sqrt(lam.clamp_min(0)))
        radius = torch.where(ok, radius, torch.zeros_like(radius))
        radius = torch.nan_to_num(radius, nan=0.0, posinf=0.0).clamp_max(1e7)
        k = torch.full_like(a, 3.0)
        if opacities is not None:
            k = torch.sqrt(2.0 * torch.log((255.0 * opacities.detach()).clamp_min(1.0)))
        extents = torch.stack(
            [torch.ceil(k * torch.sqrt(a.clamp_min(0))), torch.ceil(k * torch.sqrt(c.clamp_min(0)))], -1
        )
        extents = torch.nan_to_num(extents, nan=0.0, posinf=0.0).clamp_max(1e7)
        ex, ey = extents[:, 0], extents[:, 1]
        on_screen = (mx + ex > 0) & (mx - ex < width) & (my + ey > 0) & (my - ey < height) & (ex > 0) & (ey > 0)
        radii = torch.where(on_screen & ok, radius, torch.zeros_like(radius)).to(torch.int32)
    keep = radii > 0
    return Projected(
        means2d=torch.where(keep[:, None], means2d, torch.zeros_like(means2d)),
        conics=torch.where(keep[:, None], conics, torch.zeros_like(conics)),
        depths=torch.where(keep, tz_safe, one),
        radii=radii,
        extents=torch.where(
            keep[:, None] & (extents.amin(dim=1, keepdim=True) > 0), extents, torch.zeros_like(extents)
        ),
    )
