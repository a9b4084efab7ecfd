"""Same-process A/B of the `cpu` rasteriser's compiled ops: another git revision's ``csrc`` against the
working tree's.

    python benchmarks/ab_kernels.py --rev HEAD              # the uncommitted kernel change
    python benchmarks/ab_kernels.py --rev HEAD~3 --threads 1 --repeats 40

The revision's sources are built as a second extension (cached under ``--build-dir``), both take the same
inputs (the `metegs-bench raster` scene), and each op is timed alternately, A then B, so that both see the
same machine state; medians, the ratio A/B and whether the outputs are equal (bit for bit, else the largest
relative difference) are printed per op and size.
"""

from __future__ import annotations

import argparse
import hashlib
import statistics
import subprocess
import time
from pathlib import Path

import torch
from torch.utils import cpp_extension

from metegs.bench.raster import benchmark_camera, benchmark_scene
from metegs.engine.allocator import keep_freed_memory
from metegs.render import cpu_backend

REPO = Path(__file__).resolve().parents[1]
SIZES = [(5000, 150, 100), (20000, 300, 200), (100000, 600, 400)]


def build_revision(rev: str, build_dir: Path):
    """The extension built from ``rev``'s ``metegs/render/csrc`` (one build per commit)."""
    sha = subprocess.check_output(["git", "rev-parse", rev], cwd=REPO, text=True).strip()
    src = build_dir / sha[:12] / "csrc"
    src.mkdir(parents=True, exist_ok=True)
    csrc = cpu_backend.CSRC.relative_to(REPO).as_posix()
    files = subprocess.check_output(["git", "ls-tree", "--name-only", sha, f"{csrc}/"], cwd=REPO, text=True).split()
    for rel in files:  # the revision's own sources and headers (files come and go between revisions)
        (src / Path(rel).name).write_bytes(subprocess.check_output(["git", "show", f"{sha}:{rel}"], cwd=REPO))
    sources = sorted(str(src / Path(rel).name) for rel in files if rel.endswith(".cpp"))
    name = "metegs_ab_" + hashlib.sha1(sha.encode()).hexdigest()[:10]
    out = src.parent / "build"
    out.mkdir(exist_ok=True)
    cflags, ldflags = cpu_backend.compile_flags()  # as the working tree's build: the same threads for both sides
    return cpp_extension.load(
        name=name,
        sources=sources,
        extra_include_paths=[str(src)],
        extra_ldflags=ldflags,
        extra_cflags=cflags,
        build_directory=str(out),
        verbose=False,
    )


def op_calls(ext, n: int, width: int, height: int):
    """Name -> zero-argument call of each op of ``ext`` on the benchmark scene (inputs from ``ext`` itself)."""
    g, cam = benchmark_scene(n), benchmark_camera(width, height)
    args = (cam.world_to_cameras()[0], cam.intrinsics()[0], cam.centers[0], width, height, 0.01, 1e10, 0.3, 3)
    proj = ext.project_forward(g.means, g.quats, g.scales, g.opacities, g.sh, *args)
    m2, con, dep, col, _, extents = proj
    ids, offsets, rows = ext.bin_tiles(m2, con, g.opacities, extents, dep, width, height, True)
    tiles = ((width + 15) // 16, (height + 15) // 16)
    fwd = ext.forward(m2, con, g.opacities, col, dep, ids, offsets, *tiles, width, height, rows)
    gen = torch.Generator().manual_seed(1)
    gc, ga, gd = (torch.rand(t.shape, generator=gen) for t in fwd[:3])
    bwd = ext.backward(
        m2, con, g.opacities, col, dep, ids, offsets, fwd[3], fwd[4], gc, ga, gd, *tiles, width, height, rows
    )
    return {
        "project": lambda: ext.project_forward(g.means, g.quats, g.scales, g.opacities, g.sh, *args),
        "bin": lambda: ext.bin_tiles(m2, con, g.opacities, extents, dep, width, height, True),
        "composite": lambda: ext.forward(m2, con, g.opacities, col, dep, ids, offsets, *tiles, width, height, rows),
        "composite_bwd": lambda: ext.backward(
            m2, con, g.opacities, col, dep, ids, offsets, fwd[3], fwd[4], gc, ga, gd, *tiles, width, height, rows
        ),
        "project_bwd": lambda: ext.project_backward(
            g.means, g.quats, g.scales, g.opacities, g.sh, *args, bwd[0], bwd[1], bwd[4], bwd[3]
        ),
    }


def difference(a, b) -> str:
    pairs = [(x, y) for x, y in zip(a, b) if isinstance(x, torch.Tensor)]
    if all(torch.equal(x, y) for x, y in pairs):
        return "identical"
    worst = max(
        ((x.double() - y.double()).abs().max() / y.double().abs().max().clamp_min(1e-30)).item()
        for x, y in pairs
        if x.shape == y.shape
    )
    return f"max rel diff {worst:.1e}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rev", default="HEAD", help="git revision whose kernels are A (B: the working tree)")
    parser.add_argument("--threads", type=int, default=2, help="torch / kernel threads")
    parser.add_argument("--repeats", type=int, default=25, help="timed calls of each op and side")
    parser.add_argument("--build-dir", type=Path, default=Path("/tmp/metegs-ab-kernels"), help="where A is built")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.set_flush_denormal(True)  # as training runs (Trainer)
    keep_freed_memory()  # as training runs
    a, b = build_revision(args.rev, args.build_dir), cpu_backend.load_extension()
    print(f"A = {args.rev}, B = working tree; {args.threads} threads, median of {args.repeats}")
    for n, width, height in SIZES:
        calls = {"A": op_calls(a, n, width, height), "B": op_calls(b, n, width, height)}
        for op in calls["A"]:
            times = {"A": [], "B": []}
            outs = {}
            for _ in range(args.repeats + 1):
                for side in ("A", "B"):
                    t0 = time.perf_counter()
                    outs[side] = calls[side][op]()
                    times[side].append(time.perf_counter() - t0)
            ta, tb = (1e3 * statistics.median(times[s][1:]) for s in ("A", "B"))
            print(
                f"{n:>6} {width}x{height} {op:<13} A {ta:8.2f} ms  B {tb:8.2f} ms  A/B {ta / tb:5.2f}x  "
                f"{difference(outs['B'], outs['A'])}"
            )


if __name__ == "__main__":
    main()
