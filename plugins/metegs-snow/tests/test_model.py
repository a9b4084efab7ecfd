"""The `snow` weather model: inactive without snow, monotone in rate, tilted by the wind, coverage kept under a cap."""

import math

import pytest
import torch
from metegs.render.base import ALPHA_MIN
from metegs.render.projection import covariance_3d
from metegs.render.torch_backend import TorchRasterizer
from metegs.weather.base import WeatherModel
from metegs.weather.learnable import LearnableTransients
from snow_helpers import FAR_M, H, W, scene, theta

from metegs_snow.model import Snow, SnowConfig, flake_covariances, quat_wxyz_from_rotmat, scales_and_quats


def integrated_alpha(model: Snow, view: int = 0) -> float:
    """Σ over the view's Gaussians of their alpha integrated over the image, as the rasteriser draws them (px):
    (o − 1/255)·2π·sqrt(det(Σ₂ + εI)) with o the final (floored, clamped) opacity."""
    d = model.draw(view)
    o = torch.maximum(d["opacity"], torch.full_like(d["opacity"], model.config.min_opacity))
    o = (o + ALPHA_MIN).clamp(max=0.99) - ALPHA_MIN
    return float((o * d["footprint_px"])[d["keep"]].sum())


def test_zero_rate_is_inactive_and_draws_nothing():
    model = Snow(SnowConfig(), theta(0.0), scene())
    assert isinstance(model, WeatherModel) and model.transient and model.stage == "gaussians"
    assert not model.active and model.count == 0 and model.gaussians_for(0) is None


def test_only_reported_snow_gates_rain_records_off():
    model = Snow(SnowConfig(only_reported_snow=True), theta(2.0), scene())  # θ from values reports rain
    assert not model.active
    assert Snow(SnowConfig(), theta(2.0), scene()).active


def test_flakes_are_per_view_and_reproducible():
    model = Snow(SnowConfig(max_count=300), theta(1.0), scene(2))
    a, b, again = model.gaussians_for(0), model.gaussians_for(1), model.gaussians_for(0)
    assert len(a) > 50 and torch.equal(a.means, again.means)
    n = min(len(a), len(b))
    assert not torch.equal(a.means[:n], b.means[:n])
    other_seed = Snow(SnowConfig(max_count=300), theta(1.0), scene(2, seed=4)).gaussians_for(0)
    assert not torch.equal(a.means[: min(n, len(other_seed))], other_seed.means[: min(n, len(other_seed))])


def test_flakes_lie_in_the_frustum_and_are_near_white_oblate_gaussians():
    sky = torch.full((H, W, 3), 0.95)
    model = Snow(SnowConfig(max_count=500), theta(1.0, exposure_s=1e-5), scene(images=[sky]))
    g = model.gaussians_for(0)
    z = g.means[:, 2]
    assert float(z.min()) >= 0.5 - 1e-4 and float(z.max()) <= FAR_M + 1e-4
    rgb = g.sh[:, 0] * 0.28209479177387814 + 0.5
    assert torch.allclose(rgb, torch.full_like(rgb, 0.9 * 0.95), atol=1e-4)
    # with an instant exposure a flake is a flat disk: its thinnest axis is the world up, a·D/4 against D/4
    cov = covariance_3d(g.quats, g.scales).double()
    up = torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64)
    along_up = torch.einsum("i,nij,j->n", up, cov, up)
    widest = torch.linalg.eigvalsh(cov)[:, -1]
    assert torch.allclose(along_up / widest, torch.full_like(widest, 0.6**2), rtol=1e-3)


def test_covariances_roundtrip_through_scales_and_quaternions():
    gen = torch.Generator().manual_seed(1)
    d = torch.rand(64, generator=gen, dtype=torch.float64) * 0.02 + 0.002
    v = torch.randn(64, 3, generator=gen, dtype=torch.float64)
    up = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    _, sigma = flake_covariances(d, v, up, 0.3, 1 / 60)
    scales, quats = scales_and_quats(sigma)
    assert torch.allclose(covariance_3d(quats, scales), sigma, rtol=1e-6, atol=1e-14)
    q = torch.nn.functional.normalize(torch.randn(100, 4, generator=gen, dtype=torch.float64), dim=1)
    from metegs.cameras import quat_wxyz_to_rotmat

    back = quat_wxyz_from_rotmat(quat_wxyz_to_rotmat(q))
    assert torch.allclose(back * torch.sign(back[:, :1]), q * torch.sign(q[:, :1]), atol=1e-9)


