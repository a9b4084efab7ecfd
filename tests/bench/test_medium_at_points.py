"""benchmarks/medium_at_points.py: the medium fitted at scene points recovers the one that made their colours."""

from __future__ import annotations

import torch


def test_the_fit_recovers_a_layered_medium_from_point_colours(benchmark_script):
    """200 points seen from 10 distances each (20-200 m, cameras 0-30 m over their mean) through β 0.01/m thinning
    with a 40 m scale height under airlight (0.8, 0.85, 0.9); a tenth of the observations brightened as by streaks."""
    m = benchmark_script("medium_at_points")
    g = torch.Generator().manual_seed(0)
    points, views = 200, 10
    point = torch.arange(points).repeat_interleave(views)
    distance = 20.0 + 180.0 * torch.rand(points * views, generator=g)
    height = 30.0 * torch.rand(points * views, generator=g) - 15.0
    rise = 0.2 * torch.rand(points * views, generator=g) - 0.1
    k = 1.0 / 40.0
    tau = 0.01 * distance * m.height_profile(torch.tensor(k), height, rise, distance)
    t = torch.exp(-tau)[:, None]
    albedo = torch.rand(points, 3, generator=g) * 0.6
    airlight = torch.tensor([0.8, 0.85, 0.9])
    colour = albedo[point] * t + airlight * (1 - t)
    streaks = torch.rand(points * views, generator=g) < 0.1
    colour[streaks] = (colour[streaks] + 0.4).clamp(max=1.0)
    obs = m.PointObservations(point, colour, distance, height, rise)
    fit = m.fit_medium(obs, beta_start=0.003)
    assert abs(fit.beta_per_m - 0.01) < 0.001
    assert abs(fit.height_rate / 100.0 - k) < 0.3 * k
    assert max(abs(a - b) for a, b in zip(fit.airlight, airlight.tolist(), strict=True)) < 0.03
    assert (fit.observations, fit.points) == (points * views, points)
