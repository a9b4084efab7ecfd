"""Gaussian Transformation Network (after Deblurring-3DGS's GTnet): per-view, bounded growth of the scene
Gaussians that explains blur in the degraded photos without putting it into the scene.

Inputs (all detached, 91-D): γ(x) of the normalised position with 3 frequencies (21), γ(c) of the
normalised camera centre with 10 frequencies (63), log-scale (3) and unit quaternion (4). An MLP of
three 32-wide ReLU layers (64 in the reference) gives heads δs [3], δr [4] in [1, max_factor]: one-sided (Gaussians can only
widen, by at most 10 % by default), as in the reference. Used in the weather branch during training
only; clean renders, evaluation and export never see it.

The reference bounds the heads with clamp(0.01·raw + 0.99, 1, 1.1). With the small initial head
weights raw is near 0, so almost every factor sits on the lower clamp, whose gradient is zero: the
network barely learns (tests/models/test_gtn.py shows it). Here δ = 1 + (max − 1)·sigmoid(raw + b),
with b set so that δ starts at 1 + `init_growth`·(max − 1): the same range, gradients everywhere.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Annotated

import torch
from torch import nn

from metegs.cameras import Cameras
from metegs.errors import ConfigError
from metegs.gaussians.model import GaussianSet
from metegs.validate import NON_NEGATIVE, Range


@dataclass
class GTNConfig:
    """The Gaussian Transformation Network of the weather branch."""

    enabled: bool = True
    """Use the GTN in the weather branch where the weather blurs the photos (off: the weather branch renders the scene
    Gaussians as they are)."""
    blind: bool = False
    """Use it in blind training too (left out there, a real street scored 0.19 dB better over eight runs, from
    −0.54 to +0.88, and trained 15-18 % faster)."""
    position_frequencies: Annotated[int, NON_NEGATIVE] = 3
    """Frequencies of the positional encoding of the Gaussian position."""
    view_frequencies: Annotated[int, NON_NEGATIVE] = 10
    """Frequencies of the positional encoding of the camera centre (the view)."""
    width: Annotated[int, Range(1)] = 32
    """Width of the hidden layers (the reference's 64 scored no better on the built-in scene or two real captures
    under independent weather, and cost 3-15 % more training time: docs/benchmark.md)."""
    layers: Annotated[int, Range(1)] = 3
    """Number of hidden ReLU layers."""
    init_growth: Annotated[float, Range(0, 1, lo_open=True, hi_open=True)] = 0.01
    """Initial growth as a fraction of the allowed range: δ = 1 + (max-factor − 1)·sigmoid(raw + logit(this))."""
    max_factor: Annotated[float, Range(1)] = 1.1
    """Largest growth factor of scale and rotation components."""
    lr: Annotated[float, NON_NEGATIVE] = 1e-3
    """Learning rate of the network."""


def positional_encoding(x: torch.Tensor, frequencies: int) -> torch.Tensor:
    """[..., D] -> [..., D·(1 + 2F)]: x, sin(2^k x), cos(2^k x) for k < F."""
    if frequencies <= 0:
        return x
    scales = 2.0 ** torch.arange(frequencies, dtype=x.dtype, device=x.device)
    angles = (x[..., None, :] * scales[:, None]).flatten(-2)
    return torch.cat([x, torch.sin(angles), torch.cos(angles)], dim=-1)


class GaussianTransformationNetwork(nn.Module):
    """Bounded multiplicative corrections of scales and rotations for one view."""

    def __init__(self, config: GTNConfig, centre: torch.Tensor, extent: float):
        super().__init__()
        if not 0.0 < config.init_growth < 1.0 or not config.max_factor > 1.0:
            raise ConfigError(
                f"GTN needs 0 < init-growth < 1 and max-factor > 1, got {config.init_growth}, {config.max_factor}"
            )
        self.config = config
        self.register_buffer("centre", centre.detach().float().reshape(3).clone())
        self.extent = max(float(extent), 1e-6)
        c = config
        in_dim = 3 * (1 + 2 * c.position_frequencies) + 3 * (1 + 2 * c.view_frequencies) + 3 + 4
        layers: list[nn.Module] = []
        dim = in_dim
        for _ in range(c.layers):
            layers += [nn.Linear(dim, c.width), nn.ReLU()]
            dim = c.width
        self.trunk = nn.Sequential(*layers)
        self.head_scale = nn.Linear(dim, 3)
        self.head_rot = nn.Linear(dim, 4)
        for m in self.modules():
            if isinstance(m, nn.Linear):
                gain = 0.1 if m.out_features <= 4 else 1.0
                nn.init.xavier_normal_(m.weight, gain=gain)
                nn.init.zeros_(m.bias)

    def factors(self, means: torch.Tensor, scales: torch.Tensor, quats: torch.Tensor, cam_centre: torch.Tensor):
        """Growth factors. means, scales [N, 3], quats [N, 4], cam_centre [3] -> (δs [N, 3], δr [N, 4]) in [1, max]."""
        c = self.config
        x = ((means.detach() - self.centre) / self.extent).float()
        v = ((cam_centre.detach().reshape(1, 3) - self.centre) / self.extent).float()
        q = quats.detach().float()
        q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        pe_x = positional_encoding(x, c.position_frequencies)
        pe_v = positional_encoding(v, c.view_frequencies)
        per_gaussian = torch.cat([pe_x, torch.log(scales.detach().float().clamp_min(1e-12)), q], dim=-1)
        # The first layer on [γ(x), γ(c), s, q]: γ(c) is the same for every Gaussian of the view, so its
        # product with the weights is one bias vector instead of an [N, 63] block.
        first = self.trunk[0]
        nx = pe_x.shape[1]
        w = first.weight
        w_view = w[:, nx : nx + pe_v.shape[1]]
        w_rest = torch.cat([w[:, :nx], w[:, nx + pe_v.shape[1] :]], dim=1)
        h = torch.nn.functional.linear(per_gaussian, w_rest, first.bias + pe_v[0] @ w_view.T)
        h = self.trunk[1:](h)
        bias = math.log(c.init_growth / (1.0 - c.init_growth))
        span = c.max_factor - 1.0
        ds = 1.0 + span * torch.sigmoid(self.head_scale(h) + bias)
        dr = 1.0 + span * torch.sigmoid(self.head_rot(h) + bias)
        return ds, dr

    def forward(
        self, gaussians: GaussianSet, cam_centre: torch.Tensor, only: torch.Tensor | None = None
    ) -> GaussianSet:
        """The scene Gaussians as the degraded view sees them (means, opacity and colour unchanged).

        only: [N] bool, the Gaussians to transform (e.g. `may_be_visible`); the others keep factor 1, which is
        exact for Gaussians the view cannot see and saves the network's work on them."""
        g = gaussians
        if only is None:
            ds, dr = self.factors(g.means, g.scales, g.quats, cam_centre)
        else:
            ds = torch.ones_like(g.scales, dtype=torch.float32)
            dr = torch.ones_like(g.quats, dtype=torch.float32)
            if bool(only.any()):
                sub_ds, sub_dr = self.factors(g.means[only], g.scales[only], g.quats[only], cam_centre)
                ds = ds.index_put((only,), sub_ds)
                dr = dr.index_put((only,), sub_dr)
        return GaussianSet(
            gaussians.means,
            gaussians.quats * dr.to(gaussians.quats),
            gaussians.scales * ds.to(gaussians.scales),
            gaussians.opacities,
            gaussians.sh,
        )


