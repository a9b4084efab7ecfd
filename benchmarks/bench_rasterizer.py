"""Render forward + backward time of the `torch` and `cpu` rasterisers in one process.

    python benchmarks/bench_rasterizer.py [--threads 2] [--repeats 5] [--sizes 5000 20000]

Scene: `metegs.testing.random_scene` (SH degree 3) seen by a camera with focal length 0.9 * width;
loss: L1 against a fixed random image. One warm-up step, then the median of ``--repeats`` steps.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from metegs.gaussians.model import GaussianSet
from metegs.render.base import RenderSettings
from metegs.render.cpu_backend import CpuRasterizer
from metegs.render.torch_backend import TorchRasterizer
from metegs.testing import camera, random_scene


def step_ms(rasterizer, scene: GaussianSet, cam, target: torch.Tensor, settings: RenderSettings) -> tuple[float, int]:
    tensors = (scene.means, scene.quats, scene.scales, scene.opacities, scene.sh)
    params = [t.clone().requires_grad_(True) for t in tensors]
    t0 = time.perf_counter()
    out = rasterizer.render(GaussianSet(*params), cam, settings)
    (out.rgb - target).abs().mean().backward()
    return (time.perf_counter() - t0) * 1e3, out.num_intersections


def bench(rasterizer, scene, cam, target, settings, repeats: int) -> tuple[float, int]:
    step_ms(rasterizer, scene, cam, target, settings)  # warm-up (and extension load)
    runs = [step_ms(rasterizer, scene, cam, target, settings) for _ in range(repeats)]
    return statistics.median(r[0] for r in runs), runs[0][1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=None, help="torch intra-op threads (default: torch's)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--sizes", type=int, nargs="+", default=[5000, 20000])
    parser.add_argument("--images", type=str, nargs="+", default=["160x120", "300x200"])
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    if not CpuRasterizer.available("cpu"):
        raise SystemExit("the cpu rasteriser extension is not available on this machine")
    settings = RenderSettings(sh_degree=3)
    threads = torch.get_num_threads()
    print(f"torch {torch.__version__}, {threads} threads; forward+backward ms (median of {args.repeats})")
    print(f"{'image':>9} {'N':>7} {'isects':>8} {'torch ms':>9} {'cpu ms':>8} {'torch/cpu':>9}")
    for image in args.images:
        width, height = (int(v) for v in image.split("x"))
        cam = camera(width, height, f=0.9 * width)
        target = torch.rand(height, width, 3, generator=torch.Generator().manual_seed(0))
        for n in args.sizes:
            scene = random_scene(n, seed=1, sh_degree=3)
            t_torch, isects = bench(TorchRasterizer(), scene, cam, target, settings, args.repeats)
            t_cpu, _ = bench(CpuRasterizer(), scene, cam, target, settings, args.repeats)
            print(f"{image:>9} {n:>7} {isects:>8} {t_torch:>9.1f} {t_cpu:>8.1f} {t_torch / t_cpu:>9.1f}")


if __name__ == "__main__":
    main()
