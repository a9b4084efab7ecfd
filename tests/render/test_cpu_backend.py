"""The compiled `cpu` rasteriser against the torch reference, a brute-force compositor and finite differences."""

import math
import warnings

import pytest
import torch

from metegs.gaussians.model import GaussianSet
from metegs.render import cpu_backend
from metegs.render.base import ALPHA_MAX, ALPHA_MIN, T_MIN, RenderSettings
from metegs.render.cpu_backend import CompositeTiles, CpuBackendWarning, CpuExtensionError, CpuRasterizer
from metegs.render.pipeline import gaussian_colors
from metegs.render.projection import project_gaussians
from metegs.render.tiles import bin_gaussians
from metegs.render.torch_backend import TorchRasterizer
from metegs.testing import camera, random_scene

try:
    cpu_backend.load_extension()
except CpuExtensionError as exc:  # no compiler / ninja on this machine: nothing here can run
    pytest.skip(f"the cpu rasteriser extension cannot be built here: {exc}", allow_module_level=True)

PARAMS = ("means", "quats", "scales", "opacities", "sh")


def render_with_grads(rasterizer, g: GaussianSet, cam, settings: RenderSettings, seed: int = 0):
    """Render, back-propagate a loss touching rgb, depth and alpha; -> (output, {param: grad}, means2d grad)."""
    params = {k: getattr(g, k).clone().requires_grad_(True) for k in PARAMS}
    out = rasterizer.render(GaussianSet(**params), cam, settings)
    target = torch.rand(out.rgb.shape, dtype=out.rgb.dtype, generator=torch.Generator().manual_seed(seed))
    loss = ((out.rgb - target) ** 2).sum() + 0.01 * (out.depth * out.alpha).sum() + 0.1 * out.alpha.sum()
    loss.backward()
    return out, {k: p.grad for k, p in params.items()}, out.means2d.grad


def reference(n: int) -> TorchRasterizer:
    # One chunk holding every tile's whole list: the reference then stops a pixel for good at
    # T < T_MIN, as the CUDA kernel and this backend do (with smaller chunks it resumes compositing
    # in the next chunk, so results would depend on the chunk size).
    return TorchRasterizer(chunk=max(n, 1))


