"""ImageNet backbones shared by the LPIPS metric (`metegs.eval.lpips`) and the perceptual loss
(`metegs.losses.perceptual`): AlexNet and VGG16 feature extractors with torchvision's layers and state-dict keys,
and their torchvision weights, found on disk or downloaded into the torch hub cache as torchvision does.

A weight file is looked up, in order: a path the caller gives (a file, or a folder holding the torchvision file
name), the ``METEGS_LPIPS_BACKBONE`` environment variable, then ``torch.hub.get_dir()/checkpoints/<file>``
(``alexnet-owt-7be5be79.pth`` / ``vgg16-397923af.pth``). Found nowhere, `download_backbone` fetches it into that
cache; a download that fails (offline) is tried once per process and gives the reason. Weights are never
replaced by a substitute: missing or wrong ones raise `WeightsUnavailable`.
"""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn

from metegs.errors import MetegsError

BACKBONE_ENV = "METEGS_LPIPS_BACKBONE"
"""A torchvision backbone checkpoint (or a folder holding it) to use instead of the torch hub cache's."""


class WeightsUnavailable(MetegsError):
    """Weights (a backbone, or LPIPS's linear heads) cannot be found or loaded.

    Attributes:
        net: ``"alex"`` or ``"vgg"``.
        part: ``"backbone"`` or ``"heads"``.
        reason: human-readable explanation, including where the file was looked for and how to provide it.
    """

    def __init__(self, net: str, part: str, reason: str):
        self.net = net
        self.part = part
        self.reason = reason
        super().__init__(f"LPIPS-{net} {part} weights unavailable: {reason}")


def alexnet_features() -> nn.Sequential:
    """AlexNet feature extractor, layer-for-layer identical to torchvision ``alexnet().features``.

    Input ``[N, 3, H, W]``; state-dict keys ``{0,3,6,8,10}.{weight,bias}``.
    """
    return nn.Sequential(
        nn.Conv2d(3, 64, kernel_size=11, stride=4, padding=2),
        nn.ReLU(),
        nn.MaxPool2d(kernel_size=3, stride=2),
        nn.Conv2d(64, 192, kernel_size=5, padding=2),
        nn.ReLU(),
        nn.MaxPool2d(kernel_size=3, stride=2),
        nn.Conv2d(192, 384, kernel_size=3, padding=1),
        nn.ReLU(),
        nn.Conv2d(384, 256, kernel_size=3, padding=1),
        nn.ReLU(),
        nn.Conv2d(256, 256, kernel_size=3, padding=1),
        nn.ReLU(),
        nn.MaxPool2d(kernel_size=3, stride=2),
    )


VGG16_CFG = (64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512, "M")
"""VGG16's feature layers: convolution widths, ``M`` for a 2×2 max pool."""


def vgg16_features() -> nn.Sequential:
    """VGG16 (no batch norm) feature extractor, identical to torchvision ``vgg16().features`` (31 modules).

    Input ``[N, 3, H, W]``; state-dict keys ``{0,2,5,7,10,...,28}.{weight,bias}``.
    """
    layers: list[nn.Module] = []
    in_ch = 3
    for v in VGG16_CFG:
        if v == "M":
            layers.append(nn.MaxPool2d(kernel_size=2, stride=2))
        else:
            layers += [nn.Conv2d(in_ch, int(v), kernel_size=3, padding=1), nn.ReLU()]
            in_ch = int(v)
    return nn.Sequential(*layers)


@dataclass(frozen=True)
class BackboneSpec:
    """A backbone and its torchvision checkpoint."""

    filename: str
    """File name of the checkpoint in the torch hub cache."""
    url: str
    """Where torchvision downloads it from."""
    build: Callable[[], nn.Sequential]
    """The feature extractor, without weights."""
    slice_ends: tuple[int, ...]
    """Exclusive end index (into the Sequential) of each of the 5 LPIPS slices, as the official package."""
    channels: tuple[int, ...]
    """Channels of those 5 feature maps."""


BACKBONES: dict[str, BackboneSpec] = {
    "alex": BackboneSpec(
        "alexnet-owt-7be5be79.pth",
        "https://download.pytorch.org/models/alexnet-owt-7be5be79.pth",
        alexnet_features,
        (2, 5, 8, 10, 12),
        (64, 192, 384, 256, 256),
    ),
    "vgg": BackboneSpec(
        "vgg16-397923af.pth",
        "https://download.pytorch.org/models/vgg16-397923af.pth",
        vgg16_features,
        (4, 9, 16, 23, 30),
        (64, 128, 256, 512, 512),
    ),
}
"""The backbones by LPIPS net name."""


