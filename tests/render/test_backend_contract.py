"""What every registered rasteriser backend must do, whatever its implementation."""

import pytest
import torch

from metegs.gaussians.model import GaussianSet
from metegs.registry import registry
from metegs.render import RenderSettings
from metegs.render.select import backend_usable
from metegs.testing import random_scene


def backend_params():
    """Every registered backend; those unusable on this machine's CPU are skipped."""
    return [
        pytest.param(
            name,
            id=name,
            marks=[]
            if backend_usable(name, "cpu")
            else [pytest.mark.skip(reason=f"backend {name!r} is not available on this machine")],
        )
        for name in registry("rasterizer").names()
    ]


@pytest.fixture(params=backend_params())
def rasterizer(request):
    return registry("rasterizer").get(request.param)()


def test_means2d_gradient_is_available_for_densification(rasterizer, cam):
    g = random_scene(30, seed=4)
    means = g.means.clone().requires_grad_(True)
    out = rasterizer.render(GaussianSet(means, g.quats, g.scales, g.opacities, g.sh), cam)
    out.rgb.sum().backward()
    assert out.means2d.grad is not None and out.means2d.grad.shape == (30, 2)
    visible = out.radii > 0
    assert visible.any() and (out.means2d.grad[~visible] == 0).all()
    assert out.means2d.grad[visible].abs().sum() > 0


def test_empty_scene_renders_background_with_zero_gradients(rasterizer, cam):
    g = random_scene(10)
    g.means[:, 2] = -5.0  # all behind the camera
    params = [t.clone().requires_grad_(True) for t in (g.means, g.quats, g.scales, g.opacities, g.sh)]
    out = rasterizer.render(GaussianSet(*params), cam, RenderSettings(background=(0.1, 0.2, 0.3)))
    assert out.num_intersections == 0
    assert torch.allclose(out.rgb, torch.tensor([0.1, 0.2, 0.3]).expand_as(out.rgb))
    assert (out.alpha == 0).all()
    out.rgb.sum().backward()
    assert all(torch.isfinite(p.grad).all() and (p.grad == 0).all() for p in params)
