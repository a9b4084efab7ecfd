"""Tests of metegs.eval: PSNR closed form, SSIM parity with skimage and gradients, LPIPS loading paths."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from skimage.metrics import structural_similarity

from metegs.errors import MetegsError
from metegs.eval import backbones
from metegs.eval import lpips as lp
from metegs.eval.metrics import evaluate_images, psnr, ssim, ssim_map

# ------------------------------------------------------------------------------------------------- PSNR


def test_psnr_constant_offset_is_20db():
    target = torch.rand(2, 8, 9, 3) * 0.8
    assert float(psnr(target + 0.1, target)) == pytest.approx(20.0, abs=1e-4)


def test_psnr_mask_ignores_unmasked_pixels():
    target = torch.zeros(6, 6, 3)
    pred = target.clone()
    pred[:3] = 0.1
    pred[3:] = 0.9  # excluded by the mask
    mask = torch.zeros(6, 6, dtype=torch.bool)
    mask[:3] = True
    assert float(psnr(pred, target, mask)) == pytest.approx(20.0, abs=1e-4)
    assert float(psnr(pred, target, mask[..., None])) == pytest.approx(20.0, abs=1e-4)


def test_psnr_identical_is_inf_and_shape_mismatch_raises():
    x = torch.rand(4, 4, 3)
    assert math.isinf(float(psnr(x, x)))
    with pytest.raises(ValueError):
        psnr(x, torch.rand(4, 5, 3))


# ------------------------------------------------------------------------------------------------- SSIM


def _skimage_ssim(a: torch.Tensor, b: torch.Tensor) -> float:
    return structural_similarity(
        a.double().numpy(),
        b.double().numpy(),
        channel_axis=-1,
        data_range=1.0,
        gaussian_weights=True,
        sigma=1.5,
        use_sample_covariance=False,
    )


def _structured(h: int, w: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    yy, xx = torch.meshgrid(torch.linspace(0, 1, h), torch.linspace(0, 1, w), indexing="ij")
    base = torch.stack([0.5 + 0.4 * torch.sin(8 * xx + 3 * yy), yy, (xx > 0.5).float() * 0.7 + 0.1], dim=-1)
    noisy = (base + 0.05 * torch.randn(base.shape, generator=g)).clamp(0, 1)
    blurred = (0.5 * base + 0.25 * base.roll(1, 0) + 0.25 * base.roll(1, 1)).clamp(0, 1)
    return noisy, blurred


@pytest.mark.parametrize("hw", [(40, 50), (64, 64), (11, 23), (97, 31)])
def test_ssim_matches_skimage_random(hw):
    g = torch.Generator().manual_seed(hw[0] * 1000 + hw[1])
    a = torch.rand(*hw, 3, generator=g)
    b = (a + 0.2 * torch.randn(*hw, 3, generator=g)).clamp(0, 1)
    assert float(ssim(a, b)) == pytest.approx(_skimage_ssim(a, b), abs=1e-4)
    c = torch.rand(*hw, 3, generator=g)  # unrelated images: SSIM near 0
    assert float(ssim(a, c)) == pytest.approx(_skimage_ssim(a, c), abs=1e-4)


@pytest.mark.parametrize("hw", [(40, 50), (64, 64)])
def test_ssim_matches_skimage_structured(hw):
    a, b = _structured(*hw, seed=1)
    assert float(ssim(a, b)) == pytest.approx(_skimage_ssim(a, b), abs=1e-4)


def test_ssim_batched_is_mean_of_per_image():
    a, b = torch.rand(3, 20, 24, 3), torch.rand(3, 20, 24, 3)
    per = [_skimage_ssim(a[i], b[i]) for i in range(3)]
    assert float(ssim(a, b)) == pytest.approx(float(np.mean(per)), abs=1e-4)


def test_ssim_identity_and_map_shapes():
    x = torch.rand(2, 30, 20, 3)
    assert float(ssim(x, x)) == pytest.approx(1.0, abs=1e-6)
    assert float(ssim(x, x, crop_border=False)) == pytest.approx(1.0, abs=1e-6)
    assert ssim_map(x, x).shape == (2, 20, 10, 3)
    assert ssim_map(x, x, crop_border=False).shape == (2, 30, 20, 3)


def test_ssim_uncropped_matches_dense_reference():
    """crop_border=False equals the 3DGS reference: full 11x11 Gaussian window, zero 'same' padding."""
    a, b = torch.rand(1, 3, 18, 21, dtype=torch.float64), torch.rand(1, 3, 18, 21, dtype=torch.float64)
    x = torch.arange(11, dtype=torch.float64) - 5
    g = torch.exp(-(x**2) / (2 * 1.5**2))
    g = g / g.sum()
    w = (g[:, None] * g[None, :]).expand(3, 1, 11, 11)
    f = lambda t: torch.nn.functional.conv2d(t, w, padding=5, groups=3)
    mu1, mu2 = f(a), f(b)
    s11, s22, s12 = f(a * a) - mu1**2, f(b * b) - mu2**2, f(a * b) - mu1 * mu2
    c1, c2 = 0.01**2, 0.03**2
    ref = ((2 * mu1 * mu2 + c1) * (2 * s12 + c2)) / ((mu1**2 + mu2**2 + c1) * (s11 + s22 + c2))
    ours = ssim(a.permute(0, 2, 3, 1), b.permute(0, 2, 3, 1), crop_border=False)
    assert float(ours) == pytest.approx(float(ref.mean()), abs=1e-10)


@pytest.mark.parametrize("crop_border", [True, False])
def test_ssim_gradcheck(crop_border):
    g = torch.Generator().manual_seed(0)
    a = torch.rand(16, 16, 3, dtype=torch.float64, generator=g, requires_grad=True)
    b = torch.rand(16, 16, 3, dtype=torch.float64, generator=g)
    assert torch.autograd.gradcheck(lambda x: ssim(x, b, crop_border=crop_border), (a,), eps=1e-6, atol=1e-5)


def test_ssim_errors():
    with pytest.raises(ValueError, match="smaller than"):
        ssim(torch.rand(8, 30, 3), torch.rand(8, 30, 3))
    with pytest.raises(ValueError, match="shapes differ"):
        ssim(torch.rand(20, 30, 3), torch.rand(20, 31, 3))
    with pytest.raises(ValueError, match="channels last"):
        ssim(torch.rand(20, 30), torch.rand(20, 30))


# ------------------------------------------------------------------------------------------------ LPIPS

SHARED_HEADS = Path(__file__).resolve().parents[3] / "shared" / "data" / "weights" / "lpips-linear" / "weights" / "v0.1"


def _write_fake_weights(tmp_path: Path, net: str) -> tuple[Path, Path]:
    """Random backbone saved as a torchvision full-model state dict, and random heads in the official format."""
    torch.manual_seed(0)
    spec = backbones.BACKBONES[net]
    features = spec.build()
    state = {f"features.{k}": v for k, v in features.state_dict().items()}
    state["classifier.1.weight"] = torch.zeros(4, 4)  # torchvision files also hold the classifier: ignored
    backbone = tmp_path / spec.filename
    torch.save(state, backbone)
    heads_dir = tmp_path / "heads"
    heads_dir.mkdir()
    heads = {f"lin{i}.model.1.weight": torch.rand(1, c, 1, 1) for i, c in enumerate(spec.channels)}
    torch.save(heads, heads_dir / f"{net}.pth")
    return backbone, heads_dir


@pytest.fixture
def empty_hub(tmp_path, monkeypatch):
    """Empty torch hub dir and no env overrides; the previous hub dir is restored afterwards."""
    old = torch.hub.get_dir()
    torch.hub.set_dir(str(tmp_path / "hub"))
    monkeypatch.delenv(lp.BACKBONE_ENV, raising=False)
    monkeypatch.delenv(lp.HEADS_ENV, raising=False)
    yield tmp_path / "hub"
    torch.hub.set_dir(old)


def test_backbone_layout_matches_torchvision_keys():
    alex = lp.alexnet_features().state_dict()
    assert list(alex) == [f"{i}.{p}" for i in (0, 3, 6, 8, 10) for p in ("weight", "bias")]
    assert alex["0.weight"].shape == (64, 3, 11, 11)
    vgg = lp.vgg16_features()
    assert len(vgg) == 31
    convs = [i for i, m in enumerate(vgg) if isinstance(m, torch.nn.Conv2d)]
    assert convs == [0, 2, 5, 7, 10, 12, 14, 17, 19, 21, 24, 26, 28]


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_lpips_with_saved_random_weights(tmp_path, empty_hub, net):
    backbone, heads_dir = _write_fake_weights(tmp_path, net)
    model = lp.load_lpips(net, backbone_path=backbone, heads_dir=heads_dir)
    assert model.net == net
    g = torch.Generator().manual_seed(1)
    x = torch.rand(2, 64, 64, 3, generator=g)
    y = torch.rand(2, 64, 64, 3, generator=g)
    with torch.no_grad():
        d_xx, d_xy, d_yx = model(x, x), model(x, y), model(y, x)
    assert d_xx.shape == (2,)
    assert torch.allclose(d_xx, torch.zeros(2), atol=1e-7)
    assert (d_xy > 0).all()
    assert torch.allclose(d_xy, d_yx, rtol=1e-5, atol=1e-7)
    assert float(model(x[0], y[0])) == pytest.approx(float(d_xy[0]), rel=1e-5)
    # folders (holding the torchvision file name) and env vars work too
    model2 = lp.load_lpips(net, backbone_path=tmp_path, heads_dir=heads_dir / f"{net}.pth")
    assert torch.allclose(model2(x, y), d_xy)


def test_lpips_env_vars_and_functional(tmp_path, empty_hub, monkeypatch):
    backbone, heads_dir = _write_fake_weights(tmp_path, "alex")
    monkeypatch.setenv(lp.BACKBONE_ENV, str(backbone))
    monkeypatch.setenv(lp.HEADS_ENV, str(heads_dir))
    x, y = torch.rand(48, 40, 3), torch.rand(48, 40, 3)
    model, reason = lp.try_load_lpips("alex")
    assert reason is None and model is not None
    assert float(lp.lpips(x, y)) == pytest.approx(float(model(x, y)), rel=1e-6)


def test_lpips_hub_cache_is_used(tmp_path, empty_hub):
    spec = backbones.BACKBONES["alex"]
    backbone, heads_dir = _write_fake_weights(tmp_path, "alex")
    (empty_hub / "checkpoints").mkdir(parents=True)
    backbone.rename(empty_hub / "checkpoints" / spec.filename)
    assert lp.resolve_backbone_file("alex") == empty_hub / "checkpoints" / spec.filename
    model, reason = lp.try_load_lpips("alex", heads_dir=heads_dir)
    assert reason is None and isinstance(model, lp.LPIPS)


def test_lpips_gradients_flow_to_inputs(tmp_path, empty_hub):
    backbone, heads_dir = _write_fake_weights(tmp_path, "alex")
    model = lp.load_lpips("alex", backbone_path=backbone, heads_dir=heads_dir)
    x = torch.rand(64, 64, 3, requires_grad=True)
    model(x, torch.rand(64, 64, 3)).backward()
    assert x.grad is not None and x.grad.abs().sum() > 0
    assert not any(p.requires_grad for p in model.parameters())


def test_lpips_missing_backbone_gives_reason(tmp_path, empty_hub):
    _, heads_dir = _write_fake_weights(tmp_path, "alex")
    model, reason = lp.try_load_lpips("alex", heads_dir=heads_dir)
    assert model is None
    assert "alexnet-owt-7be5be79.pth" in reason
    assert str(empty_hub / "checkpoints") in reason
    assert lp.BACKBONE_ENV in reason and "backbone_path" in reason
    with pytest.raises(lp.WeightsUnavailable) as info:
        lp.load_lpips("vgg", heads_dir=heads_dir)
    assert isinstance(info.value, MetegsError)
    assert info.value.part == "backbone" and "vgg16-397923af.pth" in str(info.value)


def test_lpips_explicit_missing_paths_do_not_fall_back(tmp_path, empty_hub):
    backbone, heads_dir = _write_fake_weights(tmp_path, "alex")
    model, reason = lp.try_load_lpips("alex", backbone_path=tmp_path / "nope.pth", heads_dir=heads_dir)
    assert model is None and "nope.pth" in reason
    model, reason = lp.try_load_lpips("alex", backbone_path=backbone, heads_dir=tmp_path / "empty")
    assert model is None and "heads" in reason and lp.HEADS_ENV in reason


def test_lpips_mismatched_checkpoint_is_reported(tmp_path, empty_hub):
    backbone, heads_dir = _write_fake_weights(tmp_path, "alex")
    vgg_file = tmp_path / "vgg16-397923af.pth"
    torch.save(lp.vgg16_features().state_dict(), vgg_file)
    model, reason = lp.try_load_lpips("alex", backbone_path=vgg_file, heads_dir=heads_dir)
    assert model is None and "does not match" in reason
    (tmp_path / "bad.pth").write_bytes(b"not a checkpoint")
    model, reason = lp.try_load_lpips("alex", backbone_path=tmp_path / "bad.pth", heads_dir=heads_dir)
    assert model is None and "cannot read" in reason


def test_lpips_backbone_downloads_on_first_use_is_tried_once_offline_and_never_when_off(
    tmp_path, empty_hub, monkeypatch, capsys
):
    calls = []

    def offline(url, *args, **kwargs):
        calls.append(url)
        raise OSError("network unreachable")

    monkeypatch.setattr(torch.hub, "load_state_dict_from_url", offline)
    backbone, heads_dir = _write_fake_weights(tmp_path, "alex")
    assert lp.try_load_lpips("alex", heads_dir=heads_dir, allow_download=False)[0] is None and not calls
    model, reason = lp.try_load_lpips("alex", heads_dir=heads_dir)
    assert model is None and calls == [backbones.BACKBONES["alex"].url]
    assert "download" in reason and "network unreachable" in reason and str(empty_hub / "checkpoints") in reason
    assert capsys.readouterr().err.count("Download failed") == 1  # the log says so beside torch's announcement
    assert lp.try_load_lpips("alex", heads_dir=heads_dir)[1] == reason and len(calls) == 1  # one try per process
    monkeypatch.setattr(backbones, "FAILED_DOWNLOADS", {})  # a new process, online: torchvision's own file arrives
    state = torch.load(backbone, weights_only=True)
    monkeypatch.setattr(torch.hub, "load_state_dict_from_url", lambda url, **kwargs: calls.append(url) or state)
    model, reason = lp.try_load_lpips("alex", heads_dir=heads_dir)
    assert reason is None and isinstance(model, lp.LPIPS) and len(calls) == 2


def test_the_download_announcement_stays_off_stdout(tmp_path, empty_hub, monkeypatch, capsys):
    """torch.hub writes "Downloading: ..." to stdout; scripts that print JSON there must not get it."""
    state = torch.load(_write_fake_weights(tmp_path, "alex")[0], weights_only=True)

    def announcing(url, **kwargs):
        print(f"Downloading: {url}")
        return state

    monkeypatch.setattr(torch.hub, "load_state_dict_from_url", announcing)
    backbones.download_backbone(backbones.BACKBONES["alex"], "alex")
    out, err = capsys.readouterr()
    assert out == "" and "Downloading" in err


def test_bad_net_name():
    with pytest.raises(ValueError, match="alex"):
        lp.load_lpips("squeezenet")


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_the_packaged_official_heads_load_by_default(tmp_path, empty_hub, net):
    if lp.packaged_heads_dir() is None:
        pytest.skip("torchmetrics (a dependency) is not installed")
    heads_file = lp.resolve_heads_file(net)
    assert heads_file.parent == lp.packaged_heads_dir() and heads_file.name == f"{net}.pth"
    heads = torch.load(heads_file, map_location="cpu", weights_only=True)
    if (SHARED_HEADS / f"{net}.pth").is_file():  # the lpips package's own files, where a checkout has them
        official = torch.load(SHARED_HEADS / f"{net}.pth", map_location="cpu", weights_only=True)
        assert sorted(official) == sorted(heads) and all(torch.equal(official[k], heads[k]) for k in official)
    model = lp.LPIPS(net)
    model.heads.load_state_dict(heads)  # official key names and shapes
    assert all((h >= 0).all() for h in heads.values())  # LPIPS v0.1 heads are non-negative
    # full path: random backbone from a file + the real heads found by default
    spec = backbones.BACKBONES[net]
    torch.save(spec.build().state_dict(), tmp_path / spec.filename)
    model, reason = lp.try_load_lpips(net, backbone_path=tmp_path / spec.filename)
    assert reason is None
    x, y = torch.rand(64, 64, 3), torch.rand(64, 64, 3)
    assert float(model(x, x)) == pytest.approx(0.0, abs=1e-7)
    assert float(model(x, y)) > 0


# ------------------------------------------------------------------------------------------- evaluation


def test_evaluate_images_without_lpips():
    targets = torch.rand(3, 32, 32, 3) * 0.8
    preds = targets + 0.1
    out = evaluate_images(preds, targets, lpips_reason="weights missing")
    assert out["psnr"] == pytest.approx(20.0, abs=1e-3)
    expected_ssim = np.mean([_skimage_ssim(p, t) for p, t in zip(preds, targets, strict=True)])
    assert out["ssim"] == pytest.approx(float(expected_ssim), abs=1e-4)
    assert out["lpips"] is None and out["per_view"]["lpips"] is None
    assert out["lpips_reason"] == "weights missing"
    assert out["num_views"] == 3 and len(out["per_view"]["psnr"]) == 3


def test_evaluate_images_with_lpips_and_mixed_sizes(tmp_path, empty_hub):
    backbone, heads_dir = _write_fake_weights(tmp_path, "alex")
    model = lp.load_lpips("alex", backbone_path=backbone, heads_dir=heads_dir)
    targets = [torch.rand(64, 64, 3), torch.rand(48, 80, 3)]
    preds = [t.flip(0) for t in targets]
    out = evaluate_images(preds, targets, lpips_model=model)
    expected = [float(model(p, t)) for p, t in zip(preds, targets, strict=True)]
    assert out["per_view"]["lpips"] == pytest.approx(expected)
    assert out["lpips"] == pytest.approx(float(np.mean(expected)))
    assert out["lpips_net"] == "alex" and out["lpips_reason"] is None
    with pytest.raises(ValueError):
        evaluate_images(preds, targets[:1])
