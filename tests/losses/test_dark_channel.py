"""The dark-channel prior: the channel against a plain loop, the pinball loss against the quantile, dehazing against
the fog it inverts, β recovered from foggy photos alone, and a photo's veil against the transmission that made it."""

from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from metegs.eval.veil import dark_channel, patch_size, photo_veil, sample_stride
from metegs.losses.dark_channel import DarkChannelPriorConfig, dark_channel_loss, pinball
from metegs.meteo import CameraSpec, theta_from_values
from metegs.render.base import RenderOutput, RenderSettings
from metegs.weather import WeatherScene
from metegs.weather.fog_analytic import FogAnalytic, FogAnalyticConfig
from tests.weather.test_weather_physics import F, H, W, cameras

AIRLIGHT = (0.8, 0.82, 0.86)


def test_dark_channel_is_the_min_over_channels_and_patch():
    image = torch.rand(13, 17, 3, generator=torch.Generator().manual_seed(0))
    fast = dark_channel(image, 5)
    for y in range(13):
        for x in range(17):
            window = image[max(y - 2, 0) : y + 3, max(x - 2, 0) : x + 3]
            assert float(fast[y, x]) == float(window.min())


def test_patch_follows_the_image_size_and_stays_odd():
    assert patch_size(400, 600) == 15 and patch_size(250, 250) == 7 and patch_size(20, 30) == 3
    assert patch_size(100, 100, patch_px=8) == 9
    assert (sample_stride(250, 250), sample_stride(500, 500), sample_stride(660, 1000)) == (1, 2, 3)


def test_pinball_is_minimised_at_the_quantile():
    values = torch.randn(2001, generator=torch.Generator().manual_seed(1))
    shifts = torch.linspace(-2, 2, 801)
    losses = torch.stack([pinball(values - s, 0.1) for s in shifts])
    assert float(shifts[losses.argmin()]) == pytest.approx(float(values.quantile(0.1)), abs=0.01)


def fog(visibility_m: float, **options) -> FogAnalytic:
    theta = theta_from_values(
        0.0, visibility_m=visibility_m, fog_kind="fog", camera=CameraSpec.from_intrinsics(F, W, H)
    )
    scene = WeatherScene(cameras(), torch.tensor([0.0, -1.0, 0.0]), 1.0, None, seed=3)
    return FogAnalytic(FogAnalyticConfig(airlight=AIRLIGHT, **options), theta, scene)


def scene_view(seed: int = 0) -> tuple[torch.Tensor, RenderOutput]:
    """A clear view as clear views are: texture whose every 7 px patch holds a near-black pixel in some channel, at
    depths from 20 to 150 m, opaque -> (colour [H, W, 3], its render)."""
    g = torch.Generator().manual_seed(seed)
    colour = 0.2 + 0.8 * torch.rand(H, W, 3, generator=g)
    colour[::5, ::5, 1] = 0.01 * torch.rand(colour[::5, ::5, 1].shape, generator=g)
    depth = torch.linspace(20, 150, W).expand(H, W).clone()
    out = RenderOutput(colour, torch.ones(H, W), depth, torch.zeros(0), torch.zeros(0, 2), 0, W, H)
    return colour, out


HEAD = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "scenes" / "ethiopianhead-llff" / "images_8"


def veiled(colour: torch.Tensor, transmission: float, airlight: torch.Tensor) -> torch.Tensor:
    """``colour`` [H, W, 3] seen through a medium of one ``transmission``: J·t + A·(1 − t)."""
    return colour * transmission + airlight * (1.0 - transmission)


