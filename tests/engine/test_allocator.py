"""keep_freed_memory: glibc keeps the memory a render step frees, so the next step does not fault it in again."""

import subprocess
import sys

import pytest

from metegs.engine import allocator

STEP_FAULTS = """
import resource, sys, torch
from metegs.engine.allocator import keep_freed_memory
if sys.argv[1] == "1" and not keep_freed_memory():
    print("unsupported"); raise SystemExit
from metegs.render.base import RenderSettings
from metegs.render.cpu_backend import CpuRasterizer
from metegs.testing import camera, random_scene
g = random_scene(5000, seed=0, sh_degree=1)
for t in (g.means, g.quats, g.scales, g.opacities, g.sh):
    t.requires_grad_(True)
cam, rasterizer = camera(320, 240, f=100.0), CpuRasterizer()
def step():
    rasterizer.render(g, cam, RenderSettings(sh_degree=1)).rgb.sum().backward()
for _ in range(5):
    step()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(20):
    step()
print((resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before) / 20)
"""


def _faults_per_step(keep: bool) -> str:
    run = subprocess.run([sys.executable, "-c", STEP_FAULTS, "1" if keep else "0"], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    return run.stdout.strip().splitlines()[-1]


def test_render_steps_stop_faulting_in_the_memory_they_free():
    """5k Gaussians at 320x240 on the cpu backend: glibc's defaults fault about 230 pages in per step; kept, < 20."""
    from metegs.render.cpu_backend import CpuExtensionError, load_extension

    try:
        load_extension()
    except CpuExtensionError as exc:
        pytest.skip(f"the cpu rasteriser extension cannot be built here: {exc}")
    kept = _faults_per_step(True)
    if kept == "unsupported":
        pytest.skip("not glibc: no mallopt")
    default = float(_faults_per_step(False))
    assert float(kept) < max(20.0, default / 5), (kept, default)


def test_without_glibc_nothing_changes(monkeypatch):
    """A C library without mallopt (musl, macOS): False, and no error."""

    class NoMallopt:
        def __init__(self, name):
            pass

    allocator.keep_freed_memory.cache_clear()
    monkeypatch.setattr(allocator.ctypes, "CDLL", NoMallopt)
    try:
        assert allocator.keep_freed_memory() is False
    finally:
        allocator.keep_freed_memory.cache_clear()
