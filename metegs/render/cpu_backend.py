"""The `cpu` rasteriser: every stage of a render as compiled C++ with hand-written backward passes.

Three ops, each the equivalent of a torch reference stage (and tested against it):
``csrc/project.cpp`` (EWA projection + SH colours, `ProjectShade`; reference: `project_gaussians` and
`gaussian_colors`), ``csrc/binning.cpp`` (depth-sorted tile lists with an exact ellipse-tile test;
reference: `bin_gaussians`) and ``csrc/composite.cpp`` (tile compositing, `CompositeTiles`; reference:
`torch_backend.composite_tiles`); beside them ``csrc/ssim.cpp``, the training loss's SSIM map with its backward
(`metegs.losses.fused_ssim`), and ``csrc/opening.cpp``, the bright strokes of `metegs.losses.robust.without_bright_strokes`
taken out with its backward (`metegs.losses.fused_opening`). The extension is compiled with `torch.utils.cpp_extension` on first use (about 50 s on 2 cores)
and cached in ``~/.cache/metegs/torch_extensions/<torch version>/<cpu tag>/`` (``$XDG_CACHE_HOME``
is honoured, ``METEGS_EXTENSIONS_DIR`` overrides the whole path); later processes only load it. x86 intrinsics are
used only where the compiler targets them, and never with ``METEGS_CPU_PORTABLE=1`` (`machine_cflags`).
When it cannot be built, `CpuRasterizer.available` is False (with one warning saying why), so
``backend=auto`` falls back to ``torch``, and `CpuRasterizer.render` raises `CpuExtensionError`.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import platform
import re
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import torch
from torch.autograd.function import once_differentiable

from metegs.cameras import Cameras
from metegs.config import user_cache
from metegs.errors import MetegsError
from metegs.files import atomic_write_bytes
from metegs.gaussians.model import GaussianSet
from metegs.render.base import RenderOutput, RenderSettings
from metegs.render.build_lock import build_lock
from metegs.render.optional import OptionalComponent
from metegs.render.pipeline import finish_render, resolve_sh_degree
from metegs.render.tiles import TILE_SIZE, TileBins

CSRC = Path(__file__).parent / "csrc"
SOURCES = [
    CSRC / name for name in ("bindings.cpp", "project.cpp", "binning.cpp", "composite.cpp", "ssim.cpp", "opening.cpp")
]
HEADERS = [CSRC / "metegs_cpu.h", CSRC / "pool.h"]
_TORCH_TAG = "".join(ch if ch.isalnum() else "_" for ch in torch.__version__)
EXTENSION_NAME = f"metegs_cpu_composite_{_TORCH_TAG}"

# -march=native (x86) / -mcpu=native (ARM): the compositing kernels work on 16-pixel tile rows as GCC vector types,
# which become AVX-512 instructions here, or (csrc/metegs_cpu.h's Split) pairs of AVX2 or quads of SSE / NEON ones. The binary is built on, and cached for, the machine that runs
# it; the cache folder also carries a tag of the CPU model/flags so that a home directory shared between different
# machines does not load a binary built for another CPU. -mprefer-vector-width=512 lets GCC use zmm registers where
# the CPU has AVX-512. -ffp-contract=off keeps forward and backward alphas bit-identical (see composite.cpp);
# -fno-trapping-math lets GCC if-convert (vectorise) the loops of the other kernels (no FP exceptions are used). The
# kernels run on metegs' own pool (csrc/pool.h), or, called from the main thread with torch's thread count, on
# torch's own OpenMP team: hence -fopenmp where torch runs on GNU OpenMP (`openmp_flags`).
PORTABLE_ENV = "METEGS_CPU_PORTABLE"
"""Set to 1 to build the kernels without x86 intrinsics or the machine's own instruction set (-DMETEGS_PORTABLE: the
generic code that ARM machines compile), in a cache folder of its own; the test suite builds this variant too."""


def machine_cflags(portable: bool | None = None) -> list[str]:
    """Compiler flags of the kernels for this machine's architecture (``portable``: default from `PORTABLE_ENV`)."""
    if portable is None:
        portable = os.environ.get(PORTABLE_ENV, "") not in ("", "0")
    common = ["-ffp-contract=off", "-fno-trapping-math"]
    machine = platform.machine().lower()
    if portable:
        return ["-O3", *common, "-DMETEGS_PORTABLE"]
    if machine in ("x86_64", "amd64"):
        return ["-O3", "-march=native", "-mprefer-vector-width=512", *common]
    if machine in ("aarch64", "arm64"):
        return ["-O3", "-mcpu=native", *common]
    return ["-O3", *common]