def test_fall_direction_tilts_with_the_wind():
    up = torch.tensor([0.0, -1.0, 0.0])
    calm = Snow(SnowConfig(), theta(1.0), scene())
    assert torch.allclose(calm.fall_direction, -up, atol=1e-6)
    angles = []
    for wind in (1.0, 3.0, 6.0):
        model = Snow(SnowConfig(), theta(1.0, wind, 270.0), scene())  # from the west: drifts east
        angle = math.degrees(math.acos(float(-model.fall_direction @ up)))
        assert angle == pytest.approx(model.params.tilt_deg, abs=0.5)
        angles.append(angle)
        east = torch.linalg.cross(torch.tensor([0.0, 0.0, 1.0]), up)  # north = the viewing direction (+z)
        assert float(model.fall_direction @ east) > 0
    assert angles[0] > 5 and all(b > a for a, b in zip(angles, angles[1:]))
    # the flakes' blur streaks point along the fall direction
    model = Snow(SnowConfig(max_count=200), theta(1.0, 6.0, 270.0), scene())
    g = model.gaussians_for(0)
    cov = covariance_3d(g.quats, g.scales)
    axis = torch.linalg.eigh(cov.double())[1][:, :, -1].float()
    assert float((axis @ model.fall_direction).abs().min()) > 0.95


def test_count_cap_preserves_coverage():
    full = Snow(SnowConfig(max_count=None), theta(0.5), scene(2))
    views = range(12)
    capped = Snow(SnowConfig(max_count=400), theta(0.5), scene(len(views)))
    assert full.count > 10 * capped.count and capped.count == 400
    assert capped.subsample == pytest.approx(400 / full.params.expected_count)
    # uncapped, the Gaussians carry exactly the flakes' projected areas (px)
    physical = sum(float(full.draw(v)["area_px"].sum()) for v in (0, 1)) / 2
    assert sum(integrated_alpha(full, v) for v in (0, 1)) / 2 == pytest.approx(physical, rel=0.03)
    # capped, each kept flake carries the area of the 1/subsample flakes it stands for ...
    stands_for = sum(float(capped.draw(v)["area_px"].sum()) for v in views) / len(views) / capped.subsample
    assert sum(integrated_alpha(capped, v) for v in views) / len(views) == pytest.approx(stands_for, rel=0.03)
    # ... which is, on average, the physical coverage (heavy-tailed flake sizes: sampling noise of a few %)
    assert stands_for == pytest.approx(physical, rel=0.12)
    # and the kept flakes are more opaque in proportion
    assert float(capped.draw(0)["opacity"].median()) > 5 * float(full.draw(0)["opacity"].median())


def test_rendered_coverage_of_a_downward_view_is_the_projected_area_per_volume():
    """Looking straight down the flakes are seen face-on: the mean alpha is 1 − exp(−A·(far − near))."""
    views = 3
    for rate in (0.3, 1.5):
        model = Snow(SnowConfig(colour=(1.0, 1.0, 1.0), max_count=3000), theta(rate), scene(views, up=(0.0, 0.0, -1.0)))
        measured = (
            sum(
                float(TorchRasterizer().render(model.gaussians_for(v), model.scene.cameras[v]).alpha.mean())
                for v in range(views)
            )
            / views
        )
        p = model.params
        expected = 1.0 - math.exp(-p.area_density_per_m * (p.far_m - p.near_m))
        assert measured == pytest.approx(expected, rel=0.15), rate


def test_monotone_in_rate():
    rates = (0.1, 0.5, 1.0, 3.0, 6.0, 10.0)
    alphas = []
    for rate in rates:
        model = Snow(SnowConfig(colour=(1.0, 1.0, 1.0)), theta(rate), scene(2))
        out = [TorchRasterizer().render(model.gaussians_for(v), model.scene.cameras[v]).alpha.mean() for v in (0, 1)]
        alphas.append(float(sum(out)) / 2)
    assert all(b >= a * 0.97 for a, b in zip(alphas, alphas[1:])), alphas  # ≥ up to sampling noise
    assert alphas[-1] > 5 * alphas[0]


def test_learnable_wrapper_starts_at_the_physical_flakes():
    inner = Snow(SnowConfig(max_count=200), theta(1.0), scene(2))
    learn = LearnableTransients(inner, [0])
    base, start = inner.gaussians_for(0), learn.gaussians_for(0)
    assert torch.allclose(base.means, start.means) and torch.allclose(base.opacities, start.opacities, atol=1e-6)
    assert learn.prior(0).item() < 1e-12
