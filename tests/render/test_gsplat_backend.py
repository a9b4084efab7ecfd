"""The `gsplat` CUDA backend: never imported without CUDA; on a GPU, held to the torch reference."""

import subprocess
import sys

import pytest
import torch

from metegs.gaussians.model import GaussianSet
from metegs.render import gsplat_backend
from metegs.render.base import RenderSettings
from metegs.render.gsplat_backend import GsplatRasterizer
from metegs.render.torch_backend import TorchRasterizer
from metegs.testing import camera, random_scene

PARAMS = ("means", "quats", "scales", "opacities", "sh")


def test_not_available_and_not_imported_on_cpu():
    code = (
        "import sys, torch\n"
        "from metegs.render.select import resolve_backend\n"
        "from metegs.render.gsplat_backend import GsplatRasterizer\n"
        "assert not GsplatRasterizer.available('cpu')\n"
        "print(resolve_backend('auto', 'cpu'))\n"
        "assert 'gsplat' not in sys.modules, 'gsplat was imported'\n"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() in ("cpu", "torch")


def test_render_refuses_cpu_tensors(cam):
    with pytest.raises(gsplat_backend.GsplatUnavailableError, match="CUDA tensors"):
        GsplatRasterizer().render(random_scene(4), cam)


def test_unavailable_reason_is_kept_and_warned_once(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr(gsplat_backend.GSPLAT, "value", None)
    monkeypatch.setattr(gsplat_backend.GSPLAT, "error", None)
    monkeypatch.setattr(gsplat_backend.GSPLAT, "warned", False)
    with pytest.warns(gsplat_backend.GsplatBackendWarning, match="no CUDA device"):
        assert not GsplatRasterizer.available("cuda")
    assert not GsplatRasterizer.available("cuda")  # cached, no second warning (warnings are errors here)


cuda = pytest.mark.skipif(
    not (torch.cuda.is_available() and GsplatRasterizer.available("cuda")), reason="needs CUDA and gsplat"
)


def _render(rasterizer, g: GaussianSet, cam, settings):
    params = {k: getattr(g, k).detach().clone().cuda().requires_grad_(True) for k in PARAMS}
    out = rasterizer.render(GaussianSet(**params), cam, settings)
    target = torch.rand(out.rgb.shape, generator=torch.Generator().manual_seed(0)).cuda()
    loss = ((out.rgb - target) ** 2).sum() + 0.1 * out.alpha.sum()
    loss.backward()
    return out, {k: p.grad for k, p in params.items()}


@cuda
@pytest.mark.parametrize(("n", "width", "height", "sh_degree"), [(300, 70, 45, 3), (2000, 160, 120, 1)])
def test_matches_torch_reference_on_cuda(n, width, height, sh_degree):
    g = random_scene(n, seed=n, sh_degree=sh_degree)
    cam = camera(width, height, f=0.8 * width)
    settings = RenderSettings(background=(0.2, 0.4, 0.6), sh_degree=sh_degree)
    ref, ref_grads = _render(TorchRasterizer(chunk=n), g, cam, settings)
    out, grads = _render(GsplatRasterizer(), g, cam, settings)
    torch.testing.assert_close(out.rgb, ref.rgb, rtol=0, atol=1e-5)
    torch.testing.assert_close(out.alpha, ref.alpha, rtol=0, atol=1e-5)
    assert torch.equal(out.radii > 0, ref.radii > 0)
    for k in PARAMS:
        scale = ref_grads[k].abs().max().clamp_min(1e-12)
        torch.testing.assert_close(grads[k] / scale, ref_grads[k] / scale, rtol=1e-4, atol=1e-5, msg=k)
    assert out.means2d.grad is not None and out.means2d.grad.shape == (n, 2)
