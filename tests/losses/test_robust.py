"""The trimmed photometric loss: streak pixels a view cannot explain are left out, the scene's fit is kept."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from metegs.losses.photometric import PhotometricLoss, PhotometricLossConfig
from metegs.losses.robust import (
    VISIBLE_STROKE_ENERGY,
    RobustMaskConfig,
    inlier_weights,
    stroke_energy,
    stroke_width_px,
    thin_strokes,
    without_bright_strokes,
)
from metegs.weather.independent import rain_view

HEAD = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "scenes" / "ethiopianhead-llff" / "images_8"


def _residual_with_streaks(h=64, w=96):
    g = torch.Generator().manual_seed(0)
    residual = torch.randn(h, w, 3, generator=g) * 0.01
    streaks = torch.zeros(h, w, dtype=torch.bool)
    for x in range(5, w, 12):  # thin vertical streaks: 8 % of the pixels
        streaks[10:50, x] = True
    residual[streaks] += 0.5
    return residual, streaks


def test_streaks_are_outliers_and_the_rest_is_kept():
    residual, streaks = _residual_with_streaks()
    w = inlier_weights(residual, RobustMaskConfig(enabled=True))
    assert w[streaks].max() == 0
    near = torch.nn.functional.max_pool2d(streaks.float()[None, None], 3, 1, 1)[0, 0].bool()  # dilated by 1 px
    assert w[~near].mean() > 0.99 and w.mean() > 0.7


def test_only_a_photo_s_thin_strokes_can_be_trimmed():
    """A highlight (a bright blob of the photo that the render lacks) is no streak: with the photo's thin strokes
    given, the streaks are trimmed and the blob stays in the fit."""
    residual, streaks = _residual_with_streaks()
    blob = torch.zeros_like(streaks)
    blob[20:32, 67:76] = True  # 12 x 9 px, between two streaks
    residual[blob] += 0.5
    photo = 0.3 + residual  # a flat grey scene under the streaks and the highlight; the render is its grey
    strokes = thin_strokes(photo, 5, 0.04)
    assert strokes[streaks].all() and not strokes[blob].any()
    config = RobustMaskConfig(enabled=True)
    assert inlier_weights(residual, config)[blob].max() == 0  # any outlier: the highlight goes too
    thin = inlier_weights(residual, config, strokes)
    assert thin[streaks].max() == 0 and thin[blob].min() == 1


def _line(h: int, w: int, x0: float, y0: float, degrees: float, length: int) -> torch.Tensor:
    """[h, w] bool: a 1-px line of ``length`` px from (x0, y0), ``degrees`` from the image's vertical."""
    line = torch.zeros(h, w, dtype=torch.bool)
    a = np.radians(degrees)
    for s in range(length):
        x, y = round(x0 + s * np.sin(a)), round(y0 + s * np.cos(a))
        if 0 <= x < w and 0 <= y < h:
            line[y, x] = True
    return line


def test_only_strokes_that_run_with_the_rain_can_be_trimmed():
    """Streaks fall one way in a photo (a layer may turn from it by 20°); a scene's bright thin edges across them
    (a highlight's rim, a window frame) are thin strokes too, but run another way, and stay in the fit."""
    h, w = 96, 128
    streaks = torch.zeros(h, w, dtype=torch.bool)
    for x in range(4, w, 10):
        streaks |= _line(h, w, x, 4, 0.0, 40)  # the rain: vertical
    turned = torch.zeros_like(streaks)
    for x in range(9, w, 20):
        turned |= _line(h, w, x, 50, 20.0, 30)  # another layer, 20° turned
    edges = _line(h, w, 20, 70, 90.0, 90) | _line(h, w, 30, 90, 70.0, 80)  # across the rain: 90° and 70°
    photo = torch.full((h, w, 3), 0.3)
    photo[streaks | turned | edges] = 0.8
    thin = thin_strokes(photo, 5, 0.04)
    inside = torch.zeros_like(streaks)
    inside[8:-8, 8:-8] = True  # away from the border, where the line filters see reflected lines
    assert thin[streaks & ~edges & inside].float().mean() > 0.95
    assert thin[turned & ~edges & ~streaks & inside].float().mean() > 0.9
    assert thin[edges & ~streaks & ~turned & inside].float().mean() < 0.1
    assert ((photo - 0.3).mean(-1) > 0.04)[edges].all()  # they are bright and thin: only their way tells them apart
    # a photo twice the reference side or more is read in blocks: 10x larger (strokes 10 px wide), the same answer
    large = photo.repeat_interleave(10, 0).repeat_interleave(10, 1)  # 960 x 1280 px: blocks of 2 x 2
    thin_large = thin_strokes(large, 21, 0.04)[5::10, 5::10]
    assert thin_large[streaks & ~edges & inside].float().mean() > 0.9
    assert thin_large[edges & ~streaks & ~turned & inside].float().mean() < 0.1


