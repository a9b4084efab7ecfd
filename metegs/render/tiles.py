"""Tile binning: which Gaussians touch which 16x16 tile, sorted front to back (vectorised, no Python loops)."""

from __future__ import annotations

from dataclasses import dataclass

import torch

TILE_SIZE = 16


@dataclass
class TileBins:
    """Per-tile, depth-sorted lists of Gaussian ids stored as one flat array with offsets (CSR)."""

    tiles_x: int
    tiles_y: int
    gaussian_ids: torch.Tensor
    """[M] int64 Gaussian id of every (tile, Gaussian) intersection, grouped by tile, near to far."""
    offsets: torch.Tensor
    """[tiles_x * tiles_y + 1] int64 start of each tile's list in ``gaussian_ids``."""

    @property
    def counts(self) -> torch.Tensor:
        """[tiles] int64 number of Gaussians per tile."""
        return self.offsets[1:] - self.offsets[:-1]

    @property
    def num_intersections(self) -> int:
        return int(self.gaussian_ids.shape[0])


def bin_gaussians(
    means2d: torch.Tensor, extents: torch.Tensor, depths: torch.Tensor, width: int, height: int, tile: int = TILE_SIZE
) -> TileBins:
    """Bin screen-space Gaussians into tiles.

    means2d [N, 2], extents [N, 2] half-sizes in px (0 = culled), depths [N] -> TileBins. One int64 sort of
    ``tile_id * N + depth_rank`` orders every tile's list front to back.
    """
    device = means2d.device
    tiles_x = (width + tile - 1) // tile
    tiles_y = (height + tile - 1) // tile
    n = means2d.shape[0]
    with torch.no_grad():
        rx, ry = extents[:, 0].to(means2d.dtype), extents[:, 1].to(means2d.dtype)
        x0 = ((means2d[:, 0] - rx) / tile).floor().clamp(0, tiles_x).long()
        x1 = ((means2d[:, 0] + rx) / tile).floor().add(1).clamp(0, tiles_x).long()
        y0 = ((means2d[:, 1] - ry) / tile).floor().clamp(0, tiles_y).long()
        y1 = ((means2d[:, 1] + ry) / tile).floor().add(1).clamp(0, tiles_y).long()
        w = (x1 - x0).clamp_min(0)
        h = (y1 - y0).clamp_min(0)
        counts = torch.where(extents.amin(dim=1) > 0, w * h, torch.zeros_like(w))
        total = int(counts.sum())
        if total == 0:
            return TileBins(
                tiles_x,
                tiles_y,
                torch.zeros(0, dtype=torch.long, device=device),
                torch.zeros(tiles_x * tiles_y + 1, dtype=torch.long, device=device),
            )
        gid = torch.repeat_interleave(torch.arange(n, device=device), counts)
        start = torch.cumsum(counts, 0) - counts
        local = torch.arange(total, device=device) - start[gid]
        tx = x0[gid] + local % w[gid]
        ty = y0[gid] + local // w[gid]
        tile_id = ty * tiles_x + tx
        depth_rank = torch.empty(n, dtype=torch.long, device=device)
        depth_rank[torch.argsort(depths, stable=True)] = torch.arange(n, device=device)
        key = tile_id * n + depth_rank[gid]
        order = torch.argsort(key)
        per_tile = torch.bincount(tile_id, minlength=tiles_x * tiles_y)
        offsets = torch.zeros(tiles_x * tiles_y + 1, dtype=torch.long, device=device)
        offsets[1:] = torch.cumsum(per_tile, 0)
        return TileBins(tiles_x, tiles_y, gid[order], offsets)