class CpuExtensionError(MetegsError, RuntimeError):
    """The C++ compositing extension of the ``cpu`` rasteriser could not be built or loaded."""


class CpuBackendWarning(UserWarning):
    """The ``cpu`` rasteriser is unavailable; ``auto`` uses ``torch`` instead."""


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


def source_digest(cflags: list[str]) -> str:
    """Short hash of what the built extension depends on: the kernel sources' names and bytes, the compiler flags,
    Python's and torch's versions."""
    h = hashlib.sha1()
    for f in SOURCES + HEADERS:
        h.update(f.name.encode() + b"\0" + f.read_bytes() + b"\0")
    h.update(" ".join([*cflags, platform.python_version(), torch.__version__]).encode())
    return h.hexdigest()[:12]


def build_directory(cflags: list[str] | None = None) -> Path:
    """Where the extension is built and cached: one folder per CPU and `source_digest`, so that two checkouts or
    installs with the same kernels share one build and different kernels never rebuild each other's
    (``METEGS_EXTENSIONS_DIR`` overrides it)."""
    override = os.environ.get("METEGS_EXTENSIONS_DIR")
    if override:
        return Path(override).expanduser()
    digest = source_digest(compile_flags()[0] if cflags is None else cflags)
    return user_cache("torch_extensions", _TORCH_TAG, f"{_cpu_tag()}-{digest}")


def stage_sources(build_dir: Path, sources: list[Path] | None = None) -> tuple[Path, bool]:
    """(folder, changed): copies of the sources (default: the kernels', `SOURCES`) and `HEADERS` in ``build_dir/src``,
    rewritten where their bytes differ from the installation's. The build reads these copies, so its ninja file
    names no checkout's path."""
    folder = Path(build_dir) / "src"
    folder.mkdir(parents=True, exist_ok=True)
    changed = False
    for f in (SOURCES if sources is None else sources) + HEADERS:
        data, copy = f.read_bytes(), folder / f.name
        if not copy.is_file() or copy.read_bytes() != data:
            atomic_write_bytes(copy, data)
            changed = True
    return folder, changed


OPENMP_RUNTIME = re.compile(r"lib(g|i)?omp[\d.-]")
"""File names of OpenMP runtimes: libgomp.so.1, libgomp-<hash>.so.1, libiomp5.so, libomp.so."""


def openmp_flags() -> list[str]:
    """["-fopenmp"] where torch runs its ops on GNU OpenMP as ``libgomp.so.1`` (Linux), the runtime a GCC ``-fopenmp``
    build links, so that the extension's OpenMP regions run on torch's team; else [] (the kernels then always use
    metegs' pool). Decided from torch's installation, not from what else the process has loaded (pycolmap brings
    its own, renamed libgomp), so that every process builds the cached extension with the same flags."""
    if sys.platform != "linux" or "parallel backend: OpenMP" not in torch.__config__.parallel_info():
        return []
    torch_lib = Path(torch.__file__).parent / "lib"
    bundled = {f.name for f in torch_lib.glob("*.so*") if OPENMP_RUNTIME.match(f.name)}
    if bundled:  # a wheel's own runtime: it is ours to share only under the name GCC links
        return ["-fopenmp"] if "libgomp.so.1" in bundled else []
    try:  # torch uses a runtime from elsewhere (conda, a system build): the GNU one if it is loaded
        with open("/proc/self/maps", encoding="utf-8", errors="replace") as f:
            loaded = {Path(line.split()[-1]).name for line in f if "/" in line}
    except OSError:
        return []
    return ["-fopenmp"] if "libgomp.so.1" in loaded else []


