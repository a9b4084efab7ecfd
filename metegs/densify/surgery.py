"""Optimiser surgery of densification: rows of the Gaussians' parameters removed or appended, with their Adam
moments, so that every optimiser keeps pointing at the new parameters."""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import nn


@torch.no_grad()
def update_params(
    params: nn.ParameterDict,
    optimizers: dict[str, torch.optim.Optimizer],
    param_fn: Callable[[str, torch.Tensor], torch.Tensor],
    state_fn: Callable[[str, torch.Tensor], torch.Tensor],
) -> None:
    """Replace every parameter by ``param_fn(name, p)`` and every per-element optimiser state tensor
    (Adam moments) by ``state_fn(key, v)``, keeping optimisers pointing at the new parameters."""
    for name in list(params.keys()):
        old = params[name]
        new = nn.Parameter(param_fn(name, old.data).contiguous(), requires_grad=old.requires_grad)
        params[name] = new
        opt = optimizers[name]
        state = opt.state.pop(old, None)
        opt.param_groups[0]["params"] = [new]
        if state is not None:
            for key, value in state.items():
                if key != "step" and torch.is_tensor(value) and value.dim() > 0:
                    state[key] = state_fn(key, value)
            opt.state[new] = state


def select_rows(params, optimizers, keep: torch.Tensor) -> None:
    """Keep only the rows where ``keep`` [N] is True, in parameters and Adam moments."""
    update_params(params, optimizers, lambda _, p: p[keep], lambda _, v: v[keep])


def append_rows(params, optimizers, new: dict[str, torch.Tensor]) -> None:
    """Append new rows (one tensor per parameter name); their Adam moments start at zero."""
    update_params(
        params,
        optimizers,
        lambda name, p: torch.cat([p, new[name].to(p)]),
        lambda _, v: torch.cat([v, v.new_zeros((next(iter(new.values())).shape[0], *v.shape[1:]))]),
    )
