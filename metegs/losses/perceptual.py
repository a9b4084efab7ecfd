"""Perceptual loss of the clean branch: L1 distance between frozen pretrained features, at several layers and
two image scales.

    L_perc = 1/(L·S) · Σ_scales Σ_layers  mean|Φ_l(pred_s) − Φ_l(target_s)| / mean|Φ_l(target_s)|

Each layer's L1 term is divided by the mean feature magnitude of the target at that layer and scale (a
constant: no gradient flows through it), so that every term is a relative error of order 1 whatever the
layer's activation scale, and the average over layers and scales is O(1). Identical images give exactly 0.
``pred_s`` is ``pred`` average-pooled by the factor ``s`` (``scales=(1, 2)``: full and half resolution).

Backbones (frozen: no parameter needs a gradient, always in eval mode; gradients flow to ``pred``):

- ``vgg16``: torchvision's ImageNet VGG16 ``features`` (the paper's network), ImageNet mean/std
  normalisation, default layers ``relu1_2, relu2_2, relu3_3, relu4_3``. Weights: the torchvision checkpoint
  ``vgg16-397923af.pth`` (full model or features only), the same file the LPIPS-vgg metric uses.
- ``squeezenet``: SqueezeNet 1.1 (conv1 + fire2..fire9, `metegs.losses.squeezenet`) from a MATLAB ``.mat`` of
  the Caffe release, default layers ``conv1, fire3, fire5, fire9`` (resolutions 1/2 .. 1/16).

Where the weights are looked for (`resolve_weights`), in order:

1. an explicit file: ``weights_path`` in the config, else ``$METEGS_PERCEPTUAL_WEIGHTS`` (a ``.pth``/``.pt``
   is a VGG16 checkpoint, a ``.mat`` a SqueezeNet one; a folder is searched for either). An explicit path
   never falls back to another location.
2. ``backbone`` ``auto`` or ``vgg16``: ``torch.hub.get_dir()/checkpoints/vgg16-397923af.pth``.
3. ``backbone`` ``squeezenet`` only (the stand-in is never picked on its own: on the default bench, synthetic
   scene in light rain, 1000 steps, it cost 0.003 SSIM and 0.3 dB at the paper's weight 0.05, where the term
   is meant for VGG16): ``squeezenet1.1*.mat`` in ``$XDG_CACHE_HOME/metegs/weights``
   (default ``~/.cache/metegs/weights``) and in ``torch.hub.get_dir()/checkpoints``.
4. ``backbone`` ``auto`` or ``vgg16`` (unless ``download=False``): the torchvision VGG16 file is downloaded on
   first use into the torch hub cache, as torchvision does; a failed download (offline) is tried once per
   process (shared with LPIPS-vgg, `metegs.eval.lpips`) and gives the reason.

Nothing found -> `PerceptualWeightsUnavailable` (`try_load_perceptual` returns ``(None, reason)``, reason
naming every place looked at and how to provide weights). A file that is found but cannot be read or does
not match the network -> `metegs.errors.DataError` naming the file (and the layer): a broken file is never
skipped silently.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import torch
from torch import nn
from torch.nn import functional as F

from metegs.config import InstantiateConfig, user_cache
from metegs.errors import ConfigError, DataError
from metegs.eval.backbones import (
    BACKBONES,
    VGG16_CFG,
    WeightsUnavailable,
    backbone_state,
    download_backbone,
    vgg16_features,
)
from metegs.losses.squeezenet import (
    SQUEEZENET_LAYERS,
    SqueezeNetFeatures,
    load_squeezenet_mat,
    max_pool_at_least_one,
)

__all__ = [
    "PERCEPTUAL_ENV",
    "VGG16_LAYERS",
    "PerceptualLoss",
    "PerceptualLossConfig",
    "PerceptualWeightsUnavailable",
    "resolve_weights",
    "try_load_perceptual",
]

PERCEPTUAL_ENV = "METEGS_PERCEPTUAL_WEIGHTS"

DEFAULT_LAYERS = {
    "vgg16": ("relu1_2", "relu2_2", "relu3_3", "relu4_3"),
    "squeezenet1.1": ("conv1", "fire3", "fire5", "fire9"),
}
_IMAGENET_MEAN = (0.485, 0.456, 0.406)
_IMAGENET_STD = (0.229, 0.224, 0.225)
_EPS = 1e-6


def _vgg16_layer_indices() -> dict[str, int]:
    """``relu<block>_<conv>`` -> index of that ReLU in torchvision's ``vgg16().features``."""
    names: dict[str, int] = {}
    index, block, conv = 0, 1, 0
    for v in VGG16_CFG:
        if v == "M":
            index += 1
            block, conv = block + 1, 0
        else:
            conv += 1
            names[f"relu{block}_{conv}"] = index + 1
            index += 2
    return names


