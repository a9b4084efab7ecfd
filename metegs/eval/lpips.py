"""LPIPS v0.1 (Zhang et al. 2018) with explicit, offline-first weight resolution.

The metric is computed exactly as the official ``lpips`` package (v0.1, ``LPIPS(net=..., version="0.1")``
with ``normalize=True``):

1. images in [0, 1] are mapped to [-1, 1] (``2 x - 1``);
2. the ScalingLayer: ``(x - shift) / scale`` with shift ``[-.030, -.088, -.188]``, scale ``[.458, .448, .450]``;
3. five ReLU feature maps of the backbone (AlexNet ``relu1..relu5`` / VGG16 ``relu1_2, relu2_2, relu3_3,
   relu4_3, relu5_3``);
4. each feature map unit-normalised over channels (``f / (||f||_2 + 1e-10)``), squared difference,
   1x1 linear head (no bias), spatial average, sum over the five layers.

Weights come in two parts, neither of which is ever replaced by a substitute:

- **Backbone** (`metegs.eval.backbones`, shared with the perceptual loss): torchvision ImageNet checkpoints.
  Our `alexnet_features` / `vgg16_features` have the same
  layer structure and state-dict keys as torchvision's ``alexnet().features`` / ``vgg16().features``, so a
  torchvision file (full model, keys ``features.*``/``classifier.*``, or features only) loads directly.
  Looked up, in order: the ``backbone_path`` argument, the ``METEGS_LPIPS_BACKBONE`` env var (a file, or a
  folder holding the torchvision file name), then ``torch.hub.get_dir()/checkpoints/<file>``
  (``alexnet-owt-7be5be79.pth`` / ``vgg16-397923af.pth``). Found nowhere, it is downloaded on first use
  into that same cache with ``torch.hub.load_state_dict_from_url``, as torchvision does (unless
  ``allow_download=False``); a download that fails (offline) is tried once per process and gives the reason.
- **Linear heads**: the official ``lpips`` files ``<net>.pth`` (keys ``lin{0..4}.model.1.weight``, shapes
  ``[1, C_l, 1, 1]``). Looked up, in order: the ``heads_dir`` argument, the ``METEGS_LPIPS_HEADS`` env var,
  then the copy that the ``torchmetrics`` package (a dependency) ships, byte for byte the ``lpips`` package's
  v0.1 files (`packaged_heads_dir`). Each may be the ``.pth`` file itself or a folder holding ``<net>.pth``,
  ``v0.1/<net>.pth`` or ``weights/v0.1/<net>.pth``.

An explicitly given path (argument or env var) that does not hold the file is an error; it never falls
back silently to another location. Missing weights raise `WeightsUnavailable`; `try_load_lpips` turns that
into ``(None, reason)`` so an evaluator can report LPIPS as null with the reason.
"""

from __future__ import annotations

import importlib.util
import os
from pathlib import Path

import torch
from torch import nn

from metegs.eval.backbones import (
    BACKBONE_ENV,
    WeightsUnavailable,
    alexnet_features,
    backbone_spec,
    backbone_state,
    download_backbone,
    file_in,
    read_state_dict,
    resolve_backbone_file,
    vgg16_features,
)

__all__ = [
    "BACKBONE_ENV",
    "HEADS_ENV",
    "LPIPS",
    "WeightsUnavailable",
    "alexnet_features",
    "packaged_heads_dir",
    "load_lpips",
    "lpips",
    "resolve_backbone_file",
    "resolve_heads_file",
    "try_load_lpips",
    "vgg16_features",
]

HEADS_ENV = "METEGS_LPIPS_HEADS"

_SHIFT = (-0.030, -0.088, -0.188)
_SCALE = (0.458, 0.448, 0.450)
_EPS = 1e-10


# ------------------------------------------------------------------------------------------------ module


class _LinearHead(nn.Module):
    """Official ``NetLinLayer`` layout: ``model = Sequential(Dropout, Conv2d(C, 1, 1, bias=False))``.

    The dropout (identity at eval time, which is how LPIPS is always used) is an `nn.Identity` here so the
    key ``model.1.weight`` is preserved while the module behaves the same in train mode.
    """

    def __init__(self, channels: int):
        super().__init__()
        self.model = nn.Sequential(nn.Identity(), nn.Conv2d(channels, 1, kernel_size=1, bias=False))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.model(x)


class _LinearHeads(nn.Module):
    """Holds ``lin0..lin4`` so the official heads file loads with ``load_state_dict`` as is."""

    def __init__(self, channels: tuple[int, ...]):
        super().__init__()
        for i, c in enumerate(channels):
            self.add_module(f"lin{i}", _LinearHead(c))

    def __getitem__(self, i: int) -> _LinearHead:
        return getattr(self, f"lin{i}")


