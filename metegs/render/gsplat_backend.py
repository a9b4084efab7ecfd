"""The `gsplat` rasteriser: gsplat's CUDA kernels for CUDA devices (``pip install 'metegs[cuda]'``).

gsplat is imported only when a CUDA device asks for this backend: its first call JIT-compiles CUDA
code and fails with unhelpful errors on machines without CUDA, so `GsplatRasterizer.available`
imports it and renders a two-Gaussian smoke scene inside a ``try`` (once per process, with one
warning naming the reason if it fails; ``backend=auto`` then falls back to ``cpu``/``torch``).

Only gsplat's ``rasterization()`` is used. Densification and PLY export stay metegs' own (gsplat
1.5.3's DefaultStrategy never resets opacities, and its ``export_splats`` drops every splat when one
opacity is NaN; see ``shared/research/3dgs-toolkits.md``). The semantics match the ``torch``
reference: classic (non-antialiased) EWA with ``eps2d``, opacity-aware tile extents, alpha clamp
0.99, skip below 1/255, stop at T < 1e-4, SH colours + 0.5 clamped at 0, expected depth.
"""

from __future__ import annotations

import os
from pathlib import Path

import torch

from metegs.cameras import Cameras
from metegs.errors import MetegsError
from metegs.gaussians.model import GaussianSet
from metegs.render.base import RenderOutput, RenderSettings
from metegs.render.build_lock import build_lock
from metegs.render.optional import OptionalComponent
from metegs.render.pipeline import finish_render, resolve_sh_degree


class GsplatUnavailableError(MetegsError, RuntimeError):
    """gsplat cannot be imported or run on this machine."""


class GsplatBackendWarning(UserWarning):
    """The ``gsplat`` rasteriser is unavailable; ``auto`` uses another backend."""


def load_gsplat():
    """The imported and smoke-tested gsplat module (raises `GsplatUnavailableError` with the reason)."""
    return GSPLAT.load()


def build_lock_dir() -> Path:
    """The folder of metegs' lock around gsplat's first use, beside (not in) gsplat's JIT build folder: that first use
    deletes the build folder wherever it finds no finished build, so two processes starting at once on a fresh
    machine delete each other's objects (a lent H100: "can't create ... .o: No such file or directory")."""
    from torch.utils.cpp_extension import get_default_build_root

    return Path(os.environ.get("TORCH_EXTENSIONS_DIR") or get_default_build_root()) / "gsplat_cuda.metegs"


def _import_and_smoke_test():
    if not torch.cuda.is_available():
        raise GsplatUnavailableError("no CUDA device")
    with build_lock(build_lock_dir(), "gsplat's CUDA kernels"):
        try:
            import gsplat
        except ImportError as exc:
            raise GsplatUnavailableError(f"gsplat is not installed (pip install 'metegs[cuda]'): {exc}") from exc
        _smoke_render(gsplat)  # the first render JIT-compiles gsplat's kernels (minutes, once per machine)
    return gsplat


def _smoke_render(gsplat) -> None:
    """Render two Gaussians with ``gsplat`` on the GPU; raises `GsplatUnavailableError` if the image is not finite."""
    device = torch.device("cuda")
    means = torch.tensor([[0.0, 0.0, 2.0], [0.1, 0.0, 3.0]], device=device)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]] * 2, device=device)
    scales = torch.full((2, 3), 0.1, device=device)
    K = torch.tensor([[[20.0, 0, 8], [0, 20.0, 8], [0, 0, 1]]], device=device)
    colors, _, _ = gsplat.rasterization(
        means,
        quats,
        scales,
        torch.full((2,), 0.8, device=device),
        torch.rand(2, 3, device=device),
        torch.eye(4, device=device)[None],
        K,
        16,
        16,
        packed=False,
    )
    torch.cuda.synchronize()
    if not torch.isfinite(colors).all():
        raise GsplatUnavailableError("the smoke render returned non-finite values")


GSPLAT = OptionalComponent(
    _import_and_smoke_test,
    lambda exc: f"gsplat is not usable here: {type(exc).__name__}: {str(exc).strip()[:500]}",
    GsplatUnavailableError,
    GsplatBackendWarning,
    "another rasteriser is used instead",
)
"""gsplat, imported and smoke-tested once per process (only when a CUDA device asks for it)."""


class GsplatRasterizer:
    """gsplat CUDA rasterisation (CUDA tensors only)."""

    name = "gsplat"

    @staticmethod
    def available(device: torch.device | str = "cuda") -> bool:
        """True on a CUDA device where gsplat imports and renders (cached; warns once if not)."""
        return torch.device(device).type == "cuda" and GSPLAT.available()

    def render(self, gaussians: GaussianSet, camera: Cameras, settings: RenderSettings | None = None) -> RenderOutput:
        """Render one view. camera: a single view (len 1)."""
        g = gaussians
        if g.means.device.type != "cuda":
            raise GsplatUnavailableError(f"the `gsplat` rasteriser needs CUDA tensors, got {g.means.device}")
        gsplat = load_gsplat()
        s = settings or RenderSettings()
        width, height = int(camera.width[0]), int(camera.height[0])
        viewmat = camera.world_to_cameras()[0].to(g.means)
        K = camera.intrinsics()[0].to(g.means)
        campos = camera.centers[0].to(g.means)
        # Non-finite Gaussians: moved onto the camera centre (behind the near plane) so that gsplat culls
        # them as the reference does; torch.where keeps their gradients at zero.
        finite = torch.isfinite(g.means).all(1) & torch.isfinite(g.quats).all(1) & torch.isfinite(g.scales).all(1)
        means = torch.where(finite[:, None], g.means, campos.expand_as(g.means))
        quats = torch.where(finite[:, None], g.quats, g.quats.new_tensor([1.0, 0.0, 0.0, 0.0]))
        scales = torch.where(finite[:, None], g.scales, torch.ones_like(g.scales))
        sh_degree = resolve_sh_degree(g, s)
        render, alphas, meta = gsplat.rasterization(
            means,
            quats,
            scales,
            g.opacities,
            g.sh[:, : (sh_degree + 1) ** 2],
            viewmat[None],
            K[None],
            width,
            height,
            near_plane=s.near,
            far_plane=s.far,
            eps2d=s.eps2d,
            sh_degree=sh_degree,
            packed=False,
            tile_size=16,
            render_mode="RGB+ED",
            rasterize_mode="classic",
        )
        alpha = alphas[0, ..., 0]
        color = render[0, ..., :3]
        depth_sum = render[0, ..., 3] * alpha  # ED = sum(w z) / alpha
        means2d_full = meta["means2d"]  # [1, N, 2]
        means2d = means2d_full.detach()[0]
        if means2d_full.requires_grad:

            def keep_grad(grad: torch.Tensor) -> None:
                means2d.grad = grad[0].detach().clone() if means2d.grad is None else means2d.grad + grad[0]

            means2d_full.register_hook(keep_grad)
        radii = meta["radii"][0]
        if radii.dim() == 2:  # gsplat >= 1.5: per-axis radii [N, 2]
            radii = radii.amax(dim=-1)
        radii = radii.to(torch.int32)
        num_isects = int(meta["flatten_ids"].numel()) if "flatten_ids" in meta else 0
        return finish_render(color, alpha, depth_sum, s, radii, means2d, num_isects)