def degenerate(g: GaussianSet, case: str) -> GaussianSet:
    means, quats, scales, opac = g.means.clone(), g.quats.clone(), g.scales.clone(), g.opacities.clone()
    k = max(1, len(g) // 8)
    if case == "behind":
        means[:k, 2] = -2.0
    elif case == "tiny_scale":
        scales[:k] = 1e-8
    elif case == "huge_scale":
        scales[:k] = 10.0
    elif case == "saturated":
        opac[:] = 1.0
    elif case == "nan_mean":
        means[0] = float("nan")
    return GaussianSet(means, quats, scales, opac, g.sh)


def assert_grads_close(got: torch.Tensor, ref: torch.Tensor, name: str):
    scale = ref.abs().max().clamp_min(1e-12)
    torch.testing.assert_close(got / scale, ref / scale, rtol=1e-4, atol=1e-6, msg=lambda m: f"{name}: {m}")


@pytest.mark.parametrize(
    ("n", "width", "height", "sh_degree", "case"),
    [
        (40, 37, 29, 1, "none"),
        (300, 70, 45, 3, "none"),
        (200, 50, 33, 0, "behind"),
        (200, 45, 31, 2, "tiny_scale"),
        (120, 40, 30, 1, "huge_scale"),
        (300, 63, 47, 1, "saturated"),
        (150, 33, 17, 2, "nan_mean"),
    ],
)
def test_matches_torch_reference(n, width, height, sh_degree, case):
    g = degenerate(random_scene(n, seed=n + width, sh_degree=sh_degree), case)
    cam = camera(width, height, f=0.8 * width)
    settings = RenderSettings(background=(0.2, 0.4, 0.6), sh_degree=sh_degree)
    ref, ref_grads, ref_m2d = render_with_grads(reference(n), g, cam, settings)
    out, grads, m2d = render_with_grads(CpuRasterizer(), g, cam, settings)
    unculled = CpuRasterizer(cull_tiles=False).render(g, cam, settings)
    # same candidate boxes as the reference; the ellipse-tile test only drops pairs that cannot contribute
    assert out.rgb.shape == (height, width, 3) and unculled.num_intersections == ref.num_intersections > 0
    assert 0 < out.num_intersections <= ref.num_intersections
    torch.testing.assert_close(unculled.rgb, out.rgb, rtol=0, atol=1e-6)
    torch.testing.assert_close(out.rgb, ref.rgb, rtol=0, atol=1e-5)
    torch.testing.assert_close(out.alpha, ref.alpha, rtol=0, atol=1e-5)
    torch.testing.assert_close(out.depth * out.alpha, ref.depth * ref.alpha, rtol=0, atol=5e-5)
    for k in PARAMS:
        assert torch.isfinite(grads[k]).all(), k
        assert_grads_close(grads[k], ref_grads[k], k)
    assert_grads_close(m2d, ref_m2d, "means2d")


def test_float64_matches_reference_tightly():
    g = random_scene(250, seed=11, dtype=torch.float64, sh_degree=2)
    cam = camera(41, 35, f=30.0)
    settings = RenderSettings(background=(0.1, 0.1, 0.1))
    ref, ref_grads, _ = render_with_grads(reference(250), g, cam, settings)
    out, grads, _ = render_with_grads(CpuRasterizer(), g, cam, settings)
    assert out.rgb.dtype == torch.float64
    torch.testing.assert_close(out.rgb, ref.rgb, rtol=0, atol=1e-12)
    torch.testing.assert_close(out.alpha, ref.alpha, rtol=0, atol=1e-12)
    for k in PARAMS:
        torch.testing.assert_close(grads[k], ref_grads[k], rtol=1e-9, atol=1e-12)


def _composite_inputs(g: GaussianSet, cam, colors=None):
    W, H = int(cam.width[0]), int(cam.height[0])
    proj = project_gaussians(
        g.means,
        g.quats,
        g.scales,
        cam.world_to_cameras()[0].to(g.means),
        cam.intrinsics()[0].to(g.means),
        W,
        H,
        opacities=g.opacities,
    )
    bins = bin_gaussians(proj.means2d, proj.extents, proj.depths, W, H)
    if colors is None:
        colors = gaussian_colors(g, cam.centers[0].to(g.means), int(round(g.sh.shape[1] ** 0.5)) - 1)
    return proj, bins, colors, W, H


@pytest.mark.parametrize("channels", [3, 1, 5])
def test_composite_function_gradcheck(channels):
    g = random_scene(5, seed=3, dtype=torch.float64, sh_degree=0, max_opacity=0.7)
    cam = camera(20, 18, f=18.0)
    colors = torch.rand(5, channels, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    proj, bins, colors, W, H = _composite_inputs(g, cam, colors)
    assert bins.num_intersections > 0

    def composite(means2d, conics, opacities, colors, depths):
        return cpu_backend.composite_tiles_cpu(means2d, conics, opacities, colors, depths, bins, W, H)

    inputs = tuple(
        t.detach().clone().requires_grad_(True) for t in (proj.means2d, proj.conics, g.opacities, colors, proj.depths)
    )
    assert torch.autograd.gradcheck(composite, inputs, eps=1e-6, atol=1e-6, rtol=1e-4)


def brute_composite(means2d, conics, opacities, colors, depths, radii, W, H):
    """Per pixel, every drawn Gaussian in depth order with the plain 3DGS rules (stop at T < T_MIN)."""
    order = [i for i in torch.argsort(depths).tolist() if radii[i] > 0]
    img = torch.zeros(H, W, colors.shape[1], dtype=colors.dtype)
    alpha_img = torch.zeros(H, W, dtype=colors.dtype)
    for y in range(H):
        for x in range(W):
            T, c = 1.0, torch.zeros(colors.shape[1], dtype=colors.dtype)
            for i in order:
                dx, dy = x + 0.5 - float(means2d[i, 0]), y + 0.5 - float(means2d[i, 1])
                a, b, cc = (float(v) for v in conics[i])
                power = -0.5 * (a * dx * dx + cc * dy * dy) - b * dx * dy
                alpha = min(ALPHA_MAX, float(opacities[i]) * math.exp(min(power, 0.0)))
                if alpha < ALPHA_MIN:
                    continue
                if T * (1 - alpha) < T_MIN:
                    break
                c = c + alpha * T * colors[i]
                T *= 1 - alpha
            img[y, x], alpha_img[y, x] = c, 1 - T
    return img, alpha_img


@pytest.mark.parametrize("opacity_behind", [0.999, 0.3])
def test_early_termination_with_opaque_stack(opacity_behind):
    """Nearly opaque Gaussians on one pixel: a pixel stops for good before T would drop below 1e-4."""
    n = 12
    means = torch.tensor([[0.0, 0.0, 2.0 + 0.1 * i] for i in range(n)], dtype=torch.float64)
    opac = torch.full((n,), opacity_behind, dtype=torch.float64)
    opac[:3] = 0.999  # the pixel stops on the third Gaussian; the fainter ones behind must not come back
    g = GaussianSet(
        means,
        torch.tensor([[1.0, 0, 0, 0]] * n, dtype=torch.float64),
        torch.full((n, 3), 0.5, dtype=torch.float64),
        opac,
        torch.rand(n, 1, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0)),
    )
    cam = camera(16, 16)
    out = CpuRasterizer().render(g, cam)
    proj, _, colors, W, H = _composite_inputs(g, cam)
    ref, ref_alpha = brute_composite(proj.means2d, proj.conics, g.opacities, colors, proj.depths, proj.radii, W, H)
    torch.testing.assert_close(out.rgb, ref, rtol=0, atol=1e-12)
    torch.testing.assert_close(out.alpha, ref_alpha, rtol=0, atol=1e-12)
    T_end = 1 - float(out.alpha[8, 8])
    assert T_MIN * (1 - 1e-9) <= T_end <= 0.01 + 1e-12
    torch.testing.assert_close(out.rgb, reference(n).render(g, cam).rgb, rtol=0, atol=1e-12)


def test_matches_brute_force_with_general_channels():
    g = random_scene(40, seed=7, dtype=torch.float64, sh_degree=0)
    cam = camera(23, 19, f=20.0)
    colors = torch.rand(40, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    proj, bins, colors, W, H = _composite_inputs(g, cam, colors)
    color, alpha, depth_sum = CompositeTiles.apply(
        proj.means2d,
        proj.conics,
        g.opacities,
        colors,
        proj.depths,
        bins.gaussian_ids,
        bins.offsets,
        bins.tiles_x,
        bins.tiles_y,
        W,
        H,
    )
    ref, ref_alpha = brute_composite(proj.means2d, proj.conics, g.opacities, colors, proj.depths, proj.radii, W, H)
    assert color.shape == (H, W, 4)
    torch.testing.assert_close(color, ref, rtol=0, atol=1e-12)
    torch.testing.assert_close(alpha, ref_alpha, rtol=0, atol=1e-12)


def test_available_on_cpu_only():
    assert CpuRasterizer.available("cpu")
    assert CpuRasterizer.available(torch.device("cpu"))
    assert not CpuRasterizer.available("cuda")
    assert not CpuRasterizer.available("meta")


def test_build_failure_makes_backend_unavailable_with_one_warning(monkeypatch, cam):
    monkeypatch.setattr(cpu_backend.EXTENSION, "value", None)
    monkeypatch.setattr(cpu_backend.EXTENSION, "error", "cannot build ...: g++: not found")
    monkeypatch.setattr(cpu_backend.EXTENSION, "warned", False)
    with pytest.warns(CpuBackendWarning, match="g\\+\\+: not found"):
        assert not CpuRasterizer.available("cpu")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert not CpuRasterizer.available("cpu")  # cached, warned once
    with pytest.raises(CpuExtensionError, match="not found"):
        CpuRasterizer().render(random_scene(5), cam)


def test_full_render_gradcheck_float64():
    """Finite differences through every compiled stage (projection + SH, binning, compositing)."""
    g = random_scene(6, seed=5, dtype=torch.float64, sh_degree=2, max_opacity=0.7)
    cam = camera(24, 20, f=20.0)
    settings = RenderSettings(background=(0.3, 0.2, 0.1))
    weights = torch.rand(20, 24, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(4))

    def render(means, quats, scales, opacities, sh):
        out = CpuRasterizer().render(GaussianSet(means, quats, scales, opacities, sh), cam, settings)
        return (out.rgb * weights).sum(), (out.alpha * out.depth).sum()

    inputs = tuple(getattr(g, k).clone().requires_grad_(True) for k in PARAMS)
    assert torch.autograd.gradcheck(render, inputs, eps=1e-7, atol=1e-5, rtol=1e-4)


@pytest.mark.parametrize("sh_degree", [0, 1, 2, 3])
def test_projection_op_matches_torch_reference(sh_degree):
    """ProjectShade alone: outputs and every input gradient against project_gaussians + gaussian_colors."""
    g = degenerate(random_scene(400, seed=sh_degree, dtype=torch.float64, sh_degree=3), "behind")
    means = g.means.clone()
    means[5] = torch.tensor([0.0, 0.0, 1e6], dtype=torch.float64)  # far away
    means[6] = torch.tensor([30.0, 0.0, 2.0], dtype=torch.float64)  # far outside the image (clamped J)
    quats = g.quats.clone()
    quats[7] = 1e-14  # near-zero quaternion
    g = GaussianSet(means, quats, g.scales, g.opacities, g.sh)
    cam = camera(50, 40, f=45.0)
    W, H = 50, 40
    viewmat, K, campos = cam.world_to_cameras()[0].double(), cam.intrinsics()[0].double(), cam.centers[0].double()
    cot = [
        torch.randn(s, dtype=torch.float64, generator=torch.Generator().manual_seed(i))
        for i, s in enumerate([(400, 2), (400, 3), (400,), (400, 3)])
    ]

    def run(fn):
        params = [t.clone().requires_grad_(True) for t in (g.means, g.quats, g.scales, g.sh)]
        outs = fn(*params)
        sum(((o * c).sum() for o, c in zip(outs[:4], cot))).backward()
        return [o.detach() for o in outs], [p.grad for p in params]

    def ours(means, quats, scales, sh):
        return cpu_backend.ProjectShade.apply(
            means, quats, scales, g.opacities, sh, viewmat, K, campos, W, H, 0.01, 1e10, 0.3, sh_degree
        )

    def reference_fn(means, quats, scales, sh):
        p = project_gaussians(means, quats, scales, viewmat, K, W, H, opacities=g.opacities)
        colors = gaussian_colors(GaussianSet(means, quats, scales, g.opacities, sh), campos, sh_degree)
        return p.means2d, p.conics, p.depths, colors, p.radii, p.extents

    (o, og), (r, rg) = run(ours), run(reference_fn)
    for name, a, b in zip(("means2d", "conics", "depths", "colors", "radii", "extents"), o, r):
        torch.testing.assert_close(a.to(b.dtype), b, rtol=1e-10, atol=1e-10, msg=lambda m, n=name: f"{n}: {m}")
    for name, a, b in zip(("means", "quats", "scales", "sh"), og, rg):
        torch.testing.assert_close(a, b, rtol=1e-8, atol=1e-10, msg=lambda m, n=name: f"grad {n}: {m}")


@pytest.mark.parametrize("sh_degree", [0, 3])
def test_projection_vector_lanes_and_scalar_remainder_agree_bit_for_bit(sh_degree):
    """float32 Gaussians are projected 16 to a vector and the remainder one at a time: shifting the list moves
    each Gaussian between the two paths, and its outputs and gradients must not change by a bit (degenerate
    Gaussians included: behind the camera, NaN mean, zero quaternion, tiny and clamped ones)."""
    ext = cpu_backend.load_extension()
    g = degenerate(random_scene(53, seed=7, sh_degree=3), "behind")
    means, quats, scales = g.means.clone(), g.quats.clone(), g.scales.clone()
    means[9] = float("nan")
    means[10] = torch.tensor([30.0, 0.0, 2.0])  # far outside the image: clamped linearisation point
    quats[11] = 0.0
    scales[12] = 1e-8
    inputs = (means, quats, scales, g.opacities, g.sh)
    cam = camera(64, 48, f=50.0)
    args = (cam.world_to_cameras()[0], cam.intrinsics()[0], cam.centers[0], 64, 48, 0.01, 1e10, 0.3, sh_degree)
    gen = torch.Generator().manual_seed(3)
    cot = [torch.randn(53, *s, generator=gen) for s in ((2,), (3,), (), (3,))]

    def run(start):
        part = [t[start:].contiguous() for t in inputs]
        fwd = ext.project_forward(*part, *args)
        bwd = ext.project_backward(*part, *args, *(c[start:].contiguous() for c in cot))
        return list(fwd) + list(bwd)

    full = run(0)
    assert torch.isfinite(full[0]).all() and (full[4] > 0).sum() > 20  # most Gaussians are kept
    for start in (1, 5, 21, 40):  # 52, 48, 32 and 13 Gaussians: every Gaussian changes lane or path
        for whole, part in zip(full, run(start)):
            assert torch.equal(whole[start:], part)


@pytest.mark.parametrize("variant", ["no-avx512", "portable"])
def test_kernels_built_without_avx512_match_the_default_build(tmp_path, variant):
    """The kernels' fallbacks for CPUs without AVX-512 (lane loops, plain loads and stores, a division instead of
    the reciprocal estimate) against the default build: the projection, the binning and the compositing forward
    give the same bits, the compositing backward the same gradients up to the reciprocal's rounding. ``portable``:
    the build ARM machines get (`METEGS_CPU_PORTABLE`: no x86 intrinsic, no -march=native), whose multiply-adds
    round twice: the same tile lists, floats to float32 rounding."""
    from torch.utils import cpp_extension

    cflags, ldflags = cpu_backend.compile_flags()
    if variant == "portable":
        openmp = [f for f in cflags if f == "-fopenmp"]
        flags = cpu_backend.machine_cflags(portable=True) + openmp
        assert "-DMETEGS_PORTABLE" in flags and not any("native" in f or "vector-width" in f for f in flags)
    else:
        flags = [f for f in cflags if f != "-mprefer-vector-width=512"] + ["-mno-avx512f"]
    plain = cpp_extension.load(
        name=f"metegs_test_{variant.replace('-', '_')}",
        sources=[str(f) for f in cpu_backend.SOURCES],
        extra_include_paths=[str(cpu_backend.CSRC)],
        extra_ldflags=ldflags,
        extra_cflags=flags,
        build_directory=str(tmp_path),
        verbose=False,
    )
    default = cpu_backend.load_extension()
    g = degenerate(random_scene(300, seed=4, sh_degree=3), "tiny_scale")
    W, H = 70, 45
    cam = camera(W, H, f=0.8 * W)
    args = (cam.world_to_cameras()[0], cam.intrinsics()[0], cam.centers[0], W, H, 0.01, 1e10, 0.3, 3)
    gen = torch.Generator().manual_seed(2)
    g_img = (torch.rand(H, W, 3, generator=gen), torch.rand(H, W, generator=gen), torch.rand(H, W, generator=gen))

    def run(ext):
        m2, con, dep, col, radii, extents = ext.project_forward(g.means, g.quats, g.scales, g.opacities, g.sh, *args)
        ids, offsets, rows = ext.bin_tiles(m2, con, g.opacities, extents, dep, W, H, True)
        tiles = ((W + 15) // 16, (H + 15) // 16)
        fwd = ext.forward(m2, con, g.opacities, col, dep, ids, offsets, *tiles, W, H, rows)
        bwd = ext.backward(m2, con, g.opacities, col, dep, ids, offsets, fwd[3], fwd[4], *g_img, *tiles, W, H, rows)
        pbwd = ext.project_backward(
            g.means, g.quats, g.scales, g.opacities, g.sh, *args, bwd[0], bwd[1], bwd[4], bwd[3]
        )
        return [m2, con, dep, col, radii, extents, ids, offsets, rows, *fwd], [*bwd, *pbwd]

    (exact_a, grads_a), (exact_b, grads_b) = run(plain), run(default)
    assert int(exact_b[4].gt(0).sum()) > 100  # most Gaussians are drawn
    for a, b in zip(exact_a, exact_b):
        if variant == "portable" and a.is_floating_point():
            torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6 * float(b.abs().max().clamp_min(1e-12)))
        else:
            assert torch.equal(a, b)
    for a, b in zip(grads_a, grads_b):
        assert torch.isfinite(a).all()
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6 * float(b.abs().max().clamp_min(1e-12)))


@pytest.mark.parametrize("seed,ties", [(0, False), (1, False), (2, True)])
def test_binning_matches_torch_and_culling_is_a_subset(seed, ties):
    """Same lists as the torch reference; with ``ties``, depths rounded to 4 values (equal depths keep id order)."""
    g = random_scene(500, seed=seed, sh_degree=0)
    cam = camera(90, 70, f=60.0)
    proj, bins, _, W, H = _composite_inputs(g, cam)
    depths = proj.depths
    if ties:
        depths = depths.round()
        assert depths.unique().numel() < 10
        bins = bin_gaussians(proj.means2d, proj.extents, depths, W, H)
    ext = cpu_backend.load_extension()
    args = (proj.means2d, proj.conics, g.opacities, proj.extents, depths, W, H)
    ids, offsets, _ = ext.bin_tiles(*args, False)
    assert torch.equal(offsets, bins.offsets) and torch.equal(ids, bins.gaussian_ids)
    cids, coffsets, _ = ext.bin_tiles(*args, True)
    assert cids.numel() < ids.numel()
    for t in range(len(offsets) - 1):
        kept = cids[coffsets[t] : coffsets[t + 1]].tolist()
        full = ids[offsets[t] : offsets[t + 1]].tolist()
        assert kept == [i for i in full if i in set(kept)]  # a sub-list, still front to back


def _rect_qmin(a, b, c, X0, X1, Y0, Y1):
    """Minimum of a x^2 + 2 b x y + c y^2 (positive definite) over the rectangles [X0, X1] x [Y0, Y1] (float64)."""
    inside = (X0 <= 0) & (X1 >= 0) & (Y0 <= 0) & (Y1 >= 0)
    best = torch.full_like(X0, math.inf)
    for X in (X0, X1):
        y = (-b * X / c).clamp(Y0, Y1)
        best = torch.minimum(best, a * X * X + 2 * b * X * y + c * y * y)
    for Y in (Y0, Y1):
        x = (-b * Y / a).clamp(X0, X1)
        best = torch.minimum(best, a * x * x + 2 * b * x * Y + c * Y * Y)
    return torch.where(inside, torch.zeros_like(best), best)


@pytest.mark.parametrize("thin", [False, True])
def test_culled_tiles_are_those_the_ellipse_reaches(thin):
    """Brute force over every candidate tile: each tile whose pixel centres some Gaussian's alpha reaches (1/255,
    i.e. q <= 2 ln(255 o) at a centre) is in the Gaussian's list, and every kept tile's rectangle of pixel centres
    comes within the safety margin of the ellipse (the margin grows with the anisotropy: thin ellipses)."""
    gen = torch.Generator().manual_seed(7 + thin)
    n, W, H = 400, 150, 110
    means2d = torch.rand(n, 2, generator=gen) * torch.tensor([W + 40.0, H + 40.0]) - 20.0
    angle = torch.rand(n, generator=gen) * math.pi
    s1 = 0.5 + 6.0 * torch.rand(n, generator=gen)
    s2 = s1 * (torch.rand(n, generator=gen) * (0.02 if thin else 1.0) + (0.002 if thin else 0.2))
    cos, sin = angle.cos(), angle.sin()
    # conic = inverse covariance of R diag(s1^2, s2^2) R^T
    a = cos**2 / s1**2 + sin**2 / s2**2
    c = sin**2 / s1**2 + cos**2 / s2**2
    b = cos * sin * (1 / s1**2 - 1 / s2**2)
    conics = torch.stack([a, b, c], 1).float()
    opac = torch.rand(n, generator=gen).float() * 0.99 + 0.01
    depths = torch.rand(n, generator=gen)
    extents = torch.full((n, 2), 3.0 * float(s1.max()) + 2.0)
    ext = cpu_backend.load_extension()
    ids, offsets, _ = ext.bin_tiles(means2d, conics, opac, extents, depths, W, H, True)
    tx_n, ty_n = (W + 15) // 16, (H + 15) // 16
    kept = torch.zeros(n, ty_n * tx_n, dtype=torch.bool)
    for t in range(ty_n * tx_n):
        kept[ids[offsets[t] : offsets[t + 1]], t] = True
    ty, tx = torch.meshgrid(torch.arange(ty_n), torch.arange(tx_n), indexing="ij")
    ty, tx = ty.flatten().double(), tx.flatten().double()
    m, con = means2d.double(), conics.double()
    A, B, C = (con[:, k : k + 1] for k in range(3))
    thresh = 2 * torch.log((255 * opac.double()).clamp_min(1.0))[:, None]
    X0 = 16 * tx + 0.5 - m[:, :1]
    X1 = torch.minimum(16 * tx + 16, torch.tensor(float(W))) - 0.5 - m[:, :1]
    Y0 = 16 * ty + 0.5 - m[:, 1:]
    Y1 = torch.minimum(16 * ty + 16, torch.tensor(float(H))) - 0.5 - m[:, 1:]
    qmin = _rect_qmin(A, B, C, X0, X1, Y0, Y1)
    # the smallest q at a pixel centre of each tile (the ones the compositing evaluates)
    px, py = torch.arange(W).double() + 0.5, torch.arange(H).double() + 0.5
    reached = torch.zeros_like(kept)
    for g in range(n):
        dx, dy = px[None, :] - m[g, 0], py[:, None] - m[g, 1]
        q = A[g] * dx * dx + 2 * B[g] * dx * dy + C[g] * dy * dy
        q = torch.nn.functional.pad(q, (0, 16 * tx_n - W, 0, 16 * ty_n - H), value=math.inf)
        per_tile = q.reshape(ty_n, 16, tx_n, 16).amin(dim=(1, 3)).flatten()
        reached[g] = per_tile <= thresh[g]
    assert int(reached.sum()) > 200
    assert not (reached & ~kept).any(), "a tile the ellipse reaches is missing from the lists"
    det = A * C - B * B
    margin = 1e-4 * (1 + thresh * (2 + 2 * (A * C + B * B) / det))
    assert bool((qmin[kept] <= (thresh + margin).expand_as(qmin)[kept] * (1 + 1e-9)).all()), "a tile out of reach"
    assert int(kept.sum()) <= int((qmin <= thresh + margin).sum())


def test_binning_beyond_65536_tile_columns_matches_torch():
    """Tile columns past 16-bit range (an image over a million pixels wide) are listed where they belong."""
    W, H, n = 1_100_000, 20, 6
    means2d = torch.tensor([[1_050_000.0 + 37 * i, 9.0 + i] for i in range(n)])
    conics = torch.tensor([[0.02, 0.0, 0.02]]).repeat(n, 1)
    opac, depths, extents = torch.full((n,), 0.8), torch.arange(n, 0, -1).float(), torch.full((n, 2), 25.0)
    ref = bin_gaussians(means2d, extents, depths, W, H)
    ext = cpu_backend.load_extension()
    ids, offsets, _ = ext.bin_tiles(means2d, conics, opac, extents, depths, W, H, False)
    assert torch.equal(offsets, ref.offsets) and torch.equal(ids, ref.gaussian_ids)
    cids, coffsets, _ = ext.bin_tiles(means2d, conics, opac, extents, depths, W, H, True)
    tiles = torch.repeat_interleave(torch.arange(len(coffsets) - 1), coffsets.diff())
    assert cids.numel() > 0 and bool((tiles % ((W + 15) // 16) * 16 >= 1_049_000).all())
    mx = means2d[cids, 0]
    assert bool(
        ((tiles % ((W + 15) // 16)) * 16 <= mx + 25).all() & ((tiles % ((W + 15) // 16) + 1) * 16 >= mx - 25).all()
    )


def test_row_half_heights_of_bin_tiles_equal_the_composite_fallback_and_bad_rows_are_refused():
    """The compositing op gives the same image and gradients with bin_tiles' row half-heights as when it
    computes them itself; rows of the wrong shape or dtype are a clear error."""
    g = random_scene(300, seed=4, sh_degree=0)
    cam = camera(70, 50, f=50.0)
    proj, _, colors, W, H = _composite_inputs(g, cam)
    ext = cpu_backend.load_extension()
    ids, offsets, rows = ext.bin_tiles(proj.means2d, proj.conics, g.opacities, proj.extents, proj.depths, W, H, True)
    tiles = ((W + 15) // 16, (H + 15) // 16)

    def run(r):
        inputs = [t.detach().clone().requires_grad_(True) for t in (proj.means2d, proj.conics, g.opacities, colors)]
        color, alpha, _ = CompositeTiles.apply(*inputs, proj.depths, ids, offsets, *tiles, W, H, r)
        (color.sum() + alpha.sum()).backward()
        return [color, alpha] + [t.grad for t in inputs]

    for a, b in zip(run(rows), run(None), strict=True):
        assert torch.equal(a, b)
    args = (proj.means2d, proj.conics, g.opacities, colors, proj.depths, ids, offsets, *tiles, W, H)
    for bad in (rows.float(), rows[:-1]):
        with pytest.raises(RuntimeError, match="rows must be the"):
            ext.forward(*args, bad)


def test_build_failure_still_trains_through_torch(tmp_path):
    """No compiler (simulated): `backend=auto` trains with `torch`, with exactly one warning."""
    import json
    import os
    import subprocess
    import sys

    env = dict(os.environ, CXX="/bin/false", CC="/bin/false", METEGS_EXTENSIONS_DIR=str(tmp_path / "ext"))
    cmd = [
        sys.executable,
        "-W",
        "always::UserWarning",
        "-m",
        "metegs.cli.train",
        "3dgs",
        "--max-steps",
        "3",
        "--output-dir",
        str(tmp_path),
        "--experiment-name",
        "nocc",
        "--dataset.synthetic.num-views",
        "6",
        "--dataset.synthetic.width",
        "32",
        "--dataset.synthetic.height",
        "24",
        "--eval-every",
        "0",
        "--no-progress",
        "--device",
        "cpu",
    ]
    res = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    assert res.stderr.count("CpuBackendWarning") == 1, res.stderr[-3000:]
    run = tmp_path / "synthetic" / "3dgs" / "nocc"
    assert "backend: torch" in (run / "config.yml").read_text()
    assert "C++ compiler" in res.stderr
    assert json.loads((run / "metrics.json").read_text())["num_gaussians"] > 0


def test_pool_gives_the_same_bits_on_any_thread_count_and_under_concurrent_calls():
    """metegs::parallel_for (csrc/pool.h) hands out chunks dynamically: the images and gradients must not depend
    on how many threads took part, nor on two Python threads rendering at once (their jobs take turns)."""
    from concurrent.futures import ThreadPoolExecutor

    g, cam = random_scene(3000, seed=4, sh_degree=2), camera(96, 64, f=70.0)
    settings = RenderSettings(sh_degree=2)

    def run(seed: int = 0):
        out, grads, m2d = render_with_grads(CpuRasterizer(), g, cam, settings, seed=seed)
        return [out.rgb, out.depth, out.alpha, m2d, *grads.values()]

    previous = torch.get_num_threads()
    try:
        runs = {}
        for threads in (1, 2, 3):
            torch.set_num_threads(threads)
            runs[threads] = run()
        with ThreadPoolExecutor(2) as pool:
            concurrent = list(pool.map(run, [0, 1, 0, 1]))
    finally:
        torch.set_num_threads(previous)
    for threads in (2, 3):
        assert all(torch.equal(a, b) for a, b in zip(runs[1], runs[threads])), threads
    assert all(torch.equal(a, b) for a, b in zip(runs[1], concurrent[0]))
    assert all(torch.equal(a, b) for a, b in zip(concurrent[1], concurrent[3]))


def test_kernel_threads_can_differ_from_torchs_on_the_calling_thread():
    """set_kernel_threads(n): the kernels called from this thread use n threads while torch's ops use its own
    count (the live viewer runs torch's ops serially); 0 goes back to torch's count. Results stay bit-identical."""
    from concurrent.futures import ThreadPoolExecutor

    from metegs.render.cpu_backend import load_extension, set_kernel_threads

    ext = load_extension()
    g, cam = random_scene(2000, seed=5, sh_degree=1), camera(80, 64, f=60.0)
    settings = RenderSettings(sh_degree=1)

    def run():
        out, grads, m2d = render_with_grads(CpuRasterizer(), g, cam, settings)
        return [out.rgb, out.depth, m2d, *grads.values()]

    previous = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        serial = run()
        set_kernel_threads(3)
        assert ext.get_num_threads() == 3 and torch.get_num_threads() == 1
        with ThreadPoolExecutor(1) as other:  # the setting belongs to the thread that made it
            assert other.submit(ext.get_num_threads).result() != 3
        split = run()
        set_kernel_threads(0)
        assert ext.get_num_threads() == 1
    finally:
        set_kernel_threads(0)
        torch.set_num_threads(previous)
    assert all(torch.equal(a, b) for a, b in zip(serial, split))


@pytest.mark.skipif("parallel backend: OpenMP" not in torch.__config__.parallel_info(), reason="torch without OpenMP")
def test_openmp_flags_follow_torchs_own_runtime_not_what_else_is_loaded(tmp_path, monkeypatch):
    """-fopenmp only where torch's runtime is the libgomp.so.1 a GCC build links; a renamed or another runtime in
    torch's lib folder means none, whatever else the process has loaded (pycolmap's own renamed libgomp)."""
    import subprocess
    import sys

    fake_torch = tmp_path / "torch"
    (fake_torch / "lib").mkdir(parents=True)
    monkeypatch.setattr(torch, "__file__", str(fake_torch / "__init__.py"))
    expected = {"libgomp.so.1": ["-fopenmp"], "libgomp-a34b3233.so.1": [], "libiomp5.so": [], "libomp.so": []}
    for name, flags in expected.items():
        runtime = fake_torch / "lib" / name
        runtime.write_bytes(b"")
        assert cpu_backend.openmp_flags() == flags, name
        runtime.unlink()
    monkeypatch.undo()
    probe = "from metegs.render import cpu_backend; print(cpu_backend.openmp_flags())"
    alone = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=300)
    after = subprocess.run(
        [sys.executable, "-c", "import pycolmap\n" + probe], capture_output=True, text=True, timeout=300
    )
    assert alone.returncode == 0 and after.returncode == 0, alone.stderr[-2000:] + after.stderr[-2000:]
    assert alone.stdout.split("\n")[-2] == after.stdout.split("\n")[-2] == str(cpu_backend.openmp_flags())


_TEAM_SCRIPT = """
import os, threading, torch
from metegs.render import cpu_backend
from metegs.render.cpu_backend import CpuRasterizer
from metegs.testing import camera, random_scene
torch.set_num_threads(2)
ext = cpu_backend.load_extension()
g, cam = random_scene(3000, seed=4, sh_degree=1), camera(96, 64, f=70.0)
g.means.requires_grad_(True)
def render():
    g.means.grad = None
    out = CpuRasterizer().render(g, cam)
    (out.rgb.sum() + out.depth.sum()).backward()
    return [out.rgb, out.depth, g.means.grad]
threads = lambda: len(os.listdir("/proc/self/task"))
torch.rand(1_000_000).exp_()  # torch's OpenMP team exists
torch.ones(1, requires_grad=True).exp().sum().backward()  # and autograd's threads, one per GPU (on a GPU machine: 19 -> 20)
before, on_main = threads(), render()
after_main, team_here = threads(), ext.uses_openmp_team()
box = {}
def other():
    box["team"] = ext.uses_openmp_team()
    box["run"] = render()
t = threading.Thread(target=other)
t.start(); t.join()
cpu_backend.set_kernel_threads(2)
team_with_override = ext.uses_openmp_team()
print(team_here, box["team"], team_with_override, before, after_main, threads(),
      all(torch.equal(a, b) for a, b in zip(on_main, box["run"], strict=True)))
"""


@pytest.mark.skipif(not cpu_backend.openmp_flags(), reason="torch does not run on GNU OpenMP here")
def test_kernels_called_from_the_main_thread_run_on_torchs_openmp_team():
    """From the main thread with torch's count, the kernels' chunks run on torch's OpenMP team (no pool worker is
    started); another thread, or a thread split, uses metegs' pool. Both give the same bits."""
    import subprocess
    import sys

    res = subprocess.run([sys.executable, "-c", _TEAM_SCRIPT], capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    team_main, team_other, team_split, before, after_main, after_other, same = res.stdout.split()[-7:]
    assert (team_main, team_other, team_split) == ("True", "False", "False")
    assert int(after_main) == int(before), "a render on the main thread started threads of its own"
    assert int(after_other) > int(before), "the render on another thread did not use the pool's worker"
    assert same == "True"


_IDLE_SCRIPT = """
import threading, time, torch
from metegs.render import cpu_backend
from metegs.testing import camera, random_scene
torch.set_num_threads(2)
ext = cpu_backend.load_extension()
g, cam = random_scene(3000, seed=2, sh_degree=1), camera(96, 64, f=70.0)
vm, K, c = cam.world_to_cameras()[0].float(), cam.intrinsics()[0].float(), cam.centers[0].float()
project = lambda: ext.project_forward(g.means, g.quats, g.scales, g.opacities, g.sh, vm, K, c, 96, 64, 0.01, 1e10,
                                      0.3, 1)
go, done = threading.Event(), threading.Event()
def other():  # jobs on the pool, each followed at once by one from the main thread (the team, where built)
    for _ in range(200):
        go.wait(); go.clear(); project(); done.set()
threading.Thread(target=other, daemon=True).start()
for _ in range(200):
    go.set(); done.wait(); done.clear(); project()
time.sleep(0.05)
cpu = time.process_time(); time.sleep(0.5)
print(time.process_time() - cpu)
"""


def test_the_pools_workers_sleep_once_jobs_from_other_threads_and_the_main_thread_are_done():
    """A pool worker still spinning after its job may join the next job from the main thread (torch's team); it must
    then go to sleep like any other time, not wake at once for ever (it used to burn a core while idle)."""
    import subprocess
    import sys

    res = subprocess.run([sys.executable, "-c", _IDLE_SCRIPT], capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    idle_cpu_s = float(res.stdout.split()[-1])
    assert idle_cpu_s < 0.05, f"{idle_cpu_s:.2f} s of CPU time in 0.5 s with nothing to do"


def test_kernel_threads_run_under_the_callers_denormal_mode():
    """Every chunk of a kernel runs with the calling thread's flush-to-zero / denormals-are-zero mode, also on pool
    workers started under another mode (the trainer sets torch.set_flush_denormal(True) on its own thread)."""
    ext = cpu_backend.load_extension()
    W = H = 256
    ys, xs = torch.meshgrid(torch.arange(8, 256, 16.0), torch.arange(8, 256, 16.0), indexing="ij")
    m2 = torch.stack([xs.flatten(), ys.flatten()], 1)
    n = len(m2)
    conics = torch.tensor([[0.01, 0.0, 0.01]]).repeat(n, 1)
    opac, depths = torch.full((n,), 0.5), torch.linspace(1.0, 2.0, n)
    # An earlier test (a training run) may have left flush-to-zero on here, and on torch's OpenMP workers (which
    # inherit it when created), where torch's own comparisons would read denormals as 0: values are checked by bits.
    torch.set_flush_denormal(False)
    colors = torch.full((n, 3), 1e-38)  # below the smallest normal float32 (1.18e-38)
    assert bool((colors.view(torch.int32) == torch.tensor(1e-38).view(torch.int32)).all())
    ids, offsets, rows = ext.bin_tiles(m2, conics, opac, torch.full((n, 2), 40.0), depths, W, H, True)
    previous = torch.get_num_threads()
    try:
        torch.set_num_threads(3)
        for flush in (False, True, False, True):
            torch.set_flush_denormal(flush)
            color = ext.forward(m2, conics, opac, colors, depths, ids, offsets, 16, 16, W, H, rows)[0]
            bits = color.view(torch.int32)  # positive floats: nonzero bits iff the value is not 0
            if flush:
                assert torch.count_nonzero(bits) == 0
            else:
                assert bool((bits > 0).all())
    finally:
        torch.set_flush_denormal(False)
        torch.set_num_threads(previous)


def test_compiled_finish_matches_finish_render_and_finite_differences():
    """Background and expected depth (FinishRender): the same bits as pipeline.finish_render in float32, and its
    gradients match finite differences in float64, pixels with no coverage (alpha 0, below the clamp) included."""
    from metegs.render.cpu_backend import FinishRender
    from metegs.render.pipeline import finish_render

    gen = torch.Generator().manual_seed(3)
    H, W = 7, 9
    alpha = torch.rand(H, W, generator=gen)
    alpha[0, :3] = 0.0
    color = torch.rand(H, W, 3, generator=gen) * alpha[..., None]
    depth_sum = torch.rand(H, W, generator=gen) * alpha * 4.0
    settings = RenderSettings(background=(0.2, 0.4, 0.6))
    bg = settings.background_tensor(color)
    rgb, depth = FinishRender.apply(color, alpha, depth_sum, bg)
    ref = finish_render(color, alpha, depth_sum, settings, None, None, 0)
    assert torch.equal(rgb, ref.rgb) and torch.equal(depth, ref.depth)

    inputs = [t.double().requires_grad_(True) for t in (color, alpha, depth_sum)]
    inputs[1].data.clamp_(min=1e-3)  # away from the clamp's kink for the finite differences
    assert torch.autograd.gradcheck(lambda c, a, d: FinishRender.apply(c, a, d, bg.double()), inputs)
    # the clamp: no depth gradient reaches alpha where alpha < 1e-10, as in the torch ops
    depth_sum[0, :3] = 0.5  # depth but no coverage: a zero-opacity contribution's sum
    a = alpha.double().clone().requires_grad_(True)
    d = depth_sum.double().clone().requires_grad_(True)
    _, dep = FinishRender.apply(color.double(), a, d, bg.double())
    dep.sum().backward()
    a_ref, d_ref = alpha.double().clone().requires_grad_(True), depth_sum.double().clone().requires_grad_(True)
    (d_ref / a_ref.clamp_min(1e-10)).sum().backward()
    torch.testing.assert_close(a.grad, a_ref.grad)
    torch.testing.assert_close(d.grad, d_ref.grad)


def test_thread_split_sets_this_threads_counts_and_restores_them():
    """Inside thread_split("cpu", n): torch's ops on n threads, the kernels on the count before; afterwards (also
    after an error) both as before. n = 0, n >= the count, or another backend: no change."""
    from metegs.render.cpu_backend import thread_split, thread_split_counts

    ext = cpu_backend.load_extension()
    previous = torch.get_num_threads()
    try:
        torch.set_num_threads(3)
        assert thread_split_counts("cpu", 1) == (1, 3)
        with thread_split("cpu", 1):
            assert (torch.get_num_threads(), ext.get_num_threads()) == (1, 3)
        assert (torch.get_num_threads(), ext.get_num_threads()) == (3, 3)
        with pytest.raises(ValueError), thread_split("cpu", 2):
            assert (torch.get_num_threads(), ext.get_num_threads()) == (2, 3)
            raise ValueError
        assert (torch.get_num_threads(), ext.get_num_threads()) == (3, 3)
        for backend, n in (("cpu", 0), ("cpu", 3), ("torch", 1)):
            assert thread_split_counts(backend, n) is None
            with thread_split(backend, n):
                assert (torch.get_num_threads(), ext.get_num_threads()) == (3, 3)
    finally:
        torch.set_num_threads(previous)


def test_peak_probe_runs_the_work_it_counts():
    """fma_throughput's chains end where their recurrence says (acc <- acc a + b from 0: n b with a = 1, and the
    fixed point b / (1 - a) with a = 1/2), so the work it times ran and used the caller's a and b. The probe is an
    extension of its own: the kernels' does not carry it."""
    from metegs.bench.peak import PROBE, measure_peak_gflops

    assert not hasattr(cpu_backend.load_extension(), "fma_throughput")
    ext = PROBE.load()
    chunks, iterations, lanes = 5, 1000, ext.chains * 16
    assert ext.chains in (6, 12)  # 12 chains of one AVX-512 register, 6 of two 32-byte (or four 16-byte) ones
    seconds, flops, checksum = ext.fma_throughput(chunks, iterations)
    assert seconds > 0 and flops == 2 * lanes * iterations * chunks
    assert checksum == chunks * lanes * iterations
    assert ext.fma_throughput(chunks, iterations, b=0.5)[2] == chunks * lanes * iterations / 2
    assert ext.fma_throughput(chunks, iterations, a=0.5, b=1.0)[2] == chunks * lanes * 2.0
    with pytest.raises(RuntimeError, match="positive"):
        ext.fma_throughput(0, iterations)
    assert 0 < measure_peak_gflops(iterations=200) < 1e5


def test_peak_probe_refuses_a_checksum_that_shows_missing_work(monkeypatch):
    class Short:
        def set_num_threads(self, n):
            pass

        def fma_throughput(self, chunks, iterations):
            return [1e-3, 2.0 * 12 * 16 * iterations * chunks, 12 * 16 * iterations * (chunks - 1)]

    from metegs.bench import peak

    monkeypatch.setattr(peak.PROBE, "load", lambda: Short())
    with pytest.raises(CpuExtensionError, match="checksum"):
        peak.measure_peak_gflops()


def test_peak_probe_runs_on_the_kernels_thread_count_under_a_thread_split(monkeypatch):
    """The probe is an extension of its own: under `--torch-threads 1` it must still use the kernels' threads (2),
    not torch's (1), and leave its own setting as it was."""
    from metegs.bench import peak

    calls = []

    class Spy:
        def set_num_threads(self, n):
            calls.append(("threads", n))

        def fma_throughput(self, chunks, iterations):
            calls.append(("chunks", chunks))
            flops = 2.0 * 12 * 16 * iterations * chunks
            return [1e-3, flops, flops / 2]

    monkeypatch.setattr(peak.PROBE, "load", lambda: Spy())
    previous = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        with cpu_backend.thread_split("cpu", 1):
            assert torch.get_num_threads() == 1
            peak.measure_peak_gflops(iterations=10)
    finally:
        torch.set_num_threads(previous)
    assert calls == [("threads", 2), ("chunks", peak.PEAK_PROBE_CHUNKS_PER_THREAD * 2), ("threads", 0)]
