"""The machine's float32 multiply-add peak, measured with the kernels' thread count and scheduling: the raster
benchmark's floor.

``csrc/peak.cpp`` is an extension of its own, built (once, beside the kernels' build) only when a benchmark asks for
the peak: the production extension does not carry it.
"""

from __future__ import annotations

from metegs.render.cpu_backend import (
    _TORCH_TAG,
    CSRC,
    CpuBackendWarning,
    CpuExtensionError,
    _describe_build_failure,
    build_directory,
    build_extension,
    load_extension,
)
from metegs.render.optional import OptionalComponent

PEAK_SOURCE = CSRC / "peak.cpp"
PEAK_PROBE_CHUNKS_PER_THREAD = 8
"""Chunks of a peak probe per kernel thread, claimed dynamically as the kernels claim tiles."""

PROBE = OptionalComponent(
    lambda: build_extension(
        f"metegs_cpu_peak_{_TORCH_TAG}", [PEAK_SOURCE], build_directory() / "peak-probe", "the peak probe"
    ),
    _describe_build_failure,
    CpuExtensionError,
    CpuBackendWarning,
    "no peak is measured",
)
"""The probe's compiled extension (built once per process)."""


def measure_peak_gflops(iterations: int = 20000) -> float:
    """Float32 multiply-add throughput (GFLOP/s) of the ``cpu`` kernels' threads, now: the peak of the raster
    benchmark's measured arithmetic floor. Runs ``iterations`` steps of 12 chains of 16-lane multiply-adds per chunk,
    8 chunks per kernel thread (about 0.5 ms at 2 x 115 GFLOP/s with the default), with as many threads as
    the kernels and their scheduling, so it slows down with them when other processes take the cores.
    Raises `CpuExtensionError` if the chains' checksum shows that not all the counted work ran."""
    ext = PROBE.load()
    # the probe is a module of its own: it takes the kernels' thread count from theirs (a thread split, as
    # `--torch-threads 1`, sets it there), or it would run on torch's count
    threads = load_extension().get_num_threads()
    ext.set_num_threads(threads)
    try:
        seconds, flops, checksum = ext.fma_throughput(PEAK_PROBE_CHUNKS_PER_THREAD * threads, int(iterations))
    finally:
        ext.set_num_threads(0)
    if checksum != flops / 2:  # one multiply-add (2 flops) per unit the accumulators reached, with a = b = 1
        raise CpuExtensionError(f"fma_throughput: checksum {checksum} != {flops / 2}; the probe did not run its work")
    return flops / seconds / 1e9
