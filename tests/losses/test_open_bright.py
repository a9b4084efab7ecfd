"""`open_bright`: a grey-scale opening of an image, against a plain loop over the pixels."""

from __future__ import annotations

import pytest
import torch

from metegs.losses.photometric import open_bright


def plain_window(image: torch.Tensor, k: int, reduce) -> torch.Tensor:
    """[H, W, C]: ``reduce`` (min or max) of each pixel's k × k window, clipped at the borders."""
    h, w, c = image.shape
    out = torch.empty_like(image)
    r = k // 2
    for y in range(h):
        for x in range(w):
            patch = image[max(0, y - r) : y + r + 1, max(0, x - r) : x + r + 1].reshape(-1, c)
            out[y, x] = reduce(patch, dim=0).values
    return out


@pytest.mark.parametrize("width, k", [(1, 1), (3, 3), (4, 5), (7, 7)])
def test_open_bright_matches_a_plain_loop_borders_included(width, k):
    image = torch.rand(9, 13, 3, generator=torch.Generator().manual_seed(width), dtype=torch.float64)
    expected = plain_window(plain_window(image, k, torch.min), k, torch.max)
    torch.testing.assert_close(open_bright(image, width), expected)


def test_open_bright_takes_thin_bright_strokes_and_keeps_the_rest():
    image = torch.full((24, 30, 3), 0.4)
    image[:, 5] += 0.5  # a streak one pixel wide
    image[3:20, 10:12] += 0.3  # and one two pixels wide
    image[:, 20] -= 0.3  # a dark stroke
    image[4:12, 24:29] = 0.9  # a bright patch wider than the square
    opened = open_bright(image, 3)
    torch.testing.assert_close(opened[:, 5], torch.full((24, 3), 0.4))
    torch.testing.assert_close(opened[:, 10:12], torch.full((24, 2, 3), 0.4))
    torch.testing.assert_close(opened[:, 20], image[:, 20])
    torch.testing.assert_close(opened[4:12, 24:29], image[4:12, 24:29])
    assert torch.equal(open_bright(image, 0), image)
    assert bool((opened <= image).all())  # an opening never brightens
