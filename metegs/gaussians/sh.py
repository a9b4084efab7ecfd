"""Real spherical harmonics up to degree 3 (the 3DGS convention), RGB <-> DC coefficient."""

from __future__ import annotations

import torch

MAX_SH_DEGREE = 3
"""Highest SH degree the rasterisers evaluate."""

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def num_sh_bases(degree: int) -> int:
    """Number of SH coefficients per channel for ``degree`` (1, 4, 9, 16)."""
    return (degree + 1) ** 2


def rgb_to_sh(rgb: torch.Tensor) -> torch.Tensor:
    """Colour in [0, 1] -> DC coefficient (colour = 0.5 + C0 * dc). Any shape."""
    return (rgb - 0.5) / SH_C0


def sh_to_rgb(dc: torch.Tensor) -> torch.Tensor:
    """DC coefficient -> colour (before clamping). Any shape."""
    return dc * SH_C0 + 0.5


def eval_sh(degree: int, coeffs: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """Evaluate SH colour. coeffs: [N, K, 3] (K >= (degree+1)^2), dirs: [N, 3] unit -> [N, 3] (plus 0.5, unclamped)."""
    result = SH_C0 * coeffs[:, 0]
    if degree > 0:
        x, y, z = dirs[:, 0:1], dirs[:, 1:2], dirs[:, 2:3]
        result = result - SH_C1 * y * coeffs[:, 1] + SH_C1 * z * coeffs[:, 2] - SH_C1 * x * coeffs[:, 3]
        if degree > 1:
            xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
            result = (
                result
                + SH_C2[0] * xy * coeffs[:, 4]
                + SH_C2[1] * yz * coeffs[:, 5]
                + SH_C2[2] * (2.0 * zz - xx - yy) * coeffs[:, 6]
                + SH_C2[3] * xz * coeffs[:, 7]
                + SH_C2[4] * (xx - yy) * coeffs[:, 8]
            )
            if degree > 2:
                result = (
                    result
                    + SH_C3[0] * y * (3 * xx - yy) * coeffs[:, 9]
                    + SH_C3[1] * xy * z * coeffs[:, 10]
                    + SH_C3[2] * y * (4 * zz - xx - yy) * coeffs[:, 11]
                    + SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy) * coeffs[:, 12]
                    + SH_C3[4] * x * (4 * zz - xx - yy) * coeffs[:, 13]
                    + SH_C3[5] * z * (xx - yy) * coeffs[:, 14]
                    + SH_C3[6] * x * (xx - 3 * yy) * coeffs[:, 15]
                )
    return result + 0.5
