"""The `cpu` rasteriser: tile compositing (forward and backward) as a compiled C++ kernel.

Projection, SH and tile binning are the torch reference code (autograd); only the compositing runs
in ``csrc/composite.cpp`` through `CompositeTiles`, a `torch.autograd.Function` with a hand-written
backward. The extension is compiled with `torch.utils.cpp_extension` on first use (about a minute)
and cached in ``~/.cache/metegs/torch_extensions/<torch version>/<cpu tag>/`` (``$XDG_CACHE_HOME``
is honoured, ``METEGS_EXTENSIONS_DIR`` overrides the whole path); later processes only load it.
When it cannot be built, `CpuRasterizer.available` is False (with one warning saying why), so
``backend=auto`` falls back to ``torch``, and `CpuRasterizer.render` raises `CpuExtensionError`.
"""

from __future__ import annotations

import hashlib
import os
import platform
import sys
import threading
import warnings
from pathlib import Path
from typing import Any

import torch
from torch.autograd.function import once_differentiable

from metegs.cameras import Cameras
from metegs.errors import MetegsError
from metegs.gaussians.model import GaussianSet
from metegs.render.base import RenderOutput, RenderSettings
from metegs.render.pipeline import rasterize
from metegs.render.tiles import TileBins

SOURCE = Path(__file__).parent / "csrc" / "composite.cpp"
_TORCH_TAG = "".join(ch if ch.isalnum() else "_" for ch in torch.__version__)
EXTENSION_NAME = f"metegs_cpu_composite_{_TORCH_TAG}"

# -march=native: the kernel's inner loops are written for SIMD (AVX2/AVX-512 here). The binary is
# built on, and cached for, the machine that runs it; the cache folder also carries a tag of the
# CPU model/flags so that a home directory shared between different machines does not load a
# binary built for another CPU. -mprefer-vector-width=512 lets GCC use zmm registers where the CPU
# has AVX-512 (about 1.4x on the Zen 5 CI machine; ignored elsewhere). -ffp-contract=off keeps
# forward and backward alphas bit-identical (see the .cpp); -fno-trapping-math lets GCC if-convert
# (vectorise) the pixel loops (no FP exceptions are used). -fopenmp-simd enables `#pragma omp simd`
# only: threads come from torch's own pool (at::parallel_for), so no second OpenMP runtime is linked.
CFLAGS = [
    "-O3", "-march=native", "-mprefer-vector-width=512", "-ffp-contract=off", "-fno-trapping-math", "-fopenmp-simd",
]


class CpuExtensionError(MetegsError, RuntimeError):
    """The C++ compositing extension of the ``cpu`` rasteriser could not be built or loaded."""


class CpuBackendWarning(UserWarning):
    """The ``cpu`` rasteriser is unavailable; ``auto`` uses ``torch`` instead."""


_lock = threading.Lock()
_state: dict[str, Any] = {"ext": None, "error": None, "warned": False, "announced": False}


def _cpu_tag() -> str:
    """Short tag of the machine architecture and CPU model/flags (the binary is built with -march=native)."""
    info = platform.machine()
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as f:
            lines = [ln for ln in f if ln.startswith(("model name", "flags", "Features", "CPU part"))]
        info += "".join(sorted(set(lines)))
    except OSError:
        info += platform.processor()
    return f"{platform.machine()}-{hashlib.sha1(info.encode()).hexdigest()[:10]}"


def build_directory() -> Path:
    """Where the extension is built and cached (one folder per torch version and CPU)."""
    override = os.environ.get("METEGS_EXTENSIONS_DIR")
    if override:
        return Path(override).expanduser()
    cache = Path(os.environ.get("XDG_CACHE_HOME") or "~/.cache").expanduser()
    return cache / "metegs" / "torch_extensions" / _TORCH_TAG / _cpu_tag()


def _tail(text: str, lines: int = 25) -> str:
    return "\n".join(text.strip().splitlines()[-lines:])


def load_extension():
    """The compiled compositing module (built on first use; raises `CpuExtensionError` if impossible)."""
    if _state["ext"] is not None:
        return _state["ext"]
    with _lock:
        if _state["ext"] is not None:
            return _state["ext"]
        if _state["error"] is not None:
            raise CpuExtensionError(_state["error"])
        try:
            _state["ext"] = _build()
        except Exception as exc:  # noqa: BLE001 - any failure means "not available", with the reason kept
            reason = exc.args[0] if isinstance(exc, CpuExtensionError) else f"{type(exc).__name__}: {_tail(str(exc))}"
            _state["error"] = f"cannot build the metegs CPU rasteriser extension ({SOURCE.name}): {reason}"
            raise CpuExtensionError(_state["error"]) from exc
    return _state["ext"]


