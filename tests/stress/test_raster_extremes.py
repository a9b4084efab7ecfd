"""Rasterisation under extreme Gaussians: every usable backend renders finite images with finite gradients.

Cases (each on its own and mixed into an ordinary scene): scales of 1e-8 and 1e4 (and up to 1e30, beyond
float32's square), near-zero and zero quaternions, saturated opacities (exactly 1, 1 − 1e-7, exactly 0), points
1e6 m away, on the near plane and just in front of it, behind the camera and at z = 0, huge SH colours.
Culled Gaussians must not change what the others render.
"""

import pytest
import torch

from metegs.gaussians.model import GaussianSet
from metegs.registry import registry
from metegs.render import RenderSettings
from metegs.render.select import backend_usable
from metegs.testing import camera, random_scene

NEAR = RenderSettings().near
BACKGROUND = (0.1, 0.2, 0.3)


def backends():
    return [
        pytest.param(
            name,
            id=name,
            marks=[] if backend_usable(name, "cpu") else [pytest.mark.skip(reason=f"backend {name!r} unavailable")],
        )
        for name in registry("rasterizer").names()
    ]


def _edit(case: str, g: GaussianSet) -> GaussianSet:
    m, q, s, o, sh = (t.clone() for t in (g.means, g.quats, g.scales, g.opacities, g.sh))
    if case == "scale-1e-8":
        s[:] = 1e-8
    elif case == "scale-1e4":
        s[:] = 1e4
    elif case == "scale-1e19":
        s[:] = 1e19  # the covariance overflows float32
    elif case == "scale-1e30":
        s[:] = 1e30
    elif case == "anisotropic-1e-8-1e4":
        s[:, 0], s[:, 1], s[:, 2] = 1e-8, 1e4, 1.0
    elif case == "quat-1e-30":
        q[:] = 1e-30
    elif case == "quat-zero":
        q[:] = 0.0
    elif case == "quat-tiny-random":
        q[:] = q * 1e-12
    elif case == "opacity-1":
        o[:] = 1.0
    elif case == "opacity-1-minus-eps":
        o[:] = 1.0 - 1e-7
    elif case == "opacity-0":
        o[:] = 0.0
    elif case == "far-1e6":
        m[:, 2] = 1e6
        m[:, :2] *= 1e5
    elif case == "far-1e6-large":
        m[:, 2] = 1e6
        m[:, :2] *= 1e5
        s[:] = 1e4
    elif case == "on-near-plane":
        m[:, 2] = NEAR
    elif case == "just-inside-near":
        m[:, 2] = NEAR * (1 + 1e-5)
    elif case == "behind":
        m[:, 2] = -1.0
    elif case == "z-zero":
        m[:, 2] = 0.0
    elif case == "sh-1e6":
        sh[:] = 1e6
    else:
        raise ValueError(case)
    return GaussianSet(m, q, s, o, sh)


CASES = [
    "scale-1e-8",
    "scale-1e4",
    "scale-1e19",
    "scale-1e30",
    "anisotropic-1e-8-1e4",
    "quat-1e-30",
    "quat-zero",
    "quat-tiny-random",
    "opacity-1",
    "opacity-1-minus-eps",
    "opacity-0",
    "far-1e6",
    "far-1e6-large",
    "on-near-plane",
    "just-inside-near",
    "behind",
    "z-zero",
    "sh-1e6",
]


def _render_and_grads(rasterizer, g: GaussianSet):
    params = [t.clone().requires_grad_(True) for t in (g.means, g.quats, g.scales, g.opacities, g.sh)]
    out = rasterizer.render(GaussianSet(*params), camera(), RenderSettings(background=BACKGROUND))
    (out.rgb.sum() + out.alpha.sum() + 1e-3 * out.depth.sum()).backward()
    return out, params


