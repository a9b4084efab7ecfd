"""Rasteriser benchmark: forward and forward+backward time and peak memory of every backend in one process.

The scene is the one of ``shared/research/cpu-rasteriser.md``: Gaussians uniform in the view frustum
at depth 2-6 m, random rotations, anisotropy within e^{+-0.5}, opacity sigmoid(N(0, 1)), SH degree 3;
world scales chosen so that at 600x400 the 3-sigma discs add up to 10x the image area (depth
complexity about 10). The same world scene is rendered at every resolution (fx = width). The loss is
L1 against a fixed random image. Each configuration: one warm-up step, then the median of the repeats.
"""

from __future__ import annotations

import dataclasses
import math
import statistics
import time
from dataclasses import dataclass

import torch

from metegs.bench.memory import PeakMemory, sync
from metegs.bench.peak import measure_peak_gflops
from metegs.cameras import Cameras
from metegs.engine.allocator import keep_freed_memory
from metegs.gaussians.model import GaussianSet
from metegs.registry import registry
from metegs.render.base import RenderSettings
from metegs.render.cpu_backend import CpuRasterizer, thread_split

PEAK_GFLOPS = 330.0
"""Peak float32 FLOP/s of the 2-core AVX-512 CI machine (research note: 2 x 2.6 GHz x 2 FMA x 16 lanes x 2)."""
FLOPS_PER_PAIR = 100.0
"""Arithmetic of one pixel-Gaussian pair, forward (~30) plus backward (~70), as in the research note."""


@dataclass
class RasterRecord:
    """One backend at one scene size and resolution."""

    backend: str
    num_gaussians: int
    width: int
    height: int
    forward_ms: float
    """Median forward time (projection, binning, compositing)."""
    forward_backward_ms: float
    """Median forward + L1 loss + backward time."""
    peak_mem_mb: float
    """Peak memory above the level before the step (CPU: resident set; CUDA: allocator peak), over up to 3
    forward+backward steps after the timed ones."""
    num_intersections: int
    """(Tile, Gaussian) pairs the backend rasterised."""
    floor_ms: float
    """Arithmetic floor of the research note: 256 pixels x pairs of the plain 3-sigma binning x 100 flops at peak."""
    torch_threads: int
    """Threads of torch's own ops (the loss, autograd) while the backend ran."""
    machine_peak_gflops: float | None = None
    """Float32 multiply-add throughput of the cpu kernels' threads, measured between the timed steps (median;
    `measure_peak_gflops`): this machine's peak in this run. None on a GPU or without the cpu extension."""
    machine_floor_ms: float | None = None
    """The arithmetic floor at ``machine_peak_gflops`` instead of the research note's peak (None with it)."""


def benchmark_scene(n: int, seed: int = 0, device: str | torch.device = "cpu") -> GaussianSet:
    """``n`` Gaussians in the frustum of `benchmark_camera` (any resolution), SH degree 3."""
    g = torch.Generator().manual_seed(seed)
    z = 2.0 + 4.0 * torch.rand(n, generator=g)
    x = (torch.rand(n, generator=g) - 0.5) * z  # fx = W: the frustum is |x| < z / 2, |y| < z / 3
    y = (torch.rand(n, generator=g) - 0.5) * z * (2.0 / 3.0)
    means = torch.stack([x, y, z], dim=1)
    # sum over Gaussians of pi (3 sigma_px)^2 = 10 W H at 600x400, with sigma_px = fx s / z and E[1/z^2] = 1/12
    W, H = 600.0, 400.0
    s0 = math.sqrt(10 * W * H / (n * 9 * math.pi * W * W / 12.0))
    scales = s0 * torch.exp(torch.rand(n, 3, generator=g) - 0.5)
    quats = torch.randn(n, 4, generator=g)
    opacities = torch.sigmoid(torch.randn(n, generator=g))
    sh = 0.3 * torch.randn(n, 16, 3, generator=g)
    return GaussianSet(*(t.to(device) for t in (means, quats, scales, opacities, sh)))


def benchmark_camera(width: int, height: int) -> Cameras:
    """Camera at the origin looking down +z with fx = fy = width, principal point at the centre."""
    return Cameras.create(torch.eye(4)[None], float(width), float(width), width / 2, height / 2, width, height)


def _tensors(scene: GaussianSet) -> list[torch.Tensor]:
    """The set's five tensors, the benchmark's parameters."""
    return [getattr(scene, f.name) for f in dataclasses.fields(scene)]