def _build():
    from torch.utils import cpp_extension

    if not SOURCE.is_file():
        raise CpuExtensionError(f"source file {SOURCE} is missing from the installation")
    try:
        cpp_extension.verify_ninja_availability()
    except RuntimeError as exc:
        raise CpuExtensionError("the `ninja` build tool is required (pip install ninja)") from exc
    build_dir = build_directory()
    build_dir.mkdir(parents=True, exist_ok=True)
    built, ninja_file = build_dir / f"{EXTENSION_NAME}.so", build_dir / "build.ninja"
    stale = (
        not built.exists()
        or built.stat().st_mtime < SOURCE.stat().st_mtime
        or not ninja_file.exists()
        or " ".join(CFLAGS) not in ninja_file.read_text(errors="replace")
    )
    if stale and not _state["announced"]:
        _state["announced"] = True
        print(f"compiling the metegs CPU rasteriser (first use, ~1 min) in {build_dir} ...",
              file=sys.stderr, flush=True)
    return cpp_extension.load(
        name=EXTENSION_NAME,
        sources=[str(SOURCE)],
        extra_cflags=CFLAGS,
        build_directory=str(build_dir),
        verbose=False,
    )


class CompositeTiles(torch.autograd.Function):
    """Differentiable tile compositing; same inputs/outputs as `torch_backend.composite_tiles`."""

    @staticmethod
    def forward(ctx, means2d, conics, opacities, colors, depths, gaussian_ids, offsets,
                tiles_x, tiles_y, width, height):
        ext = load_extension()
        color, alpha, depth, t_final, last = ext.forward(
            means2d, conics, opacities, colors, depths, gaussian_ids, offsets, tiles_x, tiles_y, width, height
        )
        ctx.save_for_backward(means2d, conics, opacities, colors, depths, gaussian_ids, offsets, t_final, last)
        ctx.dims = (tiles_x, tiles_y, width, height)
        return color, alpha, depth

    @staticmethod
    @once_differentiable
    def backward(ctx, g_color, g_alpha, g_depth):
        means2d, conics, opacities, colors, depths, ids, offsets, t_final, last = ctx.saved_tensors
        tiles_x, tiles_y, width, height = ctx.dims
        grads = load_extension().backward(
            means2d, conics, opacities, colors, depths, ids, offsets, t_final, last,
            g_color, g_alpha, g_depth, tiles_x, tiles_y, width, height,
        )  # [N, 7 + D]: mx, my, conic a, b, c, opacity, depth, colour...
        out = (grads[:, 0:2], grads[:, 2:5], grads[:, 5], grads[:, 7:], grads[:, 6])
        out = tuple(g.contiguous() if need else None for g, need in zip(out, ctx.needs_input_grad, strict=False))
        return (*out, None, None, None, None, None, None)


def composite_tiles_cpu(
    means2d: torch.Tensor,
    conics: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    depths: torch.Tensor,
    bins: TileBins,
    width: int,
    height: int,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Compiled equivalent of `torch_backend.composite_tiles`: -> (color [H, W, D], alpha [H, W], depth_sum [H, W])."""
    return CompositeTiles.apply(
        means2d, conics, opacities, colors, depths, bins.gaussian_ids, bins.offsets,
        bins.tiles_x, bins.tiles_y, int(width), int(height),
    )


class CpuRasterizer:
    """Tile rasteriser with compiled C++ compositing (CPU tensors, float32 or float64)."""

    name = "cpu"

    @staticmethod
    def available(device: torch.device | str = "cpu") -> bool:
        """True on a CPU device once the extension builds/loads (the answer is cached; warns once if not)."""
        if torch.device(device).type != "cpu":
            return False
        try:
            load_extension()
        except CpuExtensionError as exc:
            if not _state["warned"]:
                _state["warned"] = True
                warnings.warn(f"{exc}; the `torch` rasteriser is used instead", CpuBackendWarning, stacklevel=2)
            return False
        return True

    def render(self, gaussians: GaussianSet, camera: Cameras, settings: RenderSettings | None = None) -> RenderOutput:
        """Render one view. camera: a single view (len 1)."""
        if gaussians.means.device.type != "cpu":
            raise CpuExtensionError(f"the `cpu` rasteriser needs CPU tensors, got {gaussians.means.device}")
        return rasterize(gaussians, camera, settings, composite_tiles_cpu)
