"""Backend selection: ``auto`` picks the best registered backend for the device."""

from __future__ import annotations

import torch

from metegs.errors import ConfigError
from metegs.registry import registry

AUTO_ORDER_CUDA = ("gsplat", "cpu", "torch")
AUTO_ORDER_CPU = ("cpu", "torch")


def resolve_backend(name: str, device: torch.device | str) -> str:
    """The backend name ``auto`` stands for on ``device`` (the first registered one that is usable)."""
    if name != "auto":
        if name not in registry("rasterizer"):
            raise ConfigError(f"unknown backend {name!r}; available: auto, {', '.join(registry('rasterizer').names())}")
        return name
    order = AUTO_ORDER_CUDA if torch.device(device).type == "cuda" else AUTO_ORDER_CPU
    for candidate in order:
        if candidate in registry("rasterizer"):
            cls = registry("rasterizer").get(candidate)
            available = getattr(cls, "available", None)
            if available is None or available(torch.device(device)):
                return candidate
    return "torch"


def make_rasterizer(name: str, device: torch.device | str = "cpu"):
    """Instantiate the rasteriser ``name`` (or ``auto``) for ``device``."""
    return registry("rasterizer").get(resolve_backend(name, device))()