VGG16_LAYERS = _vgg16_layer_indices()
"""VGG16 feature layer names (``relu1_1`` .. ``relu5_3``) and their index in ``vgg16().features``."""

SQUEEZENET_GLOBS = ("squeezenet1.1*.mat", "squeezenet1_1*.mat")


class PerceptualWeightsUnavailable(WeightsUnavailable):
    """No weights for the perceptual loss were found (the reason says where it looked and how to provide them)."""

    def __init__(self, reason: str):
        self.net = "perceptual"
        self.part = "backbone"
        self.reason = reason
        Exception.__init__(self, f"perceptual loss weights unavailable: {reason}")


@dataclass
class PerceptualLossConfig(InstantiateConfig):
    """L1 on frozen pretrained features (VGG16 or SqueezeNet 1.1) at several layers and image scales."""

    _target: Callable = field(default_factory=lambda: PerceptualLoss, repr=False)
    backbone: Literal["auto", "vgg16", "squeezenet"] = "auto"
    """auto: an explicit weights file of either network, else VGG16 (the paper's) from the torch hub cache, else
    off; squeezenet: the SqueezeNet 1.1 stand-in, also searched for in the metegs weights folders."""
    weights_path: Path | None = None
    """Explicit weights file (VGG16 torchvision .pth, or SqueezeNet 1.1 .mat) or a folder holding one; also
    taken from $METEGS_PERCEPTUAL_WEIGHTS."""
    download: bool = True
    """Download the torchvision VGG16 ImageNet weights into the torch hub cache on first use, as torchvision does
    (off: the loss is switched off, with the reason, unless the weights are already there)."""
    layers: tuple[str, ...] | None = None
    """Feature layers; None: relu1_2, relu2_2, relu3_3, relu4_3 (VGG16) or conv1, fire3, fire5, fire9
    (SqueezeNet 1.1)."""
    scales: tuple[int, ...] = (1, 2)
    """Image scales as average-pooling factors (1: full resolution, 2: half)."""


# ----------------------------------------------------------------------------------------------- weights


def user_weights_dir() -> Path:
    """``$XDG_CACHE_HOME/metegs/weights`` (default ``~/.cache/metegs/weights``)."""
    return user_cache("weights")


def _vgg_cache_file() -> Path:
    return Path(torch.hub.get_dir()) / "checkpoints" / BACKBONES["vgg"].filename


def _kind_of(path: Path) -> str:
    return "squeezenet" if path.suffix.lower() == ".mat" else "vgg16"


def _first(folder: Path, patterns: tuple[str, ...]) -> Path | None:
    if not folder.is_dir():
        return None
    for pattern in patterns:
        hits = sorted(p for p in folder.glob(pattern) if p.is_file())
        if hits:
            return hits[0]
    return None


def _how_to_provide(backbone: str = "auto") -> str:
    spec = BACKBONES["vgg"]
    vgg = f"place {spec.filename} ({spec.url}) in {_vgg_cache_file().parent}"
    sqz = f"place a squeezenet1.1*.mat in {user_weights_dir()}"
    what = {
        "vgg16": "a VGG16 torchvision .pth",
        "squeezenet": "a SqueezeNet 1.1 .mat",
        "auto": "a VGG16 torchvision .pth (or a SqueezeNet 1.1 .mat as weights_path)",
    }[backbone]
    places = {
        "vgg16": f"{vgg}, or leave download on (the default) where the network can reach it",
        "squeezenet": sqz,
        "auto": f"{vgg}, or leave download on (the default) where the network can reach it (--perceptual.backbone "
        f"squeezenet: {sqz})",
    }[backbone]
    return f"provide {what} with weights_path=... or {PERCEPTUAL_ENV}=..., {places}"