def compile_flags() -> tuple[list[str], list[str]]:
    """(compiler flags, linker flags) of the extension on this machine: `machine_cflags` plus `openmp_flags`."""
    openmp = openmp_flags()
    return machine_cflags() + openmp, ["-pthread", *openmp]


def _tail(text: str, lines: int = 25) -> str:
    return "\n".join(text.strip().splitlines()[-lines:])


def _describe_build_failure(exc: Exception) -> str:
    if isinstance(exc, CpuExtensionError):
        reason = exc.args[0]
    elif isinstance(exc, subprocess.CalledProcessError | FileNotFoundError):
        reason = (
            f"the C++ compiler ({os.environ.get('CXX', 'c++')}) is missing or does not work "
            f"(install g++ or set CXX): {type(exc).__name__}: {_tail(str(exc))}"
        )
    else:
        reason = f"{type(exc).__name__}: {_tail(str(exc))}"
    return f"cannot build the metegs CPU rasteriser extension (in {CSRC}): {reason}"


def load_extension():
    """The compiled extension module (built on first use; raises `CpuExtensionError` if impossible)."""
    return EXTENSION.load()


def set_kernel_threads(n: int) -> None:
    """Threads of the ``cpu`` kernels called from this thread from now on (0: torch's intra-op count, the default).

    With ``torch.set_num_threads(1)`` on the same thread this runs torch's own ops serially while the kernels
    keep ``n`` threads on their pool (``csrc/pool.h``), which does not wait for a descheduled thread."""
    load_extension().set_num_threads(int(n))


def thread_split_counts(backend: str, torch_threads: int) -> tuple[int, int] | None:
    """(threads of torch's own ops, threads of the ``cpu`` kernels) when ``torch_threads`` applies on this thread: the
    ``cpu`` backend and 0 < ``torch_threads`` < torch's present count; else None."""
    total = torch.get_num_threads()
    return (torch_threads, total) if backend == "cpu" and 0 < torch_threads < total else None


@contextlib.contextmanager
def thread_split(backend: str, torch_threads: int) -> Iterator[None]:
    """Within the block, on this thread: torch's own ops (losses, Adam, autograd) on ``torch_threads`` threads while
    the ``cpu`` kernels keep torch's present count, where `thread_split_counts` says it applies; else no change.

    The kernels then run on metegs' pool, which never waits for a descheduled thread (another process, a browser,
    taking part of a core); without a split, those called from the main thread share torch's OpenMP team, which is
    faster on an otherwise idle machine (``csrc/pool.h``, ``docs/benchmark.md``)."""
    counts = thread_split_counts(backend, torch_threads)
    if counts is None:
        yield
        return
    ops, kernels = counts
    set_kernel_threads(kernels)
    torch.set_num_threads(ops)
    try:
        yield
    finally:
        torch.set_num_threads(kernels)
        set_kernel_threads(0)


