"""One Adam per parameter group (gsplat style) and the in-place edits densification makes to them."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

import torch
from torch import nn

from metegs.validate import NON_NEGATIVE, POSITIVE


@dataclass
class OptimConfig:
    """Learning rates of the 3DGS reference (INRIA), per parameter group."""

    means_lr: Annotated[float, NON_NEGATIVE] = 1.6e-4
    """Initial position learning rate, multiplied by the scene extent."""
    means_lr_final: Annotated[float, NON_NEGATIVE] = 1.6e-6
    """Final position learning rate (exponential decay over the run), multiplied by the scene extent."""
    sh0_lr: Annotated[float, NON_NEGATIVE] = 2.5e-3
    """Learning rate of the SH DC colour."""
    shN_lr: Annotated[float, NON_NEGATIVE] = 2.5e-3 / 20
    """Learning rate of the higher SH coefficients."""
    opacities_lr: Annotated[float, NON_NEGATIVE] = 0.05
    """Learning rate of the opacity logits (0.025 in the Oct-2024 INRIA update)."""
    scales_lr: Annotated[float, NON_NEGATIVE] = 5e-3
    """Learning rate of the log-scales."""
    quats_lr: Annotated[float, NON_NEGATIVE] = 1e-3
    """Learning rate of the rotations."""
    exposure_lr: Annotated[float, POSITIVE] = 1e-3
    """Learning rate of the training views' gains and offsets (`view_exposure`)."""
    eps: Annotated[float, POSITIVE] = 1e-15
    """Adam epsilon."""


def adam(params, **kwargs) -> torch.optim.Adam:
    """``torch.optim.Adam(params, **kwargs)``, fused (one kernel per parameter) where torch has a fused Adam
    for the parameters' device: on CPU since torch 2.4, several times faster than the per-tensor loop
    torch otherwise uses there. Falls back to the default implementation elsewhere."""
    params = list(params)
    try:
        return torch.optim.Adam(params, fused=True, **kwargs)
    except (RuntimeError, ValueError, TypeError):  # device or dtype without a fused kernel (or an older torch)
        return torch.optim.Adam(params, **kwargs)


def make_optimizers(params: nn.ParameterDict, cfg: OptimConfig, extent: float) -> dict[str, torch.optim.Adam]:
    """One single-group Adam per parameter; the position rate scales with the scene ``extent``."""
    lrs = {
        "means": cfg.means_lr * extent,
        "sh0": cfg.sh0_lr,
        "shN": cfg.shN_lr,
        "opacities": cfg.opacities_lr,
        "scales": cfg.scales_lr,
        "quats": cfg.quats_lr,
    }
    return {name: adam([params[name]], lr=lrs[name], eps=cfg.eps) for name in params.keys()}


def means_lr_at(step: int, max_steps: int, cfg: OptimConfig, extent: float) -> float:
    """Log-linear decay of the position learning rate from ``means_lr`` to ``means_lr_final``."""
    t = min(max(step / max(max_steps, 1), 0.0), 1.0)
    return extent * float(cfg.means_lr ** (1 - t) * cfg.means_lr_final**t)