def resolve_weights(config: PerceptualLossConfig) -> tuple[str, Path | None]:
    """Find the weights file (no download): ``("vgg16" | "squeezenet", path)``, or ``("vgg16", None)`` when
    only a download can provide them (``download=True``).

    Raises:
        PerceptualWeightsUnavailable: nothing found; the reason lists the places tried.
        ConfigError: the explicit file does not fit the requested backbone.
    """
    want = config.backbone
    for source, given in (("weights_path", config.weights_path), (PERCEPTUAL_ENV, os.environ.get(PERCEPTUAL_ENV))):
        if not given:
            continue
        path = Path(given).expanduser()
        if path.is_dir():
            vgg = (BACKBONES["vgg"].filename, "*.pth", "*.pt")
            sqz = (*SQUEEZENET_GLOBS, "*.mat")
            order = {"vgg16": (vgg,), "squeezenet": (sqz,), "auto": (vgg, sqz)}[want]
            found = next((f for patterns in order if (f := _first(path, patterns)) is not None), None)
            if found is None:
                raise PerceptualWeightsUnavailable(
                    f"{source}={given} is a folder holding no {'/'.join(p for o in order for p in o)} file; "
                    f"{_how_to_provide(want)}"
                )
            path = found
        elif not path.is_file():
            raise PerceptualWeightsUnavailable(f"{source}={given} does not exist; {_how_to_provide(want)}")
        kind = _kind_of(path)
        if want != "auto" and kind != want:
            raise ConfigError(f"{source}={path} is a {kind} weights file ({path.suffix}) but backbone={want!r}")
        return kind, path

    looked: list[str] = []
    if want in ("auto", "vgg16"):
        cached = _vgg_cache_file()
        if cached.is_file():
            return "vgg16", cached
        looked.append(f"VGG16 {cached}")
        if config.download:
            return "vgg16", None
    if want == "squeezenet":
        dirs = [user_weights_dir(), Path(torch.hub.get_dir()) / "checkpoints"]
        for d in dirs:
            found = _first(d, SQUEEZENET_GLOBS)
            if found is not None:
                return "squeezenet", found
        looked.append(f"SqueezeNet 1.1 squeezenet1.1*.mat in {', '.join(map(str, dirs))}")
    raise PerceptualWeightsUnavailable(f"no weights found (looked for {'; '.join(looked)}); {_how_to_provide(want)}")


def _load_vgg16(path: Path | None, backbone: str = "vgg16") -> tuple[nn.Sequential, str]:
    spec = BACKBONES["vgg"]
    if path is None:
        try:
            state = download_backbone(spec, "vgg", _how_to_provide(backbone))
        except WeightsUnavailable as e:  # offline, hash mismatch, disk full
            raise PerceptualWeightsUnavailable(e.reason) from e
        where = f"{spec.url} (cached in {_vgg_cache_file().parent})"
    else:
        try:
            state = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as e:  # corrupt / truncated / not a torch file
            raise DataError(path, f"cannot read as a VGG16 checkpoint: {type(e).__name__}: {e}") from e
        if not isinstance(state, dict):
            raise DataError(path, f"does not hold a state dict (got {type(state).__name__})")
        where = str(path)
    features = vgg16_features()
    try:
        features.load_state_dict(backbone_state(state), strict=True)
    except RuntimeError as e:
        raise DataError(path or spec.url, f"does not match torchvision's VGG16 features: {e}") from e
    return features, where


# --------------------------------------------------------------------------------------------------- loss


