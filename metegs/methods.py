"""Named, complete method configs (registry kind ``method``). Variants derive from a base with `replace`."""

from __future__ import annotations

from metegs.engine.config import TrainConfig


def gaussian_splatting() -> TrainConfig:
    """Plain 3D Gaussian Splatting with the reference defaults: 0.8·L1 + 0.2·(1 − SSIM), ADC densification."""
    return TrainConfig(method="3dgs")
