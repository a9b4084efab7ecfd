"""Airlight A from images: the dark-channel-prior estimate (He, Sun and Tang, CVPR 2009)."""

from __future__ import annotations

import torch

from metegs.eval.veil import dark_channel


def estimate_airlight(images: list[torch.Tensor], top_fraction: float = 0.001, patch: int = 15) -> torch.Tensor:
    """Mean colour of the brightest-dark-channel pixels (top ``top_fraction``) over the images -> [3].

    In clear images this picks the sky or the brightest haze-free surfaces, which is what the
    airlight of a light fog looks like; a user may always give A explicitly.
    """
    pixels, darks = [], []
    for im in images:
        im = im.float()
        patch_here = max(1, min(patch, min(im.shape[:2]) // 4 * 2 + 1))
        darks.append(dark_channel(im, patch_here).reshape(-1))
        pixels.append(im.reshape(-1, 3))
    dark, rgb = torch.cat(darks), torch.cat(pixels)
    k = max(1, int(round(top_fraction * dark.numel())))
    idx = torch.topk(dark, k).indices
    return rgb[idx].mean(dim=0).clamp(0.0, 1.0)


def typical_airlight(images: list[torch.Tensor], top_fraction: float = 0.001, patch: int = 15) -> torch.Tensor:
    """Median over ``images`` (each [H, W, 3]) of each one's `estimate_airlight` -> [3]: where photos differ in
    exposure, the pooled estimate takes the brightest photo's haze, the median a typical one's."""
    return torch.stack([estimate_airlight([im], top_fraction, patch) for im in images]).median(dim=0).values
