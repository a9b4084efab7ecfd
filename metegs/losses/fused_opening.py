"""The grey-scale opening of `metegs.losses.photometric.open_bright`, and `metegs.losses.robust.without_bright_strokes`
built on it, as compiled ops with their own backward (CPU).

Same values as the references (`pooled_opening`: two stride-1 ``max_pool2d``, the erosion's then the dilation's;
`pooled_strokes_out`), in four separable passes that keep the input pixel each value came from
(``render/csrc/opening.cpp``); the backward scatters the gradient onto those pixels, where autograd through the
pools ran as long as the forward several times over. Elsewhere (CUDA, integers, no compiled extension) the
references run.
"""

from __future__ import annotations

import torch
from torch.autograd.function import once_differentiable


class FusedOpening(torch.autograd.Function):
    """Opening [B, H, W, C] of ``image`` ([B, H, W, C]) by a ``k`` × ``k`` square (``k`` odd)."""

    @staticmethod
    def forward(ctx, image, k):
        from metegs.render.cpu_backend import load_extension

        opened, index = load_extension().opening_forward(image, k, with_index=image.requires_grad)
        ctx.save_for_backward(index)
        return opened

    @staticmethod
    @once_differentiable
    def backward(ctx, g_out):
        from metegs.render.cpu_backend import load_extension

        (index,) = ctx.saved_tensors
        return load_extension().opening_backward(index, g_out), None


def fused_opening_available(image: torch.Tensor) -> bool:
    """Whether `open_bright` runs the compiled op on ``image``: a floating-point CPU tensor, and the ``cpu``
    backend's extension loaded or buildable."""
    if image.device.type != "cpu" or not image.is_floating_point():
        return False
    from metegs.render.cpu_backend import EXTENSION

    return EXTENSION.available()


def fused_opening(image: torch.Tensor, k: int) -> torch.Tensor:
    """[H, W, C] -> [H, W, C]: the compiled opening of ``image`` by an odd ``k`` × ``k`` square."""
    return FusedOpening.apply(image[None].contiguous(), k)[0]


class FusedStrokesOut(torch.autograd.Function):
    """(render, photo) [B, H, W, C] with the pixels where either holds a bright stroke narrower than ``k`` that
    stands out of its opening by more than ``min_excess`` replaced by both openings; differentiable in ``render``."""

    @staticmethod
    def forward(ctx, render, photo, k, min_excess):
        from metegs.render.cpu_backend import load_extension

        out = load_extension().strokes_out_forward(render, photo, k, min_excess, with_index=render.requires_grad)
        render_out, photo_out, index, stroke = out
        ctx.save_for_backward(index, stroke)
        ctx.mark_non_differentiable(photo_out)
        return render_out, photo_out

    @staticmethod
    @once_differentiable
    def backward(ctx, g_render, _g_photo):
        from metegs.render.cpu_backend import load_extension

        index, stroke = ctx.saved_tensors
        return load_extension().strokes_out_backward(index, stroke, g_render), None, None, None


def fused_strokes_out(
    render: torch.Tensor, photo: torch.Tensor, k: int, min_excess: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """(render, photo), each [H, W, C], with their thin bright strokes taken out by the compiled op (see
    `metegs.losses.robust.without_bright_strokes`); ``k`` odd."""
    render_out, photo_out = FusedStrokesOut.apply(
        render[None].contiguous(), photo.to(render.dtype)[None].contiguous(), k, float(min_excess)
    )
    return render_out[0], photo_out[0]
