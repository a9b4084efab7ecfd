"""`metegs.losses.robust.without_bright_strokes` as one compiled op with its own backward (CPU).

Same values as its torch reference, `pooled_strokes_out` (the openings of `metegs.losses.photometric.open_bright`:
two stride-1 ``max_pool2d``, the erosion's then the dilation's, and the masks), in four separable passes per
opening that keep the input pixel each value came from (``render/csrc/opening.cpp``); the backward scatters the
gradient onto those pixels, where autograd through the pools ran as long as the forward several times over.
Elsewhere (CUDA, integers, no compiled extension, a photo that needs a gradient) the reference runs.
"""

from __future__ import annotations

import torch
from torch.autograd.function import once_differentiable


def fused_opening_available(image: torch.Tensor) -> bool:
    """Whether `without_bright_strokes` can run the compiled op on ``image``: a floating-point CPU tensor, and the
    ``cpu`` backend's extension loaded or buildable."""
    if image.device.type != "cpu" or not image.is_floating_point():
        return False
    from metegs.render.cpu_backend import EXTENSION

    return EXTENSION.available()


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
