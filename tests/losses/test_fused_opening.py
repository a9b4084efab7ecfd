"""The compiled `without_bright_strokes` and its opening against their torch references and finite differences."""

import pytest
import torch

from metegs.losses.fused_opening import FusedStrokesOut, fused_strokes_out
from metegs.losses.photometric import open_bright
from metegs.losses.robust import pooled_strokes_out, without_bright_strokes
from metegs.render import cpu_backend
from metegs.render.cpu_backend import CpuExtensionError
from metegs.testing import autograd_graph_holds

try:
    cpu_backend.load_extension()
except CpuExtensionError as exc:  # no compiler / ninja on this machine
    pytest.skip(f"the cpu extension cannot be built here: {exc}", allow_module_level=True)


def image(shape, dtype=torch.float32, seed=0) -> torch.Tensor:
    """Noise with flat patches, thin bright lines and repeated values (ties the windows must break alike)."""
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(shape, dtype=dtype, generator=g)
    x[: shape[0] // 3, : shape[1] // 2] = 0.25  # a flat patch: every window there ties
    x[:, shape[1] // 3] += 0.5  # a bright line one pixel wide
    return x


@pytest.mark.parametrize(
    "shape, k", [((270, 480, 3), 3), ((17, 23, 3), 5), ((9, 4, 2), 7), ((1, 1, 3), 3), ((6, 8, 1), 1)]
)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_kernels_opening_matches_the_pooled_one_with_and_without_the_source_index(shape, k, dtype):
    x = image(shape, dtype, seed=k)
    ext = cpu_backend.load_extension()
    opened, index = ext.opening_forward(x[None], k, with_index=True)
    assert torch.equal(opened[0], open_bright(x, k))
    assert torch.equal(x.reshape(-1)[index.reshape(-1).long()], opened.reshape(-1))  # each value from its source
    bare, no_index = ext.opening_forward(x[None], k, with_index=False)
    assert torch.equal(bare, opened) and no_index.numel() == 0
    transposed = x.transpose(0, 1)  # not contiguous
    assert torch.equal(ext.opening_forward(transposed[None], k)[0][0], open_bright(transposed, k))


def test_gradient_against_finite_differences():
    g = torch.Generator().manual_seed(3)
    photo = torch.rand(7, 9, 3, dtype=torch.float64, generator=g)
    photo[:, 4] += 0.5  # a streak: pixels taken out and pixels left as they are
    render = torch.rand(7, 9, 3, dtype=torch.float64, generator=g).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda t: fused_strokes_out(t, photo, 3, 0.04)[0], (render,))


def made_by_the_kernel(t: torch.Tensor) -> bool:
    """Whether ``t``'s autograd graph holds `FusedStrokesOut`."""
    return autograd_graph_holds(t, FusedStrokesOut)


def test_bad_input_is_refused_by_the_kernel():
    ext = cpu_backend.load_extension()
    with pytest.raises(RuntimeError, match="odd and positive"):
        ext.opening_forward(torch.rand(1, 8, 8, 3), 4)
    with pytest.raises(RuntimeError, match=r"\[B, H, W, C\]"):
        ext.opening_forward(torch.rand(8, 8, 3), 3)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("k", [3, 5])
def test_strokes_out_matches_the_torch_ops_values_and_gradient(dtype, k):
    g = torch.Generator().manual_seed(k)
    photo = (0.4 + 0.1 * torch.rand(40, 60, 3, generator=g, dtype=dtype)).clamp(0, 1)
    photo[:, 7] += 0.5  # a streak in the photo
    render = (photo + 0.05 * torch.randn(40, 60, 3, generator=g, dtype=dtype)).requires_grad_(True)
    with torch.no_grad():
        render[10:30, 20] += 0.4  # a modelled streak where the photo has none
    expected, fused = pooled_strokes_out(render, photo, k, 0.04), fused_strokes_out(render, photo, k, 0.04)
    assert torch.equal(fused[0], expected[0]) and torch.equal(fused[1], expected[1])
    assert bool((fused[1] != photo).any(dim=-1)[:, 7].all())  # the photo's streak is taken out
    assert bool((fused[0] != render).any(dim=-1)[10:30, 20].all())  # and the render's
    g_out = torch.randn(40, 60, 3, generator=g, dtype=dtype)
    (g_expected,) = torch.autograd.grad(expected[0], render, g_out)
    (g_fused,) = torch.autograd.grad(fused[0], render, g_out)
    torch.testing.assert_close(g_fused, g_expected)
    assert not fused[1].requires_grad


def test_without_bright_strokes_runs_the_kernel_unless_the_photo_needs_a_gradient_or_it_is_missing(monkeypatch):
    render = image((20, 24, 3), seed=6).requires_grad_(True)
    photo = image((20, 24, 3), seed=7)
    assert made_by_the_kernel(without_bright_strokes(render, photo, 3, 0.04)[0])
    assert not made_by_the_kernel(without_bright_strokes(render, photo.requires_grad_(True), 3, 0.04)[0])
    assert without_bright_strokes(render, photo, 1, 0.04) == (render, photo)  # under 2 px: nothing to take
    monkeypatch.setattr(cpu_backend.EXTENSION, "available", lambda: False)
    fallback = without_bright_strokes(render, photo.detach(), 3, 0.04)
    assert not made_by_the_kernel(fallback[0])
    assert torch.equal(fallback[0], fused_strokes_out(render, photo.detach(), 3, 0.04)[0])
