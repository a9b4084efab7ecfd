"""The airlight read from photos: pooled over the photos or a typical photo's."""

from __future__ import annotations

import torch

from metegs.weather.airlight import estimate_airlight, typical_airlight


def hazy_photos(gains: list[float]) -> tuple[list[torch.Tensor], torch.Tensor]:
    """Photos [60, 80, 3] of a sky at airlight (0.80, 0.82, 0.85) over a darker textured ground, each scaled by its
    gain as auto-exposure does -> (photos, airlight)."""
    g = torch.Generator().manual_seed(0)
    airlight = torch.tensor([0.80, 0.82, 0.85])
    photos = []
    for gain in gains:
        photo = 0.1 + 0.3 * torch.rand(60, 80, 3, generator=g)
        photo[:20] = airlight
        photos.append((photo * gain).clamp(0.0, 1.0))
    return photos, airlight


def test_the_typical_airlight_is_not_the_brightest_exposure():
    """Under gains of 1 ± 0.15 the pooled estimate takes the brightest photo's sky (15 % too bright); the median of
    each photo's estimate is within 0.01 of the airlight, as both are where the exposures agree."""
    photos, airlight = hazy_photos([0.85, 0.9, 0.95, 1.0, 1.05, 1.1, 1.15])
    assert (estimate_airlight(photos) - 1.15 * airlight).abs().max() < 0.01
    assert (typical_airlight(photos) - airlight).abs().max() < 0.01
    same, _ = hazy_photos([1.0, 1.0, 1.0])
    assert (typical_airlight(same) - estimate_airlight(same)).abs().max() < 1e-6
