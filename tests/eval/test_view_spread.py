"""`view_spread`: sparse streaks spread a point's photos above their median, dense rain and clear weather evenly."""

import math

import pytest
import torch

from metegs.cameras import Cameras
from metegs.eval.view_spread import (
    EVEN_SPREAD_RATIO,
    SPARSE_STREAKS_RATIO,
    lifted_points,
    quantile_from_spread,
    view_spread,
)

WIDTH, HEIGHT, FOCAL, PLANE_Z = 64, 48, 60.0, 5.0


def wall_views(n: int = 12) -> tuple[Cameras, list[torch.Tensor], list[torch.Tensor]]:
    """``n`` cameras side by side looking down +z at a textured wall at z = 5 -> (cameras, clear photos [H, W, 3],
    z-depths [H, W])."""
    c2w = torch.eye(4).repeat(n, 1, 1)
    c2w[:, 0, 3] = torch.linspace(-0.6, 0.6, n)
    cameras = Cameras.create(c2w, FOCAL, FOCAL, WIDTH / 2, HEIGHT / 2, WIDTH, HEIGHT)
    rows, cols = torch.meshgrid(torch.arange(HEIGHT), torch.arange(WIDTH), indexing="ij")
    photos = []
    for v in range(n):
        x = float(c2w[v, 0, 3]) + (cols + 0.5 - WIDTH / 2) / FOCAL * PLANE_Z
        y = (rows + 0.5 - HEIGHT / 2) / FOCAL * PLANE_Z
        grey = 0.4 + 0.2 * torch.sin(3.0 * x) * torch.cos(2.0 * y)
        photos.append(grey[..., None].expand(HEIGHT, WIDTH, 3).float())
    return cameras, photos, [torch.full((HEIGHT, WIDTH), PLANE_Z) for _ in range(n)]


def test_lifted_points_lie_on_the_surface_the_depths_show():
    cameras, _, depths = wall_views()
    depths[1][:, : WIDTH // 2] = float("nan")  # unknown depth lifts nothing
    points = lifted_points(cameras, depths, every_view=1, stride_px=8)
    assert len(points) == (6 * 8) * 11 + 6 * 4
    assert torch.allclose(points[:, 2], torch.full((len(points),), PLANE_Z))
    # back in the view they were lifted from, at the centres of the sampled pixels
    u, v, z = cameras[0].project(points[:48])[0].unbind(-1)
    assert torch.allclose(z, torch.full_like(z, PLANE_Z))
    assert torch.allclose(torch.remainder(u - 4.5, 8.0), torch.zeros_like(u), atol=1e-3)
    assert torch.allclose(torch.remainder(v - 4.5, 8.0), torch.zeros_like(v), atol=1e-3)


def test_sparse_streaks_spread_above_the_median_and_dense_rain_evenly():
    cameras, clear, depths = wall_views()
    g = torch.Generator().manual_seed(0)
    noisy = [p + 0.01 * torch.randn(p.shape, generator=g) for p in clear]
    # streaks over 15 % of each photo: most views of a point see it clear
    sparse = [p + 0.4 * (torch.rand(p.shape[:2], generator=g) < 0.15)[..., None] for p in noisy]
    # streak layers over every pixel, of a random strength per view and pixel
    dense = [p + 0.3 * torch.rand(p.shape[:2], generator=g)[..., None] for p in noisy]
    spreads = {
        name: view_spread(cameras, photos, depths)
        for name, photos in (("clear", noisy), ("sparse", sparse), ("dense", dense))
    }
    assert all(s.points > 150 for s in spreads.values())  # 4 views lift 48 points each
    assert spreads["sparse"].ratio > 2 * SPARSE_STREAKS_RATIO
    assert spreads["dense"].ratio < SPARSE_STREAKS_RATIO and spreads["clear"].ratio < SPARSE_STREAKS_RATIO
    assert spreads["dense"].below > 5 * spreads["clear"].below  # dense rain lifts the median too
    assert spreads["sparse"].below == pytest.approx(spreads["clear"].below, rel=0.5)


def test_views_that_a_nearer_surface_hides_do_not_count():
    cameras, clear, depths = wall_views()
    hidden = [d.clone() for d in depths]
    for d in hidden[1:]:
        d[:] = PLANE_Z / 2  # every view but the first sees something nearer
    assert view_spread(cameras, clear, hidden, every_view=12, min_views=2).points == 0
    assert view_spread(cameras, clear, depths, every_view=12, min_views=2).points > 0
    empty = view_spread(cameras, clear, depths, min_views=13)  # more views than there are
    assert empty.points == 0 and math.isnan(empty.below)


def test_the_quantile_moves_from_the_low_one_to_the_median_as_the_spread_grows_one_sided():
    assert quantile_from_spread(0.7, 0.1) == quantile_from_spread(EVEN_SPREAD_RATIO, 0.1) == 0.1
    assert quantile_from_spread(SPARSE_STREAKS_RATIO, 0.1) == quantile_from_spread(25.0, 0.25) == 0.5
    middle = (EVEN_SPREAD_RATIO + SPARSE_STREAKS_RATIO) / 2
    assert quantile_from_spread(middle, 0.1) == pytest.approx(0.3) and quantile_from_spread(middle, 0.25) == 0.38
    ratios = torch.linspace(0.5, 3.0, 26).tolist()
    quantiles = [quantile_from_spread(r, 0.1) for r in ratios]
    assert quantiles == sorted(quantiles)  # never lower for a more one-sided spread