def test_darker_residuals_stay_unless_asked():
    residual, streaks = _residual_with_streaks()
    assert inlier_weights(-residual, RobustMaskConfig(enabled=True))[streaks].min() == 1
    assert inlier_weights(-residual, RobustMaskConfig(enabled=True, brighter_only=False))[streaks].max() == 0


def test_the_threshold_follows_the_fit():
    """A view fitted badly everywhere (early training) leaves little out."""
    residual, _ = _residual_with_streaks()
    noisy = residual + torch.randn(residual.shape, generator=torch.Generator().manual_seed(3)) * 0.3
    assert inlier_weights(noisy, RobustMaskConfig(enabled=True, dilate_px=0)).mean() > 0.95


def test_a_uniform_residual_is_all_inliers():
    w = inlier_weights(torch.full((32, 48, 3), 0.2), RobustMaskConfig(enabled=True))
    assert torch.equal(w, torch.ones(32, 48))


def test_weighted_loss_ignores_what_the_weights_leave_out():
    g = torch.Generator().manual_seed(1)
    pred = torch.rand(24, 32, 3, generator=g, requires_grad=True)
    target = torch.rand(24, 32, 3, generator=g)
    weights = torch.ones(24, 32)
    weights[:, :8] = 0
    loss = PhotometricLoss()
    changed = target.clone()
    changed[:, :2] = 0.0  # further than the 11-tap SSIM window reaches into the kept pixels
    assert torch.isclose(loss(pred, target, weights), loss(pred, changed, weights))
    loss(pred, target, weights).backward()
    assert pred.grad[:, :2].abs().max() == 0 and pred.grad[:, 8:].abs().max() > 0
    assert torch.isclose(loss(pred, target, torch.ones(24, 32)), loss(pred, target))


def test_a_closely_fitted_view_keeps_its_fine_texture():
    """With a tiny robust sigma, residuals a few sigmas out but under `min_excess` are texture, not weather."""
    residual = torch.randn(64, 96, 3, generator=torch.Generator().manual_seed(2)) * 0.001
    residual[::7, ::5] += 0.02  # small bright misses of fine detail
    assert inlier_weights(residual, RobustMaskConfig(enabled=True)).min() == 1
    assert inlier_weights(residual, RobustMaskConfig(enabled=True, min_excess=0.0)).mean() < 0.9


def test_pinball_l1_is_l1_at_the_median_and_least_at_its_quantile():
    """A value fitted to many photos by the pinball L1 lands on their q-quantile (closed form), not their median."""
    from metegs.losses.photometric import pinball_l1

    g = torch.Generator().manual_seed(4)
    pred, target = torch.rand(8, 8, 3, generator=g), torch.rand(8, 8, 3, generator=g)
    assert torch.equal(pinball_l1(pred, target), (pred - target).abs())
    photos = 0.3 + torch.rand(401, generator=g).pow(3) * 0.5  # one point's photos, brightened by rain
    for q in (0.1, 0.25, 0.5):
        value = torch.tensor(0.5, requires_grad=True)
        opt = torch.optim.Adam([value], lr=0.01)
        for _ in range(600):
            opt.zero_grad()
            pinball_l1(value.expand_as(photos), photos, q).mean().backward()
            opt.step()
        assert abs(float(value) - float(photos.quantile(q))) < 0.01, q


def test_the_quantile_reaches_the_l1_term_only():
    g = torch.Generator().manual_seed(5)
    pred = torch.rand(24, 32, 3, generator=g)
    target = (pred + 0.1).clamp(max=1)  # every photo brighter than the render
    loss, ones = PhotometricLoss(), torch.ones(24, 32)
    darker = (pred - 0.1).clamp(min=0)  # every photo darker
    assert loss(pred, target, ones, quantile=0.1) < loss(pred, target, ones) < loss(pred, darker, ones)
    assert loss(pred, darker, ones) < loss(pred, darker, ones, quantile=0.1)
    plain = PhotometricLoss(PhotometricLossConfig(ssim_lambda=0.0))
    assert torch.isclose(plain(pred, target, ones, 0.1), 0.2 * (target - pred).mean())


