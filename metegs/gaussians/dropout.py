"""Random Gaussian dropping while training (DropGaussian, Park et al., CVPR 2025): each training step renders the
scene without a random share of its Gaussians, the rest's opacity scaled up to keep a pixel's expected cover, so
that Gaussians behind others, or seen from few views, are fitted by more of them."""

from __future__ import annotations

from dataclasses import replace

import torch

from metegs.gaussians.model import GaussianSet


def drop_rate_at(step: int, max_steps: int, final_rate: float) -> float:
    """The share dropped at ``step``: rising linearly from 0 at the start to ``final_rate`` at ``max_steps``."""
    return final_rate * min(max(step, 0), max_steps) / max(max_steps, 1)


def drop_gaussians(gaussians: GaussianSet, rate: float, generator: torch.Generator) -> GaussianSet:
    """``gaussians`` (N of them) with each left out with probability ``rate`` (opacity 0, so they take no gradient)
    and the others' opacities divided by 1 - rate; N and the order stay, so per-Gaussian statistics still line up.
    ``generator`` is a CPU generator (the draw is the same on every device)."""
    if rate <= 0:
        return gaussians
    if rate >= 1:
        raise ValueError(f"drop rate {rate} leaves no Gaussian to render (expected a share in [0, 1))")
    n = gaussians.opacities.shape[0]
    keep = torch.rand(n, generator=generator) >= rate
    scale = keep.to(gaussians.opacities.dtype).to(gaussians.opacities.device) / (1.0 - rate)
    return replace(gaussians, opacities=gaussians.opacities * scale)
