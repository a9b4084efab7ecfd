"""Backend selection: ``auto`` picks the best registered backend for the device."""

from __future__ import annotations

import torch

from metegs.errors import ConfigError
from metegs.registry import registry

AUTO_ORDER_CUDA = ("gsplat", "cpu", "torch")
AUTO_ORDER_CPU = ("cpu", "torch")


def backend_usable(name: str, device: torch.device | str) -> bool:
    """Whether the registered backend ``name`` can render on ``device`` (backends without ``available`` always can)."""
    available = getattr(registry("rasterizer").get(name), "available", None)
    return available is None or bool(available(torch.device(device)))


def usable_backends(device: torch.device | str) -> list[str]:
    """Every registered backend that can render on ``device``."""
    return [name for name in registry("rasterizer").names() if backend_usable(name, device)]


def resolve_backend(name: str, device: torch.device | str) -> str:
    """The backend name ``auto`` stands for on ``device`` (the first registered one that is usable)."""
    if name != "auto":
        if name not in registry("rasterizer"):
            raise ConfigError(f"unknown backend {name!r}; available: auto, {', '.join(registry('rasterizer').names())}")
        return name
    order = AUTO_ORDER_CUDA if torch.device(device).type == "cuda" else AUTO_ORDER_CPU
    for candidate in order:
        if candidate in registry("rasterizer") and backend_usable(candidate, device):
            return candidate
    return "torch"


def make_rasterizer(name: str, device: torch.device | str = "cpu"):
    """Instantiate the rasteriser ``name`` (or ``auto``) for ``device``."""
    return registry("rasterizer").get(resolve_backend(name, device))()