def _time_step(rasterizer, scene: GaussianSet, cam: Cameras, target: torch.Tensor, backward: bool) -> tuple[float, int]:
    """One forward (and, with ``backward``, L1 loss and backward) of ``scene``, whose tensors are leaves that require
    grad (their gradients are cleared first, outside the timed part) -> (milliseconds, pairs rasterised)."""
    device = scene.means.device
    settings = RenderSettings(sh_degree=3)
    for t in _tensors(scene):
        t.grad = None
    sync(device)
    t0 = time.perf_counter()
    if backward:
        out = rasterizer.render(scene, cam, settings)
        (out.rgb - target).abs().mean().backward()
    else:
        with torch.no_grad():
            out = rasterizer.render(scene, cam, settings)
    sync(device)
    return (time.perf_counter() - t0) * 1e3, out.num_intersections


def plain_pairs(scene: GaussianSet, cam: Cameras) -> int:
    """Tile pairs of the plain 3-sigma binning (the research note's count), for the arithmetic floor."""
    from metegs.render.projection import project_gaussians
    from metegs.render.tiles import bin_gaussians

    W, H = int(cam.width[0]), int(cam.height[0])
    with torch.no_grad():
        p = project_gaussians(
            scene.means.cpu(),
            scene.quats.cpu(),
            scene.scales.cpu(),
            cam.world_to_cameras()[0],
            cam.intrinsics()[0],
            W,
            H,
        )
        return bin_gaussians(p.means2d, p.extents, p.depths, W, H).num_intersections


def run_raster_benchmark(
    sizes: list[int],
    images: list[tuple[int, int]],
    backends: list[str],
    repeats: int = 3,
    device: str | torch.device = "cpu",
    torch_threads: int = 0,
    progress=None,
) -> list[RasterRecord]:
    """Time every backend on every (size, image). Returns one record per combination.

    ``torch_threads``: with the ``cpu`` backend, torch's own ops on this many threads (see ``thread_split``)."""
    device = torch.device(device)
    torch.set_flush_denormal(True)  # as training runs (Trainer): denormal arithmetic is many times slower
    if device.type == "cpu":
        keep_freed_memory()  # as training runs
    probe = device.type == "cpu" and CpuRasterizer.available()
    records = []
    for n in sizes:
        scene = benchmark_scene(n, device=device)
        for t in _tensors(scene):
            t.requires_grad_(True)  # leaves, as a model's parameters (each step clears their gradients first)
        for width, height in images:
            cam = benchmark_camera(width, height)
            target = torch.rand(height, width, 3, generator=torch.Generator().manual_seed(0)).to(device)
            flops = plain_pairs(scene, cam) * 256 * FLOPS_PER_PAIR
            floor_ms = flops / (PEAK_GFLOPS * 1e9) * 1e3
            for name in backends:
                rasterizer = registry("rasterizer").get(name)()
                _time_step(rasterizer, scene, cam, target, backward=True)  # warm-up (and extension load)
                with thread_split(name, torch_threads):
                    ops_threads = torch.get_num_threads()
                    fwd = [_time_step(rasterizer, scene, cam, target, backward=False)[0] for _ in range(repeats)]
                    fb, peaks = [], []
                    for _ in range(repeats):
                        if probe:  # the machine's peak between the timed steps, so that both see the same phase
                            peaks.append(measure_peak_gflops())
                        fb.append(_time_step(rasterizer, scene, cam, target, backward=True))
                    # memory in steps of their own: on CPU a thread samples the resident set every 0.5 ms, which
                    # would take CPU time and the GIL from the timed steps
                    peak = statistics.median(peaks) if peaks else None
                    with PeakMemory(device) as mem:
                        for _ in range(min(repeats, 3)):
                            _time_step(rasterizer, scene, cam, target, backward=True)
                records.append(
                    RasterRecord(
                        backend=name,
                        num_gaussians=n,
                        width=width,
                        height=height,
                        forward_ms=statistics.median(fwd),
                        forward_backward_ms=statistics.median(t for t, _ in fb),
                        peak_mem_mb=mem.peak_mb,
                        num_intersections=fb[0][1],
                        floor_ms=floor_ms,
                        torch_threads=ops_threads,
                        machine_peak_gflops=peak,
                        machine_floor_ms=flops / (peak * 1e9) * 1e3 if peak else None,
                    )
                )
                if progress is not None:
                    progress(records[-1])
    return records
