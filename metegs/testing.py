"""Test helpers shipped with the package: small random scenes and cameras (also used by plugin authors)."""

import torch

from metegs.cameras import Cameras
from metegs.gaussians.model import GaussianSet


def random_scene(
    n: int, seed: int = 0, dtype=torch.float32, sh_degree: int = 1, max_opacity: float = 0.9
) -> GaussianSet:
    """``n`` Gaussians in front of a camera at the origin looking down +z."""
    g = torch.Generator().manual_seed(seed)
    means = torch.rand(n, 3, generator=g, dtype=torch.float64) * torch.tensor(
        [2.0, 1.6, 3.0], dtype=torch.float64
    ) + torch.tensor([-1.0, -0.8, 2.0], dtype=torch.float64)
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    scales = torch.exp(torch.rand(n, 3, generator=g, dtype=torch.float64) * 1.5 - 3.5)
    opac = 0.05 + (max_opacity - 0.05) * torch.rand(n, generator=g, dtype=torch.float64)
    sh = torch.randn(n, (sh_degree + 1) ** 2, 3, generator=g, dtype=torch.float64) * 0.5
    return GaussianSet(means.to(dtype), quats.to(dtype), scales.to(dtype), opac.to(dtype), sh.to(dtype))


def camera(width: int = 40, height: int = 30, f: float = 35.0) -> Cameras:
    return Cameras.create(torch.eye(4)[None], f, f * 1.05, width / 2 + 0.3, height / 2 - 0.2, width, height)


def autograd_graph_holds(t: torch.Tensor, *functions: type) -> bool:
    """Whether ``t``'s autograd graph holds a node of one of the custom autograd ``functions`` (their backward
    nodes are named after them)."""
    names = tuple(f.__name__ for f in functions)
    todo, seen = [t.grad_fn], set()
    while todo:
        fn = todo.pop()
        if fn is None or fn in seen:
            continue
        seen.add(fn)
        if type(fn).__name__.startswith(names):
            return True
        todo += [f for f, _ in fn.next_functions]
    return False
