"""The medium fitted at scene points recovers the one that made their colours."""

from __future__ import annotations

import torch

from metegs.cameras import Cameras
from metegs.engine.metegs_trainer import MIN_AIRLIGHT_OUTSHINES, MIN_MEDIUM_EXPLAINED, MIN_VEIL_Z
from metegs.weather.fog_analytic import height_profile
from metegs.weather.medium_fit import (
    PointObservations,
    airlight_under_haze,
    fit_medium,
    fit_uniform_medium,
    point_observations,
    unoccluded,
    veil_evidence,
)

LAYERED_K = 1.0 / 40.0
"""Height rate (1/m) of the layered test medium: a 40 m scale height."""


def layered_observations(seed: int, streaked: float) -> tuple[PointObservations, torch.Tensor]:
    """200 points seen from 10 distances each (20-200 m, cameras 0-30 m over their mean) through β 0.01/m thinning
    with a scale height of 1/`LAYERED_K` under airlight (0.8, 0.85, 0.9), a share ``streaked`` of the observations
    brightened as by streaks -> (observations, airlight)."""
    g = torch.Generator().manual_seed(seed)
    points, views = 200, 10
    point = torch.arange(points).repeat_interleave(views)
    distance = 20.0 + 180.0 * torch.rand(points * views, generator=g)
    height = 30.0 * torch.rand(points * views, generator=g) - 15.0
    rise = 0.2 * torch.rand(points * views, generator=g) - 0.1
    tau = 0.01 * distance * height_profile(torch.tensor(LAYERED_K), height, rise, distance)
    t = torch.exp(-tau)[:, None]
    albedo = torch.rand(points, 3, generator=g) * 0.6
    airlight = torch.tensor([0.8, 0.85, 0.9])
    colour = albedo[point] * t + airlight * (1 - t)
    streaks = torch.rand(points * views, generator=g) < streaked
    colour[streaks] = (colour[streaks] + 0.4).clamp(max=1.0)
    return PointObservations(point, colour, distance, height, rise), airlight


def test_the_fit_recovers_a_layered_medium_from_point_colours():
    """`layered_observations`, a tenth of them streaked: β, the scale height and the airlight."""
    obs, airlight = layered_observations(0, streaked=0.1)
    fit = fit_medium(obs, beta_start=0.003)
    assert abs(fit.beta_per_m - 0.01) < 0.001
    assert abs(fit.height_rate / 100.0 - LAYERED_K) < 0.3 * LAYERED_K
    assert max(abs(a - b) for a, b in zip(fit.airlight, airlight.tolist(), strict=True)) < 0.03
    assert (fit.observations, fit.points) == (2000, 200)


def test_the_layered_fit_holds_a_given_airlight():
    """`layered_observations` under their airlight given: `fit_medium` keeps it and finds β and the scale height; under
    an airlight 0.05 too bright the same colours need a thinner medium."""
    obs, airlight = layered_observations(1, streaked=0.0)
    fit = fit_medium(obs, beta_start=0.005, airlight=airlight)
    assert fit.airlight == tuple(float(a) for a in airlight)
    assert abs(fit.beta_per_m - 0.01) < 0.05 * 0.01 and abs(fit.height_rate / 100.0 - LAYERED_K) < 0.2 * LAYERED_K
    assert fit_medium(obs, beta_start=0.005, airlight=airlight + 0.05).beta_per_m < 0.97 * fit.beta_per_m


def test_the_fit_runs_where_gradients_are_off():
    """A run loaded for rendering under ``torch.no_grad()`` fits its medium as training does."""
    obs, airlight = layered_observations(1, streaked=0.0)
    with torch.no_grad():
        fit = fit_medium(obs, beta_start=0.005, airlight=airlight, steps=50)
    assert fit == fit_medium(obs, beta_start=0.005, airlight=airlight, steps=50)


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
    β at the bottom of its range, not the clean colours' spread read as fog, and a medium that explains little there."""
    obs, airlight = uniform_observations(0.012)
    fit = fit_uniform_medium(obs)
    assert abs(fit.beta_per_m - 0.012) < 0.05 * 0.012
    assert max(abs(a - b) for a, b in zip(fit.airlight, airlight.tolist(), strict=True)) < 0.03
    assert (fit.observations, fit.points, fit.height_rate) == (len(obs), 300, 0.0)
    clear, _ = uniform_observations(0.0, seed=1)
    clear_fit = fit_uniform_medium(clear)
    assert clear_fit.beta_per_m < 5e-4
    assert clear_fit.explained < 0.05 < 0.3 < fit.explained  # a medium explains the colours only where there is one


