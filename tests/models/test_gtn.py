"""The Gaussian Transformation Network: encodings, one-sided bounds, detached inputs."""

import math

import torch

from metegs.gaussians.model import GaussianSet
from metegs.models.gtn import GaussianTransformationNetwork, GTNConfig, positional_encoding


def _gaussians(n=200, seed=0):
    g = torch.Generator().manual_seed(seed)
    return GaussianSet(
        torch.randn(n, 3, generator=g),
        torch.randn(n, 4, generator=g),
        torch.rand(n, 3, generator=g) * 0.1 + 0.01,
        torch.rand(n, generator=g),
        torch.randn(n, 1, 3, generator=g),
    )


def test_positional_encoding_layout_and_values():
    x = torch.tensor([[0.3, -1.0, 2.0]])
    pe = positional_encoding(x, 3)
    assert pe.shape == (1, 21)
    assert torch.equal(pe[0, :3], x[0])
    # sin block: frequency-major, then coordinate: sin(2^k x_j) at 3 + 3k + j
    assert math.isclose(float(pe[0, 3 + 3 * 2 + 1]), math.sin(4 * -1.0), rel_tol=1e-6)
    assert math.isclose(float(pe[0, 3 + 9 + 3 * 1 + 2]), math.cos(2 * 2.0), rel_tol=1e-6)
    assert positional_encoding(x, 0).shape == (1, 3)


def test_input_size_matches_the_reference_91():
    net = GaussianTransformationNetwork(GTNConfig(), torch.zeros(3), 1.0)
    assert net.trunk[0].in_features == 91
    assert sum(isinstance(m, torch.nn.ReLU) for m in net.trunk) == 3


def test_factors_are_one_sided_and_bounded_even_for_wild_weights():
    net = GaussianTransformationNetwork(GTNConfig(max_factor=1.1), torch.zeros(3), 2.0)
    with torch.no_grad():
        for p in net.parameters():
            p.normal_(0, 50.0)
    g = _gaussians()
    ds, dr = net.factors(g.means, g.scales, g.quats, torch.tensor([5.0, 0.0, 1.0]))
    assert ds.shape == (200, 3) and dr.shape == (200, 4)
    for d in (ds, dr):
        assert bool((d >= 1.0).all() and (d <= 1.1 + 1e-6).all())
    assert bool((ds > 1.0).any() and (ds < 1.1).any() or (ds == 1.1).any())


def test_inputs_are_detached_but_scales_still_get_the_product_gradient():
    net = GaussianTransformationNetwork(GTNConfig(), torch.zeros(3), 1.0)
    g = _gaussians(50)
    means = g.means.clone().requires_grad_(True)
    scales = g.scales.clone().requires_grad_(True)
    out = net(GaussianSet(means, g.quats, scales, g.opacities, g.sh), torch.tensor([3.0, 1.0, 0.5]))
    ds, _ = net.factors(g.means, g.scales, g.quats, torch.tensor([3.0, 1.0, 0.5]))
    out.scales.sum().backward()
    assert means.grad is None  # positions pass through unchanged and feed the MLP detached
    assert torch.allclose(scales.grad, ds)  # d(s·δs)/ds with δs treated as a constant of s
    assert out.means is means and torch.equal(out.opacities, g.opacities) and torch.equal(out.sh, g.sh)


def _reference_factor(raw):
    """The Deblurring-3DGS head bound."""
    return (0.01 * raw + 0.99).clamp(1.0, 1.1)


def test_reference_clamp_starves_the_network_of_gradients_ours_does_not():
    raw = (torch.randn(1000, generator=torch.Generator().manual_seed(0)) * 0.1).requires_grad_(True)
    _reference_factor(raw).sum().backward()
    assert float(raw.grad.abs().sum()) == 0.0  # all on the lower clamp: nothing to learn from
    net = GaussianTransformationNetwork(GTNConfig(), torch.zeros(3), 1.0)
    g = _gaussians(100)
    ds, _ = net.factors(g.means, g.scales, g.quats, torch.zeros(3))
    ds.sum().backward()
    assert all(p.grad is not None and float(p.grad.abs().sum()) > 0 for p in net.head_scale.parameters())
    assert torch.allclose(ds, torch.full_like(ds, 1.0 + 0.1 * 0.01), atol=2e-3)