@pytest.mark.parametrize("backend", backends())
@pytest.mark.parametrize("case", CASES)
def test_extreme_gaussians_render_finite_with_finite_gradients(backend, case):
    rasterizer = registry("rasterizer").get(backend)()
    out, params = _render_and_grads(rasterizer, _edit(case, random_scene(24, seed=3)))
    for name, t in (("rgb", out.rgb), ("alpha", out.alpha), ("depth", out.depth)):
        assert torch.isfinite(t).all(), f"{backend}/{case}: non-finite {name}"
    assert (out.alpha >= 0).all() and (out.alpha <= 1 + 1e-5).all()
    for name, p in zip(("means", "quats", "scales", "opacities", "sh"), params):
        assert p.grad is not None and torch.isfinite(p.grad).all(), f"{backend}/{case}: non-finite d/d{name}"


@pytest.mark.parametrize("backend", backends())
@pytest.mark.parametrize("case", ["behind", "z-zero", "on-near-plane", "opacity-0", "scale-1e30"])
def test_culled_extremes_do_not_change_the_other_gaussians(backend, case):
    """Gaussians that cannot be drawn leave the render of an ordinary scene exactly as it was."""
    rasterizer = registry("rasterizer").get(backend)()
    base = random_scene(30, seed=5)
    extreme = _edit(case, random_scene(10, seed=6))
    alone = rasterizer.render(base, camera(), RenderSettings(background=BACKGROUND))
    mixed = rasterizer.render(GaussianSet.cat([base, extreme]), camera(), RenderSettings(background=BACKGROUND))
    torch.testing.assert_close(mixed.rgb, alone.rgb, atol=1e-6, rtol=0)
    torch.testing.assert_close(mixed.alpha, alone.alpha, atol=1e-6, rtol=0)


@pytest.mark.parametrize("backend", backends())
def test_every_extreme_at_once_in_one_scene(backend):
    rasterizer = registry("rasterizer").get(backend)()
    parts = [random_scene(10, seed=11)] + [_edit(c, random_scene(4, seed=20 + i)) for i, c in enumerate(CASES)]
    out, params = _render_and_grads(rasterizer, GaussianSet.cat(parts))
    assert all(torch.isfinite(t).all() for t in (out.rgb, out.alpha, out.depth))
    assert all(torch.isfinite(p.grad).all() for p in params)
    assert out.num_intersections > 0