def test_a_given_airlight_is_held_and_beta_found_under_it():
    """With the photos' airlight given, `fit_uniform_medium` keeps it and finds β within 3 %; under an airlight
    0.05 too bright in every channel the same colours need a thinner medium (the trade the held airlight settles)."""
    obs, airlight = uniform_observations(0.012)
    fit = fit_uniform_medium(obs, airlight=airlight)
    assert fit.airlight == tuple(float(a) for a in airlight)
    assert abs(fit.beta_per_m - 0.012) < 0.03 * 0.012
    assert fit_uniform_medium(obs, airlight=airlight + 0.05).beta_per_m < 0.97 * fit.beta_per_m


def astuple_rest(obs: PointObservations) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The geometry of ``obs``: (distance_m, camera_height_m, rise)."""
    return obs.distance_m, obs.camera_height_m, obs.rise


def test_the_veil_of_a_given_beta_is_told_from_clear_air():
    """`veil_evidence` at a rain's veil of 2.5e-3/m: photos through that veil, or one twice as thick, explain it many
    standard errors better than clear air under a bright airlight; clear photos, or photos whose colours vary from
    view to view without regard to distance, do not reach `MIN_VEIL_Z`; colours that far views mix towards the
    scene's middle grey do, but under an airlight that outshines too few of them."""
    for beta in (0.0025, 0.005):
        veiled, _ = uniform_observations(beta)
        evidence = veil_evidence(veiled, 0.0025)
        assert evidence.z > 2 * MIN_VEIL_Z and evidence.explained > 0.05
        assert evidence.brighter > MIN_AIRLIGHT_OUTSHINES
    clear, _ = uniform_observations(0.0, seed=1)
    evidence = veil_evidence(clear, 0.0025)
    assert evidence.z < MIN_VEIL_Z and evidence.explained < 0.0
    g = torch.Generator().manual_seed(3)
    noisy = PointObservations(
        clear.point,
        (clear.colour + 0.03 * torch.randn(clear.colour.shape, generator=g)).clamp(0.0, 1.0),
        *astuple_rest(clear),
    )
    assert veil_evidence(noisy, 0.0025).z < MIN_VEIL_Z
    t = torch.exp(-0.0025 * clear.distance_m)[:, None]
    mixed = clear.colour * t + clear.colour.mean(0) * (1 - t)
    evidence = veil_evidence(PointObservations(clear.point, mixed, *astuple_rest(clear)), 0.0025)
    assert evidence.z > MIN_VEIL_Z and evidence.brighter < MIN_AIRLIGHT_OUTSHINES


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


def test_points_behind_a_nearer_wall_of_points_are_hidden():
    """400 far points (depth 10) over an 80×60 frame behind a wall of 400 points (depth 2) over its left half: the far
    points more than two cells left of the wall's edge are hidden, those two cells right of it and the wall are seen."""
    g = torch.Generator().manual_seed(0)
    far_x, far_y = 80.0 * torch.rand(400, generator=g), 60.0 * torch.rand(400, generator=g)
    wall_x, wall_y = 40.0 * torch.rand(400, generator=g), 60.0 * torch.rand(400, generator=g)
    z = torch.cat([torch.full((400,), 10.0), torch.full((400,), 2.0)])
    seen = unoccluded(torch.cat([far_x, wall_x]), torch.cat([far_y, wall_y]), z, 80, 60)
    far_seen, margin = seen[:400], 2 * (80 * 60 / 800) ** 0.5
    assert not far_seen[far_x < 40 - margin].any()
    assert far_seen[far_x > 40 + margin].all()
    assert seen[400:].all()


