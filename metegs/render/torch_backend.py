"""The `torch` rasteriser: the reference backend, pure PyTorch on any device, differentiable by autograd.

Per tile, Gaussians are composited front to back in chunks of ``chunk`` Gaussians (the only Python
loop, ~max_list_length / chunk iterations); tiles whose pixels are all saturated (T < 1e-4) leave the
loop early, empty tiles cost nothing.
"""

from __future__ import annotations

from functools import partial

import torch

from metegs.cameras import Cameras
from metegs.gaussians.model import GaussianSet
from metegs.render.base import ALPHA_MAX, ALPHA_MIN, T_MIN, RenderOutput, RenderSettings
from metegs.render.pipeline import rasterize
from metegs.render.tiles import TILE_SIZE


def composite_tiles(
    means2d: torch.Tensor,
    conics: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    depths: torch.Tensor,
    bins,
    width: int,
    height: int,
    chunk: int = 32,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Front-to-back alpha compositing over tiles.

    means2d [N, 2], conics [N, 3], opacities [N], colors [N, D], depths [N] ->
    (color [H, W, D], alpha [H, W], depth_sum [H, W]) with depth_sum = sum_i w_i z_i.
    alpha_i = min(0.99, o_i exp(-q_i/2)), skipped below 1/255; a pixel stops once T < 1e-4 (the
    contribution that would bring it below is not added, as in the CUDA reference).
    """
    device, dtype = means2d.device, means2d.dtype
    tiles = bins.tiles_x * bins.tiles_y
    P = TILE_SIZE * TILE_SIZE
    D = colors.shape[1]
    counts = bins.counts
    iy, ix = torch.meshgrid(
        torch.arange(TILE_SIZE, device=device), torch.arange(TILE_SIZE, device=device), indexing="ij"
    )
    tile_idx = torch.arange(tiles, device=device)
    pix_x = (tile_idx % bins.tiles_x)[:, None] * TILE_SIZE + ix.reshape(1, P) + 0.5  # [tiles, P]
    pix_y = (tile_idx // bins.tiles_x)[:, None] * TILE_SIZE + iy.reshape(1, P) + 0.5

    # Empty slices sum to an exact 0 that keeps the outputs in the autograd graph (zero gradients, never NaN),
    # so a view that sees no Gaussian still backpropagates.
    anchor = sum(t[:0].sum() for t in (means2d, conics, opacities, colors, depths))
    color = torch.zeros(tiles, P, D, device=device, dtype=dtype) + anchor
    depth = torch.zeros(tiles, P, device=device, dtype=dtype) + anchor
    T = torch.ones(tiles, P, device=device, dtype=dtype) + anchor
    done = torch.zeros(tiles, P, device=device, dtype=torch.bool)  # pixels that stopped compositing
    active = (counts > 0).nonzero().flatten()
    start = 0
    while active.numel() > 0:
        pos = bins.offsets[active][:, None] + start + torch.arange(chunk, device=device)[None]  # [A, C]
        valid = (start + torch.arange(chunk, device=device))[None] < counts[active][:, None]
        ids = bins.gaussian_ids[pos.clamp_max(bins.gaussian_ids.numel() - 1)]
        ids = torch.where(valid, ids, torch.zeros_like(ids))
        dx = pix_x[active][:, None, :] - means2d[ids, 0][:, :, None]  # [A, C, P]
        dy = pix_y[active][:, None, :] - means2d[ids, 1][:, :, None]
        con = conics[ids]
        power = -0.5 * (con[..., 0, None] * dx * dx + con[..., 2, None] * dy * dy) - con[..., 1, None] * dx * dy
        # alpha >= 1/255 needs power >= -ln(255) = -5.55: the lower clamp only avoids slow denormal exps.
        alpha = (opacities[ids][:, :, None] * torch.exp(power.clamp(-10.0, 0.0))).clamp_max(ALPHA_MAX)
        alpha = torch.where(valid[:, :, None] & (alpha >= ALPHA_MIN), alpha, torch.zeros_like(alpha))
        T_in = T[active][:, None, :]
        T_after = T_in * torch.cumprod(1.0 - alpha, dim=1)
        # Early termination: a pixel stops before the Gaussian that would take T below T_MIN. T only
        # decreases along the list, so `live` is a prefix and the unmasked cumprod is exact on it.
        live = (T_after >= T_MIN) & ~done[active][:, None, :]
        weights = torch.where(live, alpha * torch.cat([T_in, T_after[:, :-1]], dim=1), torch.zeros_like(alpha))
        color = color.index_add(0, active, torch.einsum("acp,acd->apd", weights, colors[ids]))
        depth = depth.index_add(0, active, torch.einsum("acp,ac->ap", weights, depths[ids]))
        last = live.sum(dim=1, keepdim=True)  # number of live Gaussians per pixel in this chunk
        T_end = torch.cat([T_in, T_after], dim=1).gather(1, last).squeeze(1)
        T = T.index_copy(0, active, T_end)
        with torch.no_grad():
            done = done.index_copy(0, active, done[active] | (T_after < T_MIN).any(dim=1))
        start += chunk
        with torch.no_grad():
            still = (counts[active] > start) & ~done[active].all(dim=1)
        active = active[still]

    def to_image(t: torch.Tensor) -> torch.Tensor:
        t = t.reshape(bins.tiles_y, bins.tiles_x, TILE_SIZE, TILE_SIZE, *t.shape[2:])
        t = t.transpose(1, 2).reshape(bins.tiles_y * TILE_SIZE, bins.tiles_x * TILE_SIZE, *t.shape[4:])
        return t[:height, :width]

    return to_image(color), 1.0 - to_image(T), to_image(depth)


class TorchRasterizer:
    """Reference rasteriser in plain PyTorch (any device)."""

    name = "torch"

    def __init__(self, chunk: int = 32):
        self.chunk = chunk

    def render(self, gaussians: GaussianSet, camera: Cameras, settings: RenderSettings | None = None) -> RenderOutput:
        """Render one view. camera: a single view (len 1)."""
        return rasterize(gaussians, camera, settings, partial(composite_tiles, chunk=self.chunk))