class LPIPS(nn.Module):
    """LPIPS v0.1 distance. Parameters are frozen; gradients flow to the inputs (usable as a loss).

    ``LPIPS(net)`` has randomly initialised weights: use `load_lpips` to get the real metric.

    Attributes:
        net: ``"alex"`` or ``"vgg"``.
        features: the torchvision-compatible backbone ``nn.Sequential``.
        heads: the five 1x1 linear heads (keys ``lin{i}.model.1.weight``).
    """

    def __init__(self, net: str = "alex"):
        super().__init__()
        spec = backbone_spec(net)
        self.net = net
        self._slice_ends = spec.slice_ends
        self.register_buffer("shift", torch.tensor(_SHIFT).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("scale", torch.tensor(_SCALE).view(1, 3, 1, 1), persistent=False)
        self.features = spec.build()
        self.heads = _LinearHeads(spec.channels)
        self.requires_grad_(False)
        self.eval()

    def _layer_features(self, x: torch.Tensor) -> list[torch.Tensor]:
        """Five ReLU feature maps ``[N, C_l, H_l, W_l]`` of the scaled input ``x`` ``[N, 3, H, W]``."""
        outs = []
        start = 0
        for end in self._slice_ends:
            for i in range(start, end):
                x = self.features[i](x)
            outs.append(x)
            start = end
        return outs

    def distance_nchw(self, x0: torch.Tensor, x1: torch.Tensor) -> torch.Tensor:
        """LPIPS between ``[N, 3, H, W]`` images in **[-1, 1]** (the official ``normalize=False`` input).

        Returns:
            ``[N]`` distances.
        """
        if x0.shape != x1.shape or x0.ndim != 4 or x0.shape[1] != 3:
            raise ValueError(
                f"expected two [N, 3, H, W] tensors of equal shape, got {tuple(x0.shape)}, {tuple(x1.shape)}"
            )
        dtype = self.shift.dtype
        x0 = (x0.to(dtype) - self.shift) / self.scale
        x1 = (x1.to(dtype) - self.shift) / self.scale
        try:
            f0, f1 = self._layer_features(x0), self._layer_features(x1)
        except RuntimeError as e:
            raise ValueError(
                f"LPIPS-{self.net}: image of size {tuple(x0.shape[-2:])} is too small for the backbone ({e})"
            ) from e
        total = x0.new_zeros(x0.shape[0])
        for i, (a, b) in enumerate(zip(f0, f1, strict=True)):
            a = a / (a.pow(2).sum(dim=1, keepdim=True).sqrt() + _EPS)
            b = b / (b.pow(2).sum(dim=1, keepdim=True).sqrt() + _EPS)
            total = total + self.heads[i]((a - b).pow(2)).mean(dim=(1, 2, 3))
        return total

    def forward(self, pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """LPIPS between channels-last images in **[0, 1]**.

        Args:
            pred, target: ``[..., H, W, 3]``, same shape.

        Returns:
            distances of shape ``[...]`` (a scalar for a single ``[H, W, 3]`` image).
        """
        if pred.shape != target.shape or pred.ndim < 3 or pred.shape[-1] != 3:
            raise ValueError(
                f"expected two [..., H, W, 3] tensors of equal shape, got {tuple(pred.shape)}, {tuple(target.shape)}"
            )
        batch = pred.shape[:-3]
        h, w = pred.shape[-3:-1]
        x0 = pred.reshape(-1, h, w, 3).permute(0, 3, 1, 2) * 2 - 1
        x1 = target.reshape(-1, h, w, 3).permute(0, 3, 1, 2) * 2 - 1
        return self.distance_nchw(x0, x1).reshape(batch)


# -------------------------------------------------------------------------------------------- resolution


def packaged_heads_dir() -> Path | None:
    """The official LPIPS v0.1 heads shipped in the installed ``torchmetrics`` package
    (``torchmetrics/functional/image/lpips_models``), found without importing it; None when not installed."""
    spec = importlib.util.find_spec("torchmetrics")
    if spec is None or not spec.submodule_search_locations:
        return None
    return Path(next(iter(spec.submodule_search_locations))) / "functional" / "image" / "lpips_models"


def resolve_heads_file(net: str = "alex", heads_dir: str | Path | None = None, version: str = "0.1") -> Path:
    """Find the official LPIPS linear-heads file ``<net>.pth``.

    Order: ``heads_dir``, ``$METEGS_LPIPS_HEADS``, `packaged_heads_dir`. Each may be the file itself or a
    folder holding ``<net>.pth``, ``v<version>/<net>.pth`` or ``weights/v<version>/<net>.pth``.

    Raises:
        WeightsUnavailable: not found.
    """
    backbone_spec(net)
    names = [f"{net}.pth", f"v{version}/{net}.pth", f"weights/v{version}/{net}.pth"]
    how = (
        f"pass heads_dir=... or set {HEADS_ENV} to the official lpips v{version} '{net}.pth' (from the lpips "
        f"package, lpips/weights/v{version}/{net}.pth) or a folder holding it"
    )
    for source, given in (("heads_dir", heads_dir), (HEADS_ENV, os.environ.get(HEADS_ENV))):
        if given:
            found = file_in(Path(given).expanduser(), names)
            if found is None:
                raise WeightsUnavailable(net, "heads", f"{source}={given} holds none of {names}; {how}")
            return found
    default = packaged_heads_dir()
    if default is None:
        raise WeightsUnavailable(
            net, "heads", f"the torchmetrics package is not installed (pip install torchmetrics); or {how}"
        )
    found = file_in(default, names)
    if found is None:
        raise WeightsUnavailable(net, "heads", f"none of {names} under {default}; {how}")
    return found


# ------------------------------------------------------------------------------------------------ loading


def load_lpips(
    net: str = "alex",
    backbone_path: str | Path | None = None,
    heads_dir: str | Path | None = None,
    allow_download: bool = True,
    device: str | torch.device | None = None,
) -> LPIPS:
    """Build the LPIPS-``net`` metric with real weights (see module docstring for the lookup order).

    Args:
        net: ``"alex"`` (default, as in the 3DGS papers' tables) or ``"vgg"``.
        backbone_path: torchvision checkpoint file, or a folder holding it.
        heads_dir: official heads file ``<net>.pth`` or a folder holding it.
        allow_download: when the backbone is found nowhere, fetch it into the torch hub cache (default).
        device: where to put the model (default CPU).

    Raises:
        WeightsUnavailable: a file is missing, unreadable, or does not match the architecture.
    """
    spec = backbone_spec(net)
    try:
        state = read_state_dict(resolve_backbone_file(net, backbone_path), net, "backbone")
    except WeightsUnavailable:
        if not allow_download or backbone_path or os.environ.get(BACKBONE_ENV):
            raise
        state = download_backbone(spec, net)
    heads_file = resolve_heads_file(net, heads_dir)
    heads_state = read_state_dict(heads_file, net, "heads")

    model = LPIPS(net)
    try:
        model.features.load_state_dict(backbone_state(state), strict=True)
    except RuntimeError as e:
        raise WeightsUnavailable(
            net, "backbone", f"checkpoint does not match the {net} backbone ({spec.filename} expected): {e}"
        ) from e
    try:
        model.heads.load_state_dict(dict(heads_state), strict=True)
    except RuntimeError as e:
        raise WeightsUnavailable(net, "heads", f"{heads_file} does not match the LPIPS-{net} heads: {e}") from e
    return model.to(device) if device is not None else model


def try_load_lpips(
    net: str = "alex",
    backbone_path: str | Path | None = None,
    heads_dir: str | Path | None = None,
    allow_download: bool = True,
    device: str | torch.device | None = None,
) -> tuple[LPIPS | None, str | None]:
    """`load_lpips`, but returns ``(model, None)`` or ``(None, reason)`` instead of raising.

    Only `WeightsUnavailable` is turned into a reason; a bad ``net`` name still raises ``ValueError``.
    """
    try:
        return load_lpips(net, backbone_path, heads_dir, allow_download, device), None
    except WeightsUnavailable as e:
        return None, str(e)


_CACHE: dict[tuple, LPIPS] = {}


def lpips(
    pred: torch.Tensor,
    target: torch.Tensor,
    net: str = "alex",
    backbone_path: str | Path | None = None,
    heads_dir: str | Path | None = None,
    allow_download: bool = True,
) -> torch.Tensor:
    """Mean LPIPS between channels-last images ``[..., H, W, 3]`` in [0, 1] (scalar tensor).

    The model is loaded once per (net, paths, env) and cached; it is moved to ``pred.device``.

    Raises:
        WeightsUnavailable: weights missing (never substituted).
    """
    key = (
        net,
        str(backbone_path),
        str(heads_dir),
        os.environ.get(BACKBONE_ENV),
        os.environ.get(HEADS_ENV),
        torch.hub.get_dir(),
    )
    if key not in _CACHE:
        _CACHE[key] = load_lpips(net, backbone_path, heads_dir, allow_download)
    model = _CACHE[key].to(pred.device)
    return model(pred, target).mean()
