"""Slots for learned single-image restorers (Restormer, DehazeFormer, ...) run from weights the user gives.

metegs ships no network weights and no copies of these architectures. A slot runs a network the user
provides in one of two forms:

- an exported program (``torch.export.save``, a ``.pt2`` file) or a TorchScript file (``torch.jit.save``)
  of the model, e.g. exported from the authors' repository: ``weights: restormer_deraining.pt2`` (export
  it with dynamic height and width: the photos' sizes, padded to ``pad_multiple``, vary);
- a state-dict checkpoint plus the architecture as ``"module:callable"`` importable here (for instance
  from the authors' package installed next to metegs): ``weights: deraining.pth``,
  ``arch: basicsr.models.archs.restormer_arch:Restormer`` (``arch_kwargs`` are passed to the callable; a
  checkpoint whose tensors sit under ``params`` or ``state_dict`` is unwrapped).

Without weights, setting a slot up is a `ConfigError` that says what to give. The network sees
[1, 3, H, W] float32 RGB, reflect-padded to a multiple of ``pad_multiple``, in [0, 1] (Restormer) or
[-1, 1] (DehazeFormer's convention); the output is cropped back and clipped to [0, 1].

- Restormer: S. W. Zamir et al., "Restormer: Efficient Transformer for High-Resolution Image Restoration",
  CVPR 2022 (deraining weights remove rain).
- DehazeFormer: Y. Song et al., "Vision Transformers for Single Image Dehazing", IEEE TIP 32, 2023
  (removes fog/haze).
"""

from __future__ import annotations

import importlib
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Literal

import numpy as np
import torch

from metegs.config import InstantiateConfig
from metegs.errors import ConfigError, DataError
from metegs.restore.base import check_image


@dataclass
class LearnedRestorerConfig(InstantiateConfig):
    """A learned restorer run from user-given weights (TorchScript, or a state dict + ``arch``)."""

    _target: type = field(default_factory=lambda: LearnedRestorer, repr=False)
    weights: Path | None = None
    """Exported program (.pt2), TorchScript file, or a state-dict checkpoint with ``arch``; None: the slot's
    environment variable."""
    arch: str | None = None
    """``module:callable`` building the network for a state-dict checkpoint (None for TorchScript files)."""
    arch_kwargs: dict[str, Any] = field(default_factory=dict)
    """Keyword arguments of ``arch``."""
    device: str = "cpu"
    """Torch device the network runs on."""
    pad_multiple: int = 8
    """Inputs are reflect-padded to a multiple of this (the network's down-sampling factor)."""
    value_range: Literal["0-1", "-1-1"] = "0-1"
    """Value range the network expects and returns."""

    slot: ClassVar[str] = "learned"
    """Registry name of the slot (for messages)."""
    removes: ClassVar[frozenset[str]] = frozenset({"rain", "fog"})
    """Weather kinds the slot is meant to remove."""
    env: ClassVar[str] = "METEGS_RESTORER_WEIGHTS"
    """Environment variable read when ``weights`` is None."""
    hint: ClassVar[str] = "an export of the network (.pt2 or TorchScript), or its checkpoint with arch: module:callable"


@dataclass
class RestormerConfig(LearnedRestorerConfig):
    """Restormer (Zamir et al., CVPR 2022) with the user's deraining weights."""

    _target: type = field(default_factory=lambda: LearnedRestorer, repr=False)
    slot: ClassVar[str] = "restormer"
    removes: ClassVar[frozenset[str]] = frozenset({"rain"})
    env: ClassVar[str] = "METEGS_RESTORMER_WEIGHTS"
    hint: ClassVar[str] = (
        "the deraining checkpoint of the Restormer repository (deraining.pth) with "
        "arch: basicsr.models.archs.restormer_arch:Restormer, or an export of it (.pt2 or TorchScript)"
    )


@dataclass
class DehazeFormerConfig(LearnedRestorerConfig):
    """DehazeFormer (Song et al., IEEE TIP 2023) with the user's dehazing weights."""

    _target: type = field(default_factory=lambda: LearnedRestorer, repr=False)
    value_range: Literal["0-1", "-1-1"] = "-1-1"
    """Value range the network expects and returns (DehazeFormer works in [-1, 1])."""
    pad_multiple: int = 16
    """Inputs are reflect-padded to a multiple of this."""
    slot: ClassVar[str] = "dehazeformer"
    removes: ClassVar[frozenset[str]] = frozenset({"fog"})
    env: ClassVar[str] = "METEGS_DEHAZEFORMER_WEIGHTS"
    hint: ClassVar[str] = (
        "a DehazeFormer checkpoint (e.g. dehazeformer-b.pth) with arch: models.dehazeformer:dehazeformer_b, "
        "or an export of it (.pt2 or TorchScript)"
    )