def backbone_spec(net: str) -> BackboneSpec:
    """The `BackboneSpec` of ``net`` (``alex`` or ``vgg``); ValueError for another name."""
    if net not in BACKBONES:
        raise ValueError(f"LPIPS net must be one of {sorted(BACKBONES)}, got {net!r}")
    return BACKBONES[net]


def how_to_provide_backbone(spec: BackboneSpec) -> str:
    """Where to put ``spec``'s checkpoint, for an error message."""
    cache = Path(torch.hub.get_dir()) / "checkpoints" / spec.filename
    return (
        f"provide the torchvision checkpoint {spec.filename} ({spec.url}) by placing it at {cache}, "
        f"passing backbone_path=..., or setting {BACKBONE_ENV}=/path/to/{spec.filename}"
    )


def file_in(path: Path, names: list[str]) -> Path | None:
    """``path`` itself if it is a file, else the first existing ``path / name``."""
    if path.is_file():
        return path
    if path.is_dir():
        for name in names:
            if (path / name).is_file():
                return path / name
    return None


def resolve_backbone_file(net: str = "alex", backbone_path: str | Path | None = None) -> Path:
    """Find the torchvision backbone checkpoint on disk (no download).

    Order: ``backbone_path`` (file, or folder holding the torchvision file name), ``$METEGS_LPIPS_BACKBONE``,
    ``torch.hub.get_dir()/checkpoints/<file>``.

    Raises:
        WeightsUnavailable: not found; the message lists the places tried and how to provide the file.
    """
    spec = backbone_spec(net)
    for source, given in (("backbone_path", backbone_path), (BACKBONE_ENV, os.environ.get(BACKBONE_ENV))):
        if given:
            found = file_in(Path(given).expanduser(), [spec.filename])
            if found is None:
                raise WeightsUnavailable(
                    net,
                    "backbone",
                    f"{source}={given} is not {spec.filename} nor a folder holding it; {how_to_provide_backbone(spec)}",
                )
            return found
    cached = Path(torch.hub.get_dir()) / "checkpoints" / spec.filename
    if cached.is_file():
        return cached
    raise WeightsUnavailable(
        net,
        "backbone",
        f"{spec.filename} not found in the torch hub cache ({cached.parent}); {how_to_provide_backbone(spec)}",
    )


def read_state_dict(path: Path, net: str, part: str) -> Mapping[str, torch.Tensor]:
    """The state dict in ``path`` (tensors only: no code in the file runs); `WeightsUnavailable` if unreadable."""
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - corrupt / truncated / not a torch file
        raise WeightsUnavailable(net, part, f"cannot read {path}: {type(e).__name__}: {e}") from e
    if not isinstance(state, Mapping):
        raise WeightsUnavailable(net, part, f"{path} does not hold a state dict (got {type(state).__name__})")
    return state


def backbone_state(state: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Features-only keys from a torchvision full-model or features-only state dict."""
    if "state_dict" in state and isinstance(state["state_dict"], Mapping):
        state = state["state_dict"]
    if any(k.startswith("features.") for k in state):
        return {k[len("features.") :]: v for k, v in state.items() if k.startswith("features.")}
    return dict(state)


FAILED_DOWNLOADS: dict[str, str] = {}
"""Why each URL could not be downloaded in this process: it is not tried again (one message, no retries)."""


def download_backbone(spec: BackboneSpec, net: str, how: str | None = None) -> Mapping[str, torch.Tensor]:
    """The backbone's torchvision state dict, downloaded into the torch hub cache; a failure (remembered for the
    process) raises `WeightsUnavailable` ending with ``how`` to provide the file (default: where to put it)."""
    if spec.url not in FAILED_DOWNLOADS:
        try:  # torch.hub announces the download on stdout: keep it beside the progress bar, off JSON printed there
            with contextlib.redirect_stdout(sys.stderr):
                return torch.hub.load_state_dict_from_url(
                    spec.url, map_location="cpu", progress=True, check_hash=True, weights_only=True
                )
        except Exception as e:  # noqa: BLE001 - offline (URLError), hash mismatch, disk full...
            FAILED_DOWNLOADS[spec.url] = f"{type(e).__name__}: {e}"
            # the announcement above reads like a download that worked: say at once that it did not
            print(f"Download failed: {spec.url} ({FAILED_DOWNLOADS[spec.url]})", file=sys.stderr)
    raise WeightsUnavailable(
        net,
        "backbone",
        f"{spec.filename} is not in the torch hub cache and its download from {spec.url} failed "
        f"({FAILED_DOWNLOADS[spec.url]}); {how or how_to_provide_backbone(spec)}",
    )
