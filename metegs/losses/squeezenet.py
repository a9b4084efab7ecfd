"""SqueezeNet 1.1 feature layers (conv1 + fire2..fire9) and their loader from a MATLAB ``.mat`` file.

The architecture is that of the Caffe release (DeepScale SqueezeNet v1.1), which torchvision's
``squeezenet1_1().features`` also follows:

    conv1 (3->64, 3x3, stride 2, no padding) + ReLU            -> "conv1"   (1/2 resolution)
    max-pool 3x3 / 2 (ceil mode)
    fire2 (16 -> 64 + 64), fire3 (16 -> 64 + 64)                -> "fire2", "fire3"  (1/4)
    max-pool 3x3 / 2 (ceil mode)
    fire4 (32 -> 128 + 128), fire5 (32 -> 128 + 128)            -> "fire4", "fire5"  (1/8)
    max-pool 3x3 / 2 (ceil mode)
    fire6, fire7 (48 -> 192 + 192), fire8, fire9 (64 -> 256 + 256)  -> "fire6".."fire9"  (1/16)

A fire module is ``s = ReLU(squeeze1x1(x))``, output ``cat(ReLU(expand1x1(s)), ReLU(expand3x3(s)))`` (the
3x3 expand padded by 1), in that channel order. A pooling window larger than the map it pools (images
too small for the deep layers) shrinks to the map, so small images still give every layer.

The ``.mat`` file (e.g. ``sqz_notop.mat`` converted from the Caffe model through keras-squeezenet) holds one
entry per convolution, named ``conv1``, ``fire<k>/squeeze1x1``, ``fire<k>/expand1x1``, ``fire<k>/expand3x3``,
each a pair ``[kernel, bias]`` with the kernel in TensorFlow's HWIO layout (converted here to PyTorch's
OIHW; both are cross-correlations, so no flip) and the bias ``[1, C_out]``.

Input preprocessing is that of the Caffe model the weights come from: pixel values 0-255 in **BGR**
order minus the per-channel mean ``[104.006, 116.669, 122.679]`` (B, G, R), as documented by the
keras-squeezenet conversion the file derives from (the hosting repository feeds RGB minus the same means
listed in RGB order; the two differ only in the channel order, which has not been verified independently).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from metegs.errors import DataError

__all__ = ["SQUEEZENET_LAYERS", "SqueezeNetFeatures", "load_squeezenet_mat", "max_pool_at_least_one"]

SQUEEZENET_LAYERS = ("conv1", "fire2", "fire3", "fire4", "fire5", "fire6", "fire7", "fire8", "fire9")
"""Names of the feature maps `SqueezeNetFeatures` can return, shallow to deep."""

# (name, in_channels, squeeze, expand) of each fire module
_FIRES = (
    ("fire2", 64, 16, 64),
    ("fire3", 128, 16, 64),
    ("fire4", 128, 32, 128),
    ("fire5", 256, 32, 128),
    ("fire6", 256, 48, 192),
    ("fire7", 384, 48, 192),
    ("fire8", 384, 64, 256),
    ("fire9", 512, 64, 256),
)
_POOL_AFTER = ("conv1", "fire3", "fire5")
"""A 3x3 / 2 ceil-mode max pool follows these layers."""

BGR_MEAN_255 = (104.006, 116.669, 122.679)
"""Per-channel mean (B, G, R) of the Caffe model, on 0-255 pixel values."""


class Fire(nn.Module):
    """SqueezeNet fire module: squeeze 1x1, then expand 1x1 and 3x3 concatenated (all ReLU)."""

    def __init__(self, in_channels: int, squeeze: int, expand: int):
        super().__init__()
        self.squeeze1x1 = nn.Conv2d(in_channels, squeeze, kernel_size=1)
        self.expand1x1 = nn.Conv2d(squeeze, expand, kernel_size=1)
        self.expand3x3 = nn.Conv2d(squeeze, expand, kernel_size=3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        s = F.relu(self.squeeze1x1(x))
        return torch.cat([F.relu(self.expand1x1(s)), F.relu(self.expand3x3(s))], dim=1)


class SqueezeNetFeatures(nn.Module):
    """SqueezeNet 1.1 feature layers; ``forward(x, layers)`` returns the requested feature maps.

    Input ``[N, 3, H, W]`` already preprocessed (see `preprocess`). Parameter names follow the ``.mat``
    entries with ``/`` replaced by ``.`` (``conv1.weight``, ``fire2.squeeze1x1.weight``, ...).
    """

    def __init__(self):
        super().__init__()
        self.conv1 = nn.Conv2d(3, 64, kernel_size=3, stride=2)
        for name, cin, sq, ex in _FIRES:
            self.add_module(name, Fire(cin, sq, ex))

    @staticmethod
    def preprocess(rgb01: torch.Tensor) -> torch.Tensor:
        """``[N, 3, H, W]`` RGB in [0, 1] -> BGR 0-255 minus the Caffe mean."""
        mean = torch.tensor(BGR_MEAN_255, dtype=rgb01.dtype, device=rgb01.device).view(1, 3, 1, 1)
        return rgb01.flip(1) * 255.0 - mean

    def forward(self, x: torch.Tensor, layers: tuple[str, ...] = SQUEEZENET_LAYERS) -> dict[str, torch.Tensor]:
        wanted = set(layers)
        last = max(SQUEEZENET_LAYERS.index(name) for name in wanted)
        out: dict[str, torch.Tensor] = {}
        for i, name in enumerate(SQUEEZENET_LAYERS[: last + 1]):
            x = F.relu(self.conv1(x)) if i == 0 else getattr(self, name)(x)
            if name in wanted:
                out[name] = x
            if name in _POOL_AFTER and i < last:
                x = max_pool_at_least_one(x, 3, 2, ceil_mode=True)
        return out


def max_pool_at_least_one(x: torch.Tensor, kernel: int, stride: int, ceil_mode: bool = False) -> torch.Tensor:
    """Max pooling whose window shrinks to the map where the map is smaller than the window (a map of 1 or 2
    pixels then pools to 1 pixel instead of failing); identical to ``F.max_pool2d`` otherwise."""
    kh, kw = min(kernel, x.shape[-2]), min(kernel, x.shape[-1])
    return F.max_pool2d(x, kernel_size=(kh, kw), stride=stride, ceil_mode=ceil_mode)


def _mat_entries() -> list[str]:
    names = ["conv1"]
    for fire, *_ in _FIRES:
        names += [f"{fire}/squeeze1x1", f"{fire}/expand1x1", f"{fire}/expand3x3"]
    return names


def load_squeezenet_mat(path: str | Path) -> SqueezeNetFeatures:
    """Build `SqueezeNetFeatures` with the weights of a SqueezeNet 1.1 ``.mat`` file (HWIO kernels).

    Raises:
        DataError: the file cannot be read as a ``.mat``, or a layer is missing or has the wrong shape (the
            message names the file and the layer).
    """
    from scipy.io import loadmat

    path = Path(path)
    try:
        mat = loadmat(str(path))
    except Exception as e:  # truncated, not a .mat, unreadable
        raise DataError(
            path, f"cannot read as a MATLAB .mat file of SqueezeNet 1.1 weights: {type(e).__name__}: {e}"
        ) from e
    model = SqueezeNetFeatures()
    modules = dict(model.named_modules())
    state: dict[str, torch.Tensor] = {}
    for entry in _mat_entries():
        if entry not in mat:
            raise DataError(path, f"layer {entry!r} missing (SqueezeNet 1.1 weights need {', '.join(_mat_entries())})")
        try:
            kernel, bias = (np.asarray(v, dtype=np.float32) for v in np.asarray(mat[entry], dtype=object).ravel())
        except (ValueError, TypeError) as e:
            raise DataError(path, f"layer {entry!r} is not a [kernel, bias] pair ({e})") from e
        conv = modules[entry.replace("/", ".")]
        o, i, kh, kw = conv.weight.shape
        if kernel.shape != (kh, kw, i, o) or bias.size != o:
            raise DataError(
                path,
                f"layer {entry!r} has kernel {kernel.shape} and bias {bias.shape}; SqueezeNet 1.1 "
                f"needs kernel {(kh, kw, i, o)} (HWIO) and {o} biases",
            )
        key = entry.replace("/", ".")
        state[f"{key}.weight"] = torch.from_numpy(np.ascontiguousarray(kernel.transpose(3, 2, 0, 1)))
        state[f"{key}.bias"] = torch.from_numpy(bias.reshape(o).copy())
    model.load_state_dict(state, strict=True)
    return model