def test_the_network_learns_to_widen_where_the_photo_asks():
    torch.manual_seed(0)
    net = GaussianTransformationNetwork(GTNConfig(), torch.zeros(3), 1.0)
    g = _gaussians(64)
    cam = torch.tensor([2.0, 0.0, 0.0])
    opt = torch.optim.Adam(net.parameters(), lr=1e-2)
    start = net(g, cam).scales.mean().item()
    for _ in range(200):
        loss = ((net(g, cam).scales - g.scales * 1.08) ** 2).sum()
        opt.zero_grad()
        loss.backward()
        opt.step()
    end = net(g, cam).scales.mean().item()
    assert end > start * 1.03
    assert torch.allclose(net(g, cam).scales, g.scales * 1.08, rtol=0.02)


def test_factorised_first_layer_equals_the_plain_91d_mlp():
    torch.manual_seed(1)
    net = GaussianTransformationNetwork(GTNConfig(), torch.tensor([0.5, -1.0, 2.0]), 3.0)
    with torch.no_grad():
        for p in net.parameters():
            p.normal_(0, 0.3)
    g = _gaussians(64)
    cam = torch.tensor([4.0, 1.0, -2.0])
    ds, dr = net.factors(g.means, g.scales, g.quats, cam)
    x = (g.means - net.centre) / net.extent
    v = ((cam - net.centre) / net.extent).reshape(1, 3).expand(64, 3)
    q = g.quats / g.quats.norm(dim=-1, keepdim=True)
    feats = torch.cat([positional_encoding(x, 3), positional_encoding(v, 10), torch.log(g.scales), q], -1)
    h = net.trunk(feats)
    b = math.log(0.01 / 0.99)
    assert torch.allclose(ds, 1 + 0.1 * torch.sigmoid(net.head_scale(h) + b), atol=1e-6)
    assert torch.allclose(dr, 1 + 0.1 * torch.sigmoid(net.head_rot(h) + b), atol=1e-6)


def test_transforming_only_what_the_view_may_see_renders_the_same():
    from metegs.models.gtn import may_be_visible
    from metegs.render.base import RenderSettings
    from metegs.render.torch_backend import TorchRasterizer
    from metegs.testing import camera, random_scene

    g = random_scene(300, seed=3)
    spread = torch.Generator().manual_seed(4)
    g.means[:150] += (torch.rand(150, 3, generator=spread) - 0.5) * torch.tensor([12.0, 12.0, 8.0])  # many outside
    g.scales[:5] *= 20.0  # a few wide ones whose centre is outside but whose footprint reaches in
    cam = camera(48, 36, f=40.0)
    only = may_be_visible(g, cam, growth=1.1)
    assert 0 < int(only.sum()) < len(g) * 0.8
    net = GaussianTransformationNetwork(GTNConfig(init_growth=0.5), torch.zeros(3), 3.0)
    settings = RenderSettings(background=(0.1, 0.2, 0.3))
    centre = torch.tensor([0.3, -0.2, -1.0])
    full = TorchRasterizer().render(net(g, centre), cam, settings)
    part = TorchRasterizer().render(net(g, centre, only), cam, settings)
    assert (full.radii > 0)[~only].sum() == 0  # nothing left out reaches the image
    torch.testing.assert_close(part.rgb, full.rgb, rtol=0, atol=1e-6)
    torch.testing.assert_close(part.alpha, full.alpha, rtol=0, atol=1e-6)
    grads = [torch.autograd.grad(r.rgb.sum(), list(net.parameters())) for r in (full, part)]
    for a, b in zip(*grads):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-7)
