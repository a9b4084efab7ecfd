"""The medium fitted at scene points recovers the one that made their colours."""

from __future__ import annotations

import torch

from metegs.weather.fog_analytic import height_profile
from metegs.weather.medium_fit import PointObservations, fit_medium, fit_uniform_medium


def test_the_fit_recovers_a_layered_medium_from_point_colours():
    """200 points seen from 10 distances each (20-200 m, cameras 0-30 m over their mean) through β 0.01/m thinning
    with a 40 m scale height under airlight (0.8, 0.85, 0.9); a tenth of the observations brightened as by streaks."""
    g = torch.Generator().manual_seed(0)
    points, views = 200, 10
    point = torch.arange(points).repeat_interleave(views)
    distance = 20.0 + 180.0 * torch.rand(points * views, generator=g)
    height = 30.0 * torch.rand(points * views, generator=g) - 15.0
    rise = 0.2 * torch.rand(points * views, generator=g) - 0.1
    k = 1.0 / 40.0
    tau = 0.01 * distance * height_profile(torch.tensor(k), height, rise, distance)
    t = torch.exp(-tau)[:, None]
    albedo = torch.rand(points, 3, generator=g) * 0.6
    airlight = torch.tensor([0.8, 0.85, 0.9])
    colour = albedo[point] * t + airlight * (1 - t)
    streaks = torch.rand(points * views, generator=g) < 0.1
    colour[streaks] = (colour[streaks] + 0.4).clamp(max=1.0)
    obs = PointObservations(point, colour, distance, height, rise)
    fit = fit_medium(obs, beta_start=0.003)
    assert abs(fit.beta_per_m - 0.01) < 0.001
    assert abs(fit.height_rate / 100.0 - k) < 0.3 * k
    assert max(abs(a - b) for a, b in zip(fit.airlight, airlight.tolist(), strict=True)) < 0.03
    assert (fit.observations, fit.points) == (points * views, points)


def uniform_observations(beta: float, seed: int = 0) -> tuple[PointObservations, torch.Tensor]:
    """300 points seen from 8 distances each (20-200 m) through a uniform medium of extinction ``beta`` under
    airlight (0.8, 0.85, 0.9), a tenth of the observations brightened as by streaks -> (observations, airlight)."""
    g = torch.Generator().manual_seed(seed)
    points, views = 300, 8
    point = torch.arange(points).repeat_interleave(views)
    distance = 20.0 + 180.0 * torch.rand(points * views, generator=g)
    t = torch.exp(-beta * distance)[:, None]
    airlight = torch.tensor([0.8, 0.85, 0.9])
    colour = (torch.rand(points, 3, generator=g) * 0.7)[point] * t + airlight * (1 - t)
    streaks = torch.rand(points * views, generator=g) < 0.1
    colour[streaks] = (colour[streaks] + 0.4).clamp(max=1.0)
    zeros = torch.zeros(points * views)
    return PointObservations(point, colour, distance, zeros, zeros), airlight


def test_the_closed_form_fit_recovers_a_uniform_medium_and_reads_clear_air_as_none():
    """`fit_uniform_medium` (no gradient steps) finds β within 5 % and A within 0.03; through clear air it finds
    β at the bottom of its range, not the clean colours' spread read as fog."""
    obs, airlight = uniform_observations(0.012)
    fit = fit_uniform_medium(obs)
    assert abs(fit.beta_per_m - 0.012) < 0.05 * 0.012
    assert max(abs(a - b) for a, b in zip(fit.airlight, airlight.tolist(), strict=True)) < 0.03
    assert (fit.observations, fit.points, fit.height_rate) == (len(obs), 300, 0.0)
    clear, _ = uniform_observations(0.0, seed=1)
    assert fit_uniform_medium(clear).beta_per_m < 5e-4


def test_points_seen_from_one_distance_are_left_out_of_the_measure():
    """Far points seen from about one distance (250-260 m) through thinner air, as hills where the fog thins with
    height, say nothing of β but through the airlight's model and pull a uniform fit low; `spread` keeps only the
    points seen from distances at least 1.5 times apart, whose β is the medium's."""
    near, airlight = uniform_observations(0.012)
    g = torch.Generator().manual_seed(2)
    points, views = 300, 8
    point = torch.arange(points).repeat_interleave(views) + int(near.point.max()) + 1
    distance = 250.0 + 10.0 * torch.rand(points * views, generator=g)
    t = torch.exp(-0.002 * distance)[:, None]
    colour = (torch.rand(points, 3, generator=g) * 0.7).repeat_interleave(views, 0) * t + airlight * (1 - t)
    zeros = torch.zeros(points * views)
    obs = PointObservations(
        torch.cat([near.point, point]),
        torch.cat([near.colour, colour]),
        torch.cat([near.distance_m, distance]),
        torch.cat([near.camera_height_m, zeros]),
        torch.cat([near.rise, zeros]),
    )
    assert fit_uniform_medium(obs).beta_per_m < 0.5 * 0.012  # the far points' thin air read as the medium's
    kept = obs.spread(1.5)
    assert (len(kept), len(torch.unique(kept.point))) == (len(near), 300)
    assert abs(fit_uniform_medium(kept).beta_per_m - 0.012) < 0.05 * 0.012