def test_a_view_in_which_a_nearer_patch_hides_a_point_does_not_observe_it():
    """A far plane of points (z 50) and a near patch (z 10) in front of its centre, seen by a camera at the origin and
    one 8 units to the side: the far plane's centre is observed by the second camera alone, the patch by both."""
    ys, xs = torch.meshgrid(torch.arange(-45.0, 46.0, 2.0), torch.arange(-60.0, 61.0, 2.0), indexing="ij")
    plane = torch.stack([xs.flatten(), ys.flatten(), torch.full((xs.numel(),), 50.0)], dim=1)
    ys, xs = torch.meshgrid(torch.arange(-3.0, 3.01, 0.25), torch.arange(-3.0, 3.01, 0.25), indexing="ij")
    patch = torch.stack([xs.flatten(), ys.flatten(), torch.full((xs.numel(),), 10.0)], dim=1)
    points = torch.cat([plane, patch])
    poses = torch.eye(4).repeat(2, 1, 1)
    poses[1, 0, 3] = 8.0
    cameras = Cameras.create(poses, 40.0, 40.0, 40.0, 30.0, 80, 60)
    obs = point_observations(cameras, [torch.zeros(60, 80, 3)] * 2, points, torch.tensor([0.0, -1.0, 0.0]), 1.0)
    centre = int(((plane - torch.tensor([0.0, 0.0, 50.0])).norm(dim=1)).argmin())
    seen_from = obs.distance_m[obs.point == centre]
    assert torch.allclose(seen_from, (plane[centre] - poses[1, :3, 3]).norm()[None])
    patch_centre = len(plane) + int(patch.norm(dim=1).argmin())
    assert (obs.point == patch_centre).sum() == 2


def haze_over_a_white_wall(seed: int = 0) -> tuple[PointObservations, torch.Tensor]:
    """300 points seen from 8 distances each (20-200 m, β 0.02/m) under airlight (0.72, 0.70, 0.62), a sixth of them
    white (0.95), brighter than it, as the fox's wallpaper is -> (observations, airlight)."""
    g = torch.Generator().manual_seed(seed)
    points, views = 300, 8
    point = torch.arange(points).repeat_interleave(views)
    distance = 20.0 + 180.0 * torch.rand(points * views, generator=g)
    t = torch.exp(-0.02 * distance)[:, None]
    albedo = torch.rand(points, 3, generator=g) * 0.6
    albedo[::6] = 0.95
    airlight = torch.tensor([0.72, 0.70, 0.62])
    zeros = torch.zeros(points * views)
    return PointObservations(point, albedo[point] * t + airlight * (1 - t), distance, zeros, zeros), airlight


def test_the_points_lower_a_brightest_haze_that_a_white_surface_lifts_over_the_airlight():
    """`airlight_under_haze`: where a white surface lifts the brightest haze over the airlight, the airlight that the
    points fit along with β replaces it (within 0.02), and β under it is the medium's, where under the haze it reads a
    fifth too thin; a haze darker than that fit is kept channel by channel, as the fit only trades the airlight against
    β above it; without observations, or through clear air, the haze is all there is."""
    obs, airlight = haze_over_a_white_wall()
    lifted = torch.tensor([0.79, 0.78, 0.74])
    lowered = airlight_under_haze(lifted, obs, MIN_MEDIUM_EXPLAINED)
    assert torch.allclose(lowered, airlight, atol=0.02)
    assert abs(fit_uniform_medium(obs, airlight=lowered).beta_per_m - 0.02) < 0.05 * 0.02
    assert fit_uniform_medium(obs, airlight=lifted).beta_per_m < 0.8 * 0.02
    darker = torch.tensor([0.70, 0.72, 0.60])
    kept = airlight_under_haze(darker, obs, MIN_MEDIUM_EXPLAINED)
    assert kept[0] == darker[0] and kept[2] == darker[2] and abs(float(kept[1]) - 0.70) < 0.02
    assert airlight_under_haze(lifted, None, MIN_MEDIUM_EXPLAINED) is lifted
    clear, _ = uniform_observations(0.0, seed=1)  # no medium: its airlight says nothing
    assert airlight_under_haze(lifted, clear, MIN_MEDIUM_EXPLAINED) is lifted
