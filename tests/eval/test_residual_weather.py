"""The residual-weather measures: zero for a perfect render, streaks found and told from noise, haze's contrast
loss equal to its transmittance."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from metegs.eval.residual_weather import contrast_ratio, streak_energy
from metegs.weather.independent import rain_view


def _scene(seed=0) -> torch.Tensor:
    rng = np.random.default_rng(seed)
    img = np.zeros((120, 160, 3), np.float32)
    for _ in range(12):  # blocks of colour: edges and flat areas, like a real view
        x, y = rng.integers(0, 140), rng.integers(0, 100)
        img[y : y + rng.integers(10, 40), x : x + rng.integers(10, 40)] = rng.random(3)
    return torch.from_numpy(img * 0.8 + 0.1)


def test_a_perfect_render_has_no_residual_weather():
    ref = _scene()
    assert streak_energy(ref, ref) == 0.0
    assert contrast_ratio(ref, ref) == pytest.approx(1.0)


def test_streaks_score_far_above_noise_of_the_same_energy():
    ref = _scene()
    rainy = torch.from_numpy(rain_view(np.random.default_rng(1), ref.numpy(), "heavy", 10.0, np.full(3, 0.8))[0])
    residual = rainy - ref
    noise = torch.randn_like(ref) * residual.std()
    streaks, speckle = streak_energy(rainy, ref), streak_energy((ref + noise).clamp(0, 1), ref)
    assert streaks > 3 * speckle > 0
    assert streak_energy(ref + 0.1, ref) == pytest.approx(0.0, abs=1e-6)  # a uniform offset is no streak
    blurred = torch.from_numpy(cv2.GaussianBlur(ref.numpy(), (0, 0), 1.5))
    assert streaks > 10 * streak_energy(blurred, ref)  # nor is a blurry render's error at the edges


@pytest.mark.parametrize("t", [0.3, 0.6, 0.9])
def test_homogeneous_haze_keeps_its_transmittance_of_contrast(t):
    ref = _scene()
    hazy = ref * t + 0.8 * (1 - t)
    assert contrast_ratio(hazy, ref) == pytest.approx(t, rel=1e-4)
