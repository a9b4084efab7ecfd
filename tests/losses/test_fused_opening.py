"""The compiled opening of `open_bright`, and `without_bright_strokes` built on it, against their torch references
and finite differences."""

import pytest
import torch

from metegs.losses.fused_opening import FusedOpening, FusedStrokesOut, fused_opening, fused_strokes_out
from metegs.losses.photometric import open_bright, pooled_opening
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
def test_values_and_gradient_match_the_pooled_reference(shape, k, dtype):
    x = image(shape, dtype, seed=k).requires_grad_(True)
    expected, opened = pooled_opening(x, k), fused_opening(x, k)
    assert torch.equal(opened, expected)
    g_out = torch.randn(expected.shape, dtype=dtype, generator=torch.Generator().manual_seed(1))
    (g_expected,) = torch.autograd.grad(expected, x, g_out)
    (g_opened,) = torch.autograd.grad(opened, x, g_out)
    torch.testing.assert_close(g_opened, g_expected)  # summation order aside, every pixel takes the same outputs


def test_gradient_against_finite_differences():
    x = torch.rand(7, 9, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(3)).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda t: fused_opening(t, 3), (x,))


def test_a_photo_without_gradient_is_opened_alike_without_the_source_index():
    x = image((40, 50, 3), seed=4)
    opened, index = cpu_backend.load_extension().opening_forward(x[None], 5, with_index=False)
    assert index.numel() == 0
    assert torch.equal(opened[0], pooled_opening(x, 5))
    assert torch.equal(open_bright(x.permute(1, 0, 2), 5), pooled_opening(x.permute(1, 0, 2), 5))  # not contiguous


def made_by_the_kernel(t: torch.Tensor) -> bool:
    """Whether ``t``'s autograd graph holds `FusedOpening` or `FusedStrokesOut`."""
    return autograd_graph_holds(t, FusedOpening, FusedStrokesOut)


def test_open_bright_runs_the_kernel_on_cpu_and_the_reference_without_it(monkeypatch):
    x = image((20, 24, 3), seed=5).requires_grad_(True)
    assert made_by_the_kernel(open_bright(x, 3))
    monkeypatch.setattr(cpu_backend.EXTENSION, "available", lambda: False)
    assert not made_by_the_kernel(open_bright(x, 3))
    torch.testing.assert_close(open_bright(x, 3), pooled_opening(x, 3))


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


def test_without_bright_strokes_runs_the_kernel_unless_the_photo_needs_a_gradient():
    render = image((20, 24, 3), seed=6).requires_grad_(True)
    photo = image((20, 24, 3), seed=7)
    assert made_by_the_kernel(without_bright_strokes(render, photo, 3, 0.04)[0])
    assert not made_by_the_kernel(without_bright_strokes(render, photo.requires_grad_(True), 3, 0.04)[0])
    assert without_bright_strokes(render, photo, 1, 0.04) == (render, photo)  # under 2 px: nothing to take