def may_be_visible(gaussians: GaussianSet, camera: Cameras, growth: float = 1.0, near: float = 0.01) -> torch.Tensor:
    """[N] bool: the Gaussians whose footprint, grown by up to ``growth``, can reach the image of ``camera`` (len 1).

    Conservative: a Gaussian in front of the near plane counts when its centre's projection lies within
    r = 3.34·growth·σ_max·‖J‖_F + 2 px of the image, ‖J‖_F the Frobenius norm of the projection's Jacobian
    (bounds the 2D standard deviation; 3.34σ is the rasterisers' widest box, 2 px covers the screen dilation)."""
    w2c = camera.world_to_cameras()[0].to(gaussians.means)
    p = gaussians.means.detach() @ w2c[:3, :3].T + w2c[:3, 3]
    z = p[:, 2]
    zc = z.clamp_min(near)
    x, y = p[:, 0] / zc, p[:, 1] / zc
    f = float(max(camera.fx[0], camera.fy[0]))
    jac = (f / zc) * torch.sqrt(2.0 + x * x + y * y)
    radius = 3.34 * growth * gaussians.scales.detach().amax(-1) * jac + 2.0
    u = float(camera.fx[0]) * x + float(camera.cx[0])
    v = float(camera.fy[0]) * y + float(camera.cy[0])
    width, height = int(camera.width[0]), int(camera.height[0])
    return (z > near) & (u + radius >= 0) & (u - radius <= width) & (v + radius >= 0) & (v - radius <= height)