def _overflow_camera():
    """The 64x48 view of the 1000x-learning-rate run that found the float32-overflow bug below."""
    from metegs.cameras import Cameras

    c2w = torch.tensor(
        [
            [-0.99984902, -0.00451112, 0.01677877, 0.00135910],
            [-0.01737462, 0.25959924, -0.96556014, 8.49479675],
            [0.0, -0.96570587, -0.25963843, 3.20628571],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )
    return Cameras.create(c2w[None], 55.4256, 55.4256, 32.0, 24.0, 64, 48)


def test_cpu_projection_gradients_stay_finite_near_float32_overflow():
    """Found by a 1000x-learning-rate run: a Gaussian with scale ~7e8 at ~10 m (det of its 2D covariance
    ~3e38) got NaN gradients from the cpu backend (a*a / det^2 = inf / inf in the conic backward), finite ones
    (zero: its alpha is saturated) from torch."""
    if not backend_usable("cpu", "cpu"):
        pytest.skip("cpu backend unavailable")
    cam = _overflow_camera()
    sh = torch.zeros(1, 16, 3)
    sh[0, 0] = torch.tensor([8.9, 9.2, 8.36])
    g = GaussianSet(
        torch.tensor([[8.4528, -2.3992, 4.1480]]),
        torch.tensor([[1.0, 0.0, 3.7874, -3.7876]]),
        torch.full((1, 3), 6.93e8),
        torch.tensor([1.0]),
        sh,
    )
    grads = {}
    for name in ("torch", "cpu"):
        params = [t.clone().requires_grad_(True) for t in (g.means, g.quats, g.scales, g.opacities, g.sh)]
        out = registry("rasterizer").get(name)().render(GaussianSet(*params), cam, RenderSettings())
        assert out.num_intersections > 0, f"{name}: the huge Gaussian was culled"
        out.rgb.sum().backward()
        assert all(torch.isfinite(p.grad).all() for p in params), f"{name}: non-finite gradients"
        grads[name] = [p.grad for p in params]
    for got, ref in zip(grads["cpu"], grads["torch"], strict=True):
        torch.testing.assert_close(got, ref, rtol=1e-4, atol=1e-3)


def test_cpu_projection_gradients_are_accurate_near_float32_overflow():
    """ProjectShade alone, with non-zero conic cotangents, on Gaussians whose float32 2D covariance entries
    (~2e19) square past float32's range while their determinant (~1e38) does not: the float32 cpu gradients
    match the float64 torch reference. (The float32 torch reference itself underflows here: its quats and
    scales gradients, ~1e-28, are not compared with.)"""
    if not backend_usable("cpu", "cpu"):
        pytest.skip("cpu backend unavailable")
    from metegs.render.cpu_backend import ProjectShade
    from metegs.render.projection import project_gaussians

    cam = _overflow_camera()
    W, H = 64, 48
    f64 = torch.float64
    means = torch.tensor([[8.4528, -2.3992, 4.1480]], dtype=f64).repeat(4, 1)
    quats = torch.tensor(
        [[1.0, 0.0, 3.7874, -3.7876], [0.3, 0.5, -0.2, 0.7], [1.0, 0.0, 0.0, 0.0], [0.9, 0.1, 0.4, -0.2]], dtype=f64
    )
    scales = torch.tensor(
        [[6.93e8, 6.93e8, 6.93e8], [6.9e8, 4e8, 1.5e8], [8e8, 2e8, 5e8], [1.2e9, 1e6, 3e8]], dtype=f64
    )
    opacities = torch.full((4,), 0.5, dtype=f64)
    cot = [
        torch.randn(s, dtype=f64, generator=torch.Generator().manual_seed(i))
        for i, s in enumerate([(4, 2), (4, 3), (4,)])
    ]

    def run(dt, fn):
        viewmat, K = cam.world_to_cameras()[0].to(dt), cam.intrinsics()[0].to(dt)
        params = [t.to(dt).requires_grad_(True) for t in (means, quats, scales)]
        outs = fn(*params, viewmat, K, dt)
        sum((o * c.to(dt)).sum() for o, c in zip(outs[:3], cot)).backward()
        return [o.detach() for o in outs], [p.grad for p in params]

    def ours(m, q, s, viewmat, K, dt):
        sh = torch.zeros(4, 1, 3, dtype=dt)
        campos = cam.centers[0].to(dt)
        outs = ProjectShade.apply(m, q, s, opacities.to(dt), sh, viewmat, K, campos, W, H, 0.01, 1e10, 0.3, 0)
        return outs[0], outs[1], outs[2], outs[4]

    def reference(m, q, s, viewmat, K, dt):
        p = project_gaussians(m, q, s, viewmat, K, W, H, opacities=opacities.to(dt))
        return p.means2d, p.conics, p.depths, p.radii

    (out, grads), (ref, ref_grads) = run(torch.float32, ours), run(f64, reference)
    assert (ref[3] > 0).all() and (out[3] > 0).all(), "the huge Gaussians must be drawn"
    torch.testing.assert_close(out[1].double(), ref[1], rtol=1e-5, atol=0)
    for name, got, want in zip(("means", "quats", "scales"), grads, ref_grads, strict=True):
        assert torch.isfinite(got).all(), f"non-finite d/d{name}"
        scale = want.abs().max()
        torch.testing.assert_close(
            got.double() / scale, want / scale, rtol=1e-4, atol=1e-5, msg=lambda m, n=name: f"{n}: {m}"
        )
