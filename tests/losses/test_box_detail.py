"""`box_detail`: an image minus its box mean, against a plain loop over the pixels."""

from __future__ import annotations

import pytest
import torch

from metegs.losses.photometric import box_detail


def plain_box_detail(image: torch.Tensor, k: int) -> torch.Tensor:
    h, w, _ = image.shape
    out = torch.empty_like(image)
    r = k // 2
    for y in range(h):
        for x in range(w):
            patch = image[max(0, y - r) : y + r + 1, max(0, x - r) : x + r + 1]
            out[y, x] = image[y, x] - patch.reshape(-1, image.shape[2]).mean(0)
    return out


@pytest.mark.parametrize("width, k", [(1, 1), (3, 3), (5, 5), (4, 5), (21, 21)])
def test_box_detail_matches_a_plain_loop_borders_included(width, k):
    image = torch.rand(9, 13, 3, generator=torch.Generator().manual_seed(width), dtype=torch.float64)
    torch.testing.assert_close(box_detail(image, width), plain_box_detail(image, k))


def test_box_detail_drops_tone_and_keeps_thin_strokes():
    image = torch.full((20, 30, 3), 0.4)
    image[:, 12] += 0.5  # a one-pixel streak
    brighter = box_detail(image * 1.0 + 0.3, 9)
    torch.testing.assert_close(box_detail(image, 9), brighter)  # an offset is no detail
    assert float(brighter[:, 12].mean()) > 0.4  # the streak stands out of its mean
    assert torch.equal(box_detail(image, 0), image)