@contextlib.contextmanager
def single_thread() -> Iterator[None]:
    """Run torch on one thread inside (restored after): a view's work is small, and OpenMP threads that
    busy-wait for a core taken by another process slow it down up to 20x on a loaded 2-core machine."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def build_extension(name: str, sources: list[Path], build_dir: Path, what: str):
    """Compile (when its staged sources or flags changed) and load the extension ``name`` from ``sources`` and
    `HEADERS` in ``build_dir``, under the build lock; ``what`` names it in the one-line message while it builds."""
    from torch.utils import cpp_extension

    missing = [str(f) for f in sources + HEADERS if not f.is_file()]
    if missing:
        raise CpuExtensionError(f"source files missing from the installation: {', '.join(missing)}")
    try:
        cpp_extension.verify_ninja_availability()
    except RuntimeError as exc:
        raise CpuExtensionError("the `ninja` build tool is required (pip install ninja)") from exc
    cflags, ldflags = compile_flags()
    with build_lock(build_dir):
        src, changed = stage_sources(build_dir, sources)
        built, ninja_file = build_dir / f"{name}.so", build_dir / "build.ninja"
        stale = (
            changed
            or not built.exists()
            or not ninja_file.exists()
            or " ".join(cflags) not in ninja_file.read_text(errors="replace")
        )
        if stale:
            print(f"compiling {what} (first use, under a minute) in {build_dir} ...", file=sys.stderr, flush=True)
        return cpp_extension.load(
            name=name,
            sources=[str(src / f.name) for f in sources],
            extra_include_paths=[str(src)],
            extra_ldflags=ldflags,
            extra_cflags=cflags,
            build_directory=str(build_dir),
            verbose=False,
        )


def _build():
    return build_extension(EXTENSION_NAME, SOURCES, build_directory(), "the metegs CPU rasteriser")


EXTENSION = OptionalComponent(
    _build, _describe_build_failure, CpuExtensionError, CpuBackendWarning, "the `torch` rasteriser is used instead"
)
"""The compiled extension of this backend (built once per process)."""


class ProjectShade(torch.autograd.Function):
    """Fused projection + SH colours; same outputs as `project_gaussians` + `gaussian_colors`."""

    @staticmethod
    def forward(
        ctx, means, quats, scales, opacities, sh, viewmat, K, campos, width, height, near, far, eps2d, sh_degree
    ):
        ext = load_extension()
        args = (viewmat, K, campos, int(width), int(height), float(near), float(far), float(eps2d), int(sh_degree))
        means2d, conics, depths, colors, radii, extents = ext.project_forward(
            means, quats, scales, opacities, sh, *args
        )
        ctx.save_for_backward(means, quats, scales, opacities, sh)
        ctx.args = args
        ctx.mark_non_differentiable(radii, extents)
        return means2d, conics, depths, colors, radii, extents

    @staticmethod
    @once_differentiable
    def backward(ctx, g_means2d, g_conics, g_depths, g_colors, _g_radii, _g_extents):
        means, quats, scales, opacities, sh = ctx.saved_tensors
        n = means.shape[0]
        grads = [
            g if g is not None else means.new_zeros(shape)
            for g, shape in ((g_means2d, (n, 2)), (g_conics, (n, 3)), (g_depths, (n,)), (g_colors, (n, 3)))
        ]
        g_means, g_quats, g_scales, g_sh = load_extension().project_backward(
            means, quats, scales, opacities, sh, *ctx.args, *grads
        )
        return (g_means, g_quats, g_scales, None, g_sh) + (None,) * 9


class CompositeTiles(torch.autograd.Function):
    """Differentiable tile compositing; same inputs/outputs as `torch_backend.composite_tiles`."""

    @staticmethod
    def forward(
        ctx,
        means2d,
        conics,
        opacities,
        colors,
        depths,
        gaussian_ids,
        offsets,
        tiles_x,
        tiles_y,
        width,
        height,
        rows=None,
    ):
        ext = load_extension()
        color, alpha, depth, t_final, last = ext.forward(
            means2d, conics, opacities, colors, depths, gaussian_ids, offsets, tiles_x, tiles_y, width, height, rows
        )
        ctx.save_for_backward(means2d, conics, opacities, colors, depths, gaussian_ids, offsets, t_final, last)
        ctx.dims = (tiles_x, tiles_y, width, height)
        ctx.rows = rows
        return color, alpha, depth

    @staticmethod
    @once_differentiable
    def backward(ctx, g_color, g_alpha, g_depth):
        means2d, conics, opacities, colors, depths, ids, offsets, t_final, last = ctx.saved_tensors
        tiles_x, tiles_y, width, height = ctx.dims
        grads = load_extension().backward(
            means2d,
            conics,
            opacities,
            colors,
            depths,
            ids,
            offsets,
            t_final,
            last,
            g_color,
            g_alpha,
            g_depth,
            tiles_x,
            tiles_y,
            width,
            height,
            ctx.rows,
        )  # means2d, conics, opacities, colours, depths
        out = tuple(g if need else None for g, need in zip(grads, ctx.needs_input_grad, strict=False))
        return (*out, None, None, None, None, None, None, None)


class FinishRender(torch.autograd.Function):
    """Compiled `pipeline.finish_render` maths: (color [H,W,3], alpha [H,W], depth_sum [H,W], background [3]) ->
    (rgb [H,W,3] over the background, depth [H,W] = depth_sum / alpha), one pass over the pixels each way instead
    of about ten torch ops."""

    @staticmethod
    def forward(ctx, color, alpha, depth_sum, background):
        rgb, depth = load_extension().finish_forward(color, alpha, depth_sum, background)
        ctx.save_for_backward(alpha, depth_sum, background)
        return rgb, depth

    @staticmethod
    @once_differentiable
    def backward(ctx, g_rgb, g_depth):
        alpha, depth_sum, background = ctx.saved_tensors
        if g_rgb is None:
            g_rgb = alpha.new_zeros((*alpha.shape, 3))
        g_color, g_alpha, g_depth_sum = load_extension().finish_backward(alpha, depth_sum, background, g_rgb, g_depth)
        return g_color, g_alpha, g_depth_sum, None


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
        means2d,
        conics,
        opacities,
        colors,
        depths,
        bins.gaussian_ids,
        bins.offsets,
        bins.tiles_x,
        bins.tiles_y,
        int(width),
        int(height),
    )


class CpuRasterizer:
    """Tile rasteriser with compiled C++ compositing (CPU tensors, float32 or float64)."""

    name = "cpu"

    @staticmethod
    def available(device: torch.device | str = "cpu") -> bool:
        """True on a CPU device once the extension builds/loads (the answer is cached; warns once if not)."""
        return torch.device(device).type == "cpu" and EXTENSION.available()

    def __init__(self, cull_tiles: bool = True):
        self.cull_tiles = cull_tiles
        """Bin a Gaussian only into tiles its ellipse reaches (exact; fewer pairs for elongated Gaussians)."""

    def render(self, gaussians: GaussianSet, camera: Cameras, settings: RenderSettings | None = None) -> RenderOutput:
        """Render one view. camera: a single view (len 1)."""
        g = gaussians
        if g.means.device.type != "cpu":
            raise CpuExtensionError(f"the `cpu` rasteriser needs CPU tensors, got {g.means.device}")
        s = settings or RenderSettings()
        width, height = int(camera.width[0]), int(camera.height[0])
        viewmat = camera.world_to_cameras()[0].to(g.means)
        K = camera.intrinsics()[0].to(g.means)
        campos = camera.centers[0].to(g.means)
        means2d, conics, depths, colors, radii, extents = ProjectShade.apply(
            g.means,
            g.quats,
            g.scales,
            g.opacities,
            g.sh,
            viewmat,
            K,
            campos,
            width,
            height,
            s.near,
            s.far,
            s.eps2d,
            resolve_sh_degree(g, s),
        )
        if means2d.requires_grad:
            means2d.retain_grad()
        ids, offsets, rows = load_extension().bin_tiles(
            means2d.detach(),
            conics.detach(),
            g.opacities.detach(),
            extents,
            depths.detach(),
            width,
            height,
            self.cull_tiles,
        )
        bins = TileBins((width + TILE_SIZE - 1) // TILE_SIZE, (height + TILE_SIZE - 1) // TILE_SIZE, ids, offsets)
        color, alpha, depth_sum = CompositeTiles.apply(
            means2d, conics, g.opacities, colors, depths, ids, offsets, bins.tiles_x, bins.tiles_y, width, height, rows
        )
        background = s.background_tensor(color)
        if background.requires_grad:  # a learned background: its gradient comes from the torch ops
            return finish_render(color, alpha, depth_sum, s, radii, means2d, bins.num_intersections)
        rgb, depth = FinishRender.apply(color, alpha, depth_sum, background)
        return RenderOutput(
            rgb=rgb,
            alpha=alpha,
            depth=depth,
            radii=radii,
            means2d=means2d,
            num_intersections=bins.num_intersections,
            width=width,
            height=height,
        )