def test_without_bright_strokes_takes_streaks_from_either_side():
    """Where the photo or the render holds a stroke narrower than the square and brighter than its surroundings by
    more than ``min_excess``, both are opened; fainter strokes (texture), dark ones and wide bright patches stay,
    and the render's gradient passes."""
    photo = torch.full((24, 30, 3), 0.4)
    photo[:, 5] += 0.5  # a streak in the photo
    photo[:, 8] += 0.02  # faint texture
    photo[:, 20] -= 0.3  # a dark stroke
    photo[4:12, 24:29] = 0.9  # a bright patch wider than the square
    render = torch.full((24, 30, 3), 0.4, requires_grad=True)
    modelled = render + torch.nn.functional.pad(torch.full((24, 1, 3), 0.3), (0, 0, 15, 14))  # a streak at x = 15
    out_render, out_photo = without_bright_strokes(modelled, photo, 3, 0.04)
    torch.testing.assert_close(out_photo[:, 5], torch.full((24, 3), 0.4))
    torch.testing.assert_close(out_render[:, 15], torch.full((24, 3), 0.4))
    kept = torch.ones(24, 30, dtype=torch.bool)
    kept[:, 5] = kept[:, 15] = False
    assert torch.equal(out_photo[kept], photo[kept]) and torch.equal(out_photo[:, 15], photo[:, 15])
    assert torch.equal(out_render.detach()[kept], modelled.detach()[kept])
    out_render.sum().backward()  # every output passes its gradient to the pixel it came from
    assert float(render.grad.sum()) == out_render.numel()
    faint = without_bright_strokes(modelled.detach(), photo, 3, 0.6)  # nothing stands out by 0.6
    assert torch.equal(faint[1], photo) and torch.equal(faint[0], modelled.detach())
    off = without_bright_strokes(modelled.detach(), photo, 0, 0.04)
    assert torch.equal(off[1], photo) and torch.equal(off[0], modelled.detach())


def test_the_stroke_width_grows_with_the_image():
    """`stroke_width_px`: the width given at 480 px, scaled to the image's longer side, odd; 1 under two pixels."""
    assert stroke_width_px(3.0, 480) == 3
    assert stroke_width_px(3.0, 514) == 3
    assert stroke_width_px(3.0, 640) == 5  # 4 px, and an odd square
    assert stroke_width_px(3.0, 1600) == 11
    assert stroke_width_px(3.0, 160) == 1 and stroke_width_px(3.0, 300) == 3
    assert stroke_width_px(0.0, 1600) == 1


def _rainy(image: np.ndarray, klass: str, seed: int = 1) -> torch.Tensor:
    """``image`` [H, W, 3] under the independent family's streak layers of WMO class ``klass``."""
    return torch.from_numpy(rain_view(np.random.default_rng(seed), image, klass, 10.0, np.full(3, 0.8))[0])


def test_stroke_energy_finds_streaks_and_not_a_scene_s_bright_details():
    """Streaks of one rain lead in one orientation; a scene without thin bright strokes, or with specks that go
    every way, holds next to none; a photo larger than the working size is measured at that size, so its streaks,
    twice as wide at twice the size, still show."""
    g = torch.Generator().manual_seed(0)
    blocks = torch.full((192, 256, 3), 0.1)
    for y in range(4, 192, 48):  # a 4 x 4 grid of coloured blocks, 8 px apart: nothing thin and bright
        for x in range(4, 256, 64):
            blocks[y : y + 40, x : x + 56] = torch.rand(3, generator=g)
    assert stroke_energy(blocks) == pytest.approx(0.0, abs=1e-9)
    for klass in ("moderate", "heavy"):
        for seed in (1, 2):
            assert stroke_energy(_rainy(blocks.numpy(), klass, seed)) > 1.5 * VISIBLE_STROKE_ENERGY
    noise = (0.5 + 0.05 * torch.randn(192, 256, 3, generator=g)).clamp(0, 1)  # specks as bright as light streaks
    assert stroke_energy(noise) < 0.5 * VISIBLE_STROKE_ENERGY
    wide = torch.nn.functional.interpolate(blocks.permute(2, 0, 1)[None], size=(360, 480))[0].permute(1, 2, 0)
    rainy = _rainy(wide.numpy(), "heavy")  # at the working size
    twice = torch.nn.functional.interpolate(rainy.permute(2, 0, 1)[None], scale_factor=2, mode="bilinear")
    assert stroke_energy(twice[0].permute(1, 2, 0)) > 0.5 * stroke_energy(rainy) > VISIBLE_STROKE_ENERGY


@pytest.mark.data
def test_a_real_capture_shows_no_streaks_until_it_rains():
    """The Ethiopian head's photos stay well under `VISIBLE_STROKE_ENERGY`; the same photos under heavy independent
    rain pass it well."""
    files = sorted(HEAD.glob("*.jpg"))[::16] if HEAD.is_dir() else []
    if not files:
        pytest.skip(f"real LLFF scene not found at {HEAD} (needs ../shared beside the repository)")
    for path in files:
        photo = np.asarray(Image.open(path).convert("RGB"), dtype=np.float32) / 255
        clear, rainy = stroke_energy(torch.from_numpy(photo)), stroke_energy(_rainy(photo, "heavy"))
        assert clear < 0.5 * VISIBLE_STROKE_ENERGY and rainy > 1.5 * VISIBLE_STROKE_ENERGY, path.name