def _load_callable(spec: str, slot: str):
    module_name, _, attr = spec.partition(":")
    if not module_name or not attr:
        raise ConfigError(f"restorer {slot!r}: arch must be 'module:callable', got {spec!r}")
    try:
        obj = importlib.import_module(module_name)
        for part in attr.split("."):
            obj = getattr(obj, part)
    except (ImportError, AttributeError) as exc:
        raise ConfigError(f"restorer {slot!r}: cannot import arch {spec!r}: {type(exc).__name__}: {exc}") from exc
    return obj


class LearnedRestorer:
    """Runs a user-given network on one image at a time (see the module docstring)."""

    def __init__(self, config: LearnedRestorerConfig):
        self.config = config
        self.name = config.slot
        self.removes = config.removes
        path = config.weights or (Path(os.environ[config.env]) if os.environ.get(config.env) else None)
        if path is None:
            raise ConfigError(
                f"restorer {config.slot!r} needs network weights, which metegs does not ship: give {config.hint} "
                f"(suite option weights: PATH, or the environment variable {config.env})"
            )
        path = Path(path).expanduser()
        if not path.is_file():
            raise ConfigError(f"restorer {config.slot!r}: weights file {path} not found")
        self.weights_path = path
        """The network's weights file (part of `cache_key`)."""
        self.device = torch.device(config.device)
        net = self._load(path).to(self.device)
        self.net = net.eval() if hasattr(net, "eval") and not path.suffix == ".pt2" else net

    def _load(self, path: Path) -> torch.nn.Module:
        c = self.config
        if c.arch is None and path.suffix == ".pt2":
            try:
                return torch.export.load(str(path)).module()
            except Exception as exc:  # noqa: BLE001 - any failure means: not an exported program
                raise DataError(
                    path, f"restorer {c.slot!r}: not a torch.export program ({type(exc).__name__}: {exc})"
                ) from exc
        if c.arch is None:
            try:
                return torch.jit.load(str(path), map_location="cpu")
            except Exception as exc:  # noqa: BLE001 - any failure means: not a TorchScript file
                raise DataError(
                    path,
                    f"restorer {c.slot!r}: not a TorchScript file ({type(exc).__name__}); for a state-dict "
                    f"checkpoint also give arch: module:callable",
                ) from exc
        net = _load_callable(c.arch, c.slot)(**c.arch_kwargs)
        state = torch.load(path, map_location="cpu", weights_only=True)
        for key in ("params", "state_dict", "model"):
            if isinstance(state, dict) and key in state and isinstance(state[key], dict):
                state = state[key]
                break
        state = {k.removeprefix("module."): v for k, v in state.items()}
        try:
            net.load_state_dict(state)
        except RuntimeError as exc:
            raise DataError(path, f"restorer {c.slot!r}: the checkpoint does not fit {c.arch}: {exc}") from exc
        return net

    @torch.no_grad()
    def restore(self, image: np.ndarray) -> np.ndarray:
        image = check_image(image, self.name)
        H, W = image.shape[:2]
        m = max(1, self.config.pad_multiple)
        x = torch.from_numpy(image).permute(2, 0, 1)[None].to(self.device)
        ph, pw = (-H) % m, (-W) % m
        if ph or pw:
            mode = "reflect" if ph < H and pw < W else "replicate"
            x = torch.nn.functional.pad(x, (0, pw, 0, ph), mode=mode)
        if self.config.value_range == "-1-1":
            x = x * 2.0 - 1.0
        y = self.net(x)
        if isinstance(y, (tuple, list)):
            y = y[0]
        if self.config.value_range == "-1-1":
            y = (y + 1.0) * 0.5
        y = y[0, :, :H, :W].permute(1, 2, 0).float().cpu().numpy()
        if not np.isfinite(y).all():
            raise DataError(None, f"restorer {self.name!r} returned NaN or Inf values")
        return np.clip(y, 0.0, 1.0).astype(np.float32)