class _VGG16Extractor(nn.Module):
    """VGG16 features truncated after the deepest wanted layer; returns the wanted ReLU outputs."""

    def __init__(self, features: nn.Sequential, layers: tuple[str, ...]):
        super().__init__()
        self.at = {VGG16_LAYERS[name]: name for name in layers}
        self.features = features[: max(self.at) + 1]
        self.register_buffer("mean", torch.tensor(_IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(_IMAGENET_STD).view(1, 3, 1, 1), persistent=False)

    def preprocess(self, rgb01: torch.Tensor) -> torch.Tensor:
        return (rgb01 - self.mean) / self.std

    def forward(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        out = {}
        for i, module in enumerate(self.features):
            if isinstance(module, nn.MaxPool2d):
                x = max_pool_at_least_one(x, 2, 2)
            else:
                x = module(x)
            if i in self.at:
                out[self.at[i]] = x
        return out


class _SqueezeExtractor(nn.Module):
    def __init__(self, features: SqueezeNetFeatures, layers: tuple[str, ...]):
        super().__init__()
        self.features = features
        self.layers = layers

    def preprocess(self, rgb01: torch.Tensor) -> torch.Tensor:
        return SqueezeNetFeatures.preprocess(rgb01)

    def forward(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        return self.features(x, self.layers)


class PerceptualLoss(nn.Module):
    """Frozen-feature L1 loss (see the module docstring). ``PerceptualLoss(config)`` loads the weights.

    Attributes:
        backbone_name: ``"vgg16"`` or ``"squeezenet1.1"``.
        layers: the feature layers used.
        scales: the average-pooling factors.
        source: where the weights came from (file or URL).

    Raises:
        PerceptualWeightsUnavailable: no weights found (`try_load_perceptual` turns it into a reason).
        DataError: a weights file is unreadable or does not match the network.
        ConfigError: unknown layer names or bad scales.
    """

    def __init__(self, config: PerceptualLossConfig | None = None, device: str | torch.device | None = None):
        super().__init__()
        self.config = config = config or PerceptualLossConfig()
        if not config.scales or any(int(s) != s or s < 1 for s in config.scales):
            raise ConfigError(f"perceptual.scales must be positive integers, got {config.scales!r}")
        kind, path = resolve_weights(config)
        features = None
        if kind == "vgg16" and path is None:  # only a download can provide VGG16
            features, source = _load_vgg16(None, config.backbone)
        if kind == "vgg16":
            self.backbone_name = "vgg16"
            layers = self._check_layers(config.layers, tuple(VGG16_LAYERS))
            if features is None:
                features, source = _load_vgg16(path)
            self.source = source
            self.extractor: nn.Module = _VGG16Extractor(features, layers)
        else:
            self.backbone_name = "squeezenet1.1"
            layers = self._check_layers(config.layers, SQUEEZENET_LAYERS)
            self.extractor = _SqueezeExtractor(load_squeezenet_mat(path), layers)
            self.source = str(path)
        self.layers = layers
        self.scales = tuple(int(s) for s in config.scales)
        self.requires_grad_(False)
        self.eval()
        if device is not None:
            self.to(device)

    def _check_layers(self, layers: tuple[str, ...] | None, valid: tuple[str, ...]) -> tuple[str, ...]:
        layers = tuple(layers) if layers else DEFAULT_LAYERS[self.backbone_name]
        bad = [name for name in layers if name not in valid]
        if bad:
            raise ConfigError(f"perceptual.layers {bad} are not {self.backbone_name} layers; valid: {', '.join(valid)}")
        return layers

    def train(self, mode: bool = True) -> PerceptualLoss:
        """The backbone stays in eval mode whatever the caller asks (it is frozen)."""
        return super().train(False)

    def _nchw(self, image: torch.Tensor) -> torch.Tensor:
        dtype = next(self.extractor.parameters()).dtype
        h, w = image.shape[-3:-1]
        return image.reshape(-1, h, w, 3).permute(0, 3, 1, 2).to(dtype)

    def _features(self, image: torch.Tensor) -> list[dict[str, torch.Tensor]]:
        """Features of a channels-last image at every scale (one dict of layers per scale)."""
        x = self.extractor.preprocess(self._nchw(image))
        out = []
        for s in self.scales:
            try:
                out.append(self.extractor(F.avg_pool2d(x, s) if s > 1 else x))
            except RuntimeError as e:
                raise ValueError(
                    f"perceptual loss ({self.backbone_name}): image of size {tuple(image.shape[-3:-1])} "
                    f"at scale 1/{s} is too small for layers {self.layers} ({e})"
                ) from e
        return out

    @torch.no_grad()
    def target_features(self, target: torch.Tensor) -> list[dict[str, torch.Tensor]]:
        """Features of a fixed reference image [..., H, W, 3], to reuse across calls of `forward`."""
        return self._features(target.detach())

    def forward(
        self,
        pred: torch.Tensor,
        target: torch.Tensor | None = None,
        *,
        target_features: list[dict[str, torch.Tensor]] | None = None,
    ) -> torch.Tensor:
        """Scalar loss between channels-last images ``[..., H, W, 3]`` in [0, 1] (gradients flow to ``pred``);
        ``target_features`` (from `target_features`) replaces ``target`` when the reference repeats."""
        if target_features is None:
            if target is None or pred.shape != target.shape or pred.ndim < 3 or pred.shape[-1] != 3:
                shape = None if target is None else tuple(target.shape)
                raise ValueError(f"expected two [..., H, W, 3] images of equal shape, got {tuple(pred.shape)}, {shape}")
            target_features = self.target_features(target)
        total = pred.new_zeros((), dtype=next(self.extractor.parameters()).dtype)
        for fx, fy in zip(self._features(pred), target_features, strict=True):
            for name in self.layers:
                norm = fy[name].abs().mean().clamp_min(_EPS)
                total = total + (fx[name] - fy[name]).abs().mean() / norm
        return total / (len(self.layers) * len(self.scales))


def try_load_perceptual(
    config: PerceptualLossConfig, device: str | torch.device | None = None
) -> tuple[PerceptualLoss | None, str | None]:
    """``(loss, None)``, or ``(None, reason)`` when no weights are found (never raises for missing weights).

    A weights file that exists but is broken still raises `DataError` naming it; a bad config raises
    `ConfigError`.
    """
    try:
        return PerceptualLoss(config, device), None
    except PerceptualWeightsUnavailable as e:
        return None, str(e)