@pytest.mark.parametrize("transmission", [1.0, 0.95, 0.8, 0.5, 0.2])
def test_a_photos_veil_is_the_contrast_its_medium_takes(transmission):
    """Under one transmission t the darkest patches read 1 − t (`veil_fraction`), to within their own dark colour
    (0.01·t / A); a larger photo of the same view reads the same (it is sampled, its patch scaled)."""
    colour, _ = scene_view()
    airlight = torch.tensor(AIRLIGHT)
    photo = veiled(colour, transmission, airlight)
    assert photo_veil(photo, airlight) == pytest.approx(1.0 - transmission, abs=0.015)
    large = torch.nn.functional.interpolate(photo.permute(2, 0, 1)[None], scale_factor=4, mode="nearest")
    assert photo_veil(large[0].permute(1, 2, 0), airlight) == pytest.approx(1.0 - transmission, abs=0.015)
    bordered = photo.clone()
    bordered[: H // 4] = 0.0  # a black border (an undistorted photo's) over a quarter of the view is no surface
    bordered[:, -3:] = 0.0
    assert photo_veil(bordered, airlight) == pytest.approx(1.0 - transmission, abs=0.015)
    assert photo_veil(torch.zeros_like(photo), airlight) == 0.0


@pytest.mark.data
def test_a_real_capture_shows_no_veil_until_a_medium_lifts_it():
    """The Ethiopian head's clear photos show under half the contrast a person notices (`VISIBLE_CONTRAST_LOSS`);
    through a medium that takes 10 % of it they read 10 %."""
    from metegs.weather.airlight import estimate_airlight
    from metegs.weather.medium import VISIBLE_CONTRAST_LOSS

    files = sorted(HEAD.glob("*.jpg"))[::16] if HEAD.is_dir() else []
    if not files:
        pytest.skip(f"real LLFF scene not found at {HEAD} (needs ../shared beside the repository)")
    photos = [torch.from_numpy(np.asarray(Image.open(p).convert("RGB"), dtype=np.float32) / 255) for p in files]
    airlight = estimate_airlight(photos)
    for path, photo in zip(files, photos):
        assert photo_veil(photo, airlight) < 0.5 * VISIBLE_CONTRAST_LOSS, path.name
        assert photo_veil(veiled(photo, 0.9, airlight), airlight) == pytest.approx(0.1, abs=0.03), path.name


def test_dehazing_inverts_the_fog_where_the_surface_is_seen():
    colour, out = scene_view()
    medium = fog(300.0)
    photo = medium.apply(colour, out, 0, RenderSettings()).detach()
    dehazed, valid = medium.dehaze(photo, out, 0, min_transmission=0.05)
    assert bool(valid.all())
    assert torch.allclose(dehazed, colour, atol=1e-4)
    out.alpha = torch.where(torch.arange(W) < W // 2, 1.0, 0.2).expand(H, W)  # the right half see-through
    assert torch.equal(medium.dehaze(photo, out, 0, 0.05)[1], out.alpha > 0.5)
    assert not bool(medium.dehaze(photo, out, 0, 0.99)[1].any())  # nothing is seen that clearly through the fog


@pytest.mark.parametrize("start_visibility_m", [600.0, 120.0])
def test_the_prior_finds_beta_from_foggy_photos_alone(start_visibility_m):
    """Fog at 250 m over clear views; a medium started at half or twice that β learns it from the photos."""
    truth = fog(250.0)
    medium = fog(start_visibility_m)
    views = [scene_view(seed) for seed in range(3)]
    photos = [truth.apply(c, out, 0, RenderSettings()).detach() for c, out in views]
    optimiser = torch.optim.Adam([medium.log_beta], lr=0.02)
    config = DarkChannelPriorConfig(quantile=0.1, patch_px=7)
    for step in range(300):
        _, out = views[step % 3]
        dehazed, valid = medium.dehaze(photos[step % 3], out, 0, config.min_transmission)
        loss = dark_channel_loss(dehazed, valid, config)
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
    assert medium.airlight_logit.grad is None  # the airlight is the photos' to fit
    assert torch.allclose(medium.beta_rgb.detach(), truth.beta_rgb, rtol=0.1)


def test_patches_scale_the_optical_depth_cell_by_cell_and_their_prior_pulls_them_to_one():
    medium = fog(300.0, patches=4)
    assert medium.patch_log_scale.shape == (1, 4, 4) and not medium.patchy
    _, out = scene_view()
    plain = medium.optical_distance(out.depth, out.alpha, 0)
    assert medium.learn_patches() and medium.patchy
    assert torch.equal(medium.optical_distance(out.depth, out.alpha, 0), plain)  # they start at 1
    with torch.no_grad():
        medium.patch_log_scale[0] = torch.log(torch.tensor(2.0)) * (torch.arange(4) >= 2).float()  # right half x2
    scaled = medium.optical_distance(out.depth, out.alpha, 0)
    ratio = scaled / plain
    assert torch.allclose(ratio[:, : W // 2 - 6], torch.ones(()), atol=1e-5)  # away from the bilinear seam
    assert torch.allclose(ratio[:, W // 2 + 6 :], torch.full((), 2.0), atol=1e-5)
    medium.use_record_prior = False
    assert float(medium.prior(0).detach()) == pytest.approx(0.01 * 0.5 * float(torch.log(torch.tensor(2.0))) ** 2)
    assert fog(300.0).prior(0) is None  # neither prior is on


def test_a_medium_whose_patches_never_learned_loads_into_any_grid():
    """Runs saved before patches were on by default (a 0-cell grid) reopen with the default grid, still uniform;
    learned patches keep their shape."""
    old = fog(300.0, patches=0).state_dict()
    medium = fog(300.0, patches=4)
    medium.load_state_dict(old)
    assert medium.patch_log_scale.shape == (1, 4, 4) and not medium.patchy
    learned = fog(300.0, patches=2)
    with torch.no_grad():
        learned.patch_log_scale += 0.5
    with pytest.raises(RuntimeError, match="patch_log_scale"):
        medium.load_state_dict(learned.state_dict())
