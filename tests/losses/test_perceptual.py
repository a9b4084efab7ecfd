"""Perceptual loss: value, gradients, frozen backbone, weight discovery and clear errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from scipy.io import savemat

from metegs.errors import ConfigError, DataError
from metegs.eval import backbones
from metegs.eval import lpips as lp
from metegs.losses import perceptual as perc
from metegs.losses.perceptual import PerceptualLoss, PerceptualLossConfig, try_load_perceptual
from metegs.losses.squeezenet import SqueezeNetFeatures, load_squeezenet_mat

SHARED_MAT_DIR = Path(__file__).resolve().parents[3] / "shared" / "data" / "weights" / "squeezenet1.1-caffe"


def _shared_mat() -> Path:
    mats = sorted(SHARED_MAT_DIR.glob("*.mat")) if SHARED_MAT_DIR.is_dir() else []
    if not mats:
        pytest.skip(
            f"no SqueezeNet 1.1 .mat in {SHARED_MAT_DIR} (the shared weights are only in development checkouts)"
        )
    return mats[0]


def write_random_mat(path: Path, seed: int = 0, break_layer: str | None = None) -> Path:
    """A SqueezeNet 1.1 .mat in the shared file's layout (HWIO kernels, [1, C] biases) with random weights."""
    torch.manual_seed(seed)
    model = SqueezeNetFeatures()
    entries = {}
    for name, module in model.named_modules():
        if isinstance(module, torch.nn.Conv2d):
            pair = np.empty((1, 2), dtype=object)
            kernel = module.weight.detach().numpy().transpose(2, 3, 1, 0)
            if name.replace(".", "/") == break_layer:
                kernel = kernel[..., :-1]  # one output channel short
            pair[0, 0] = np.ascontiguousarray(kernel)
            pair[0, 1] = module.bias.detach().numpy()[None]
            entries[name.replace(".", "/")] = pair
    savemat(str(path), entries)
    return path


@pytest.fixture
def no_weights(tmp_path, monkeypatch):
    """An environment with no weights anywhere: empty hub and user cache, no env var (and no network: conftest)."""
    old = torch.hub.get_dir()
    torch.hub.set_dir(str(tmp_path / "hub"))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.delenv(perc.PERCEPTUAL_ENV, raising=False)
    yield tmp_path
    torch.hub.set_dir(old)


@pytest.fixture
def random_sqz(tmp_path) -> PerceptualLoss:
    path = write_random_mat(tmp_path / "random.mat")
    return PerceptualLoss(PerceptualLossConfig(backbone="squeezenet", weights_path=path))


def blurred(img: torch.Tensor, k: int) -> torch.Tensor:
    x = img.permute(2, 0, 1)[None]
    return F.avg_pool2d(x, k, stride=1, padding=k // 2, count_include_pad=False)[0].permute(1, 2, 0)


def test_mat_layout_matches_the_shared_file_layout(tmp_path):
    model = load_squeezenet_mat(write_random_mat(tmp_path / "w.mat", seed=3))
    torch.manual_seed(3)
    ref = SqueezeNetFeatures()
    for key, value in ref.state_dict().items():
        assert torch.equal(model.state_dict()[key], value), key  # HWIO -> OIHW round trip
    out = model(torch.zeros(1, 3, 64, 64))
    assert [v.shape[1] for v in out.values()] == [64, 128, 128, 256, 256, 384, 384, 512, 512]
    assert out["conv1"].shape[-1] == 31 and out["fire3"].shape[-1] == 15 and out["fire9"].shape[-1] == 3  # ceil pools


def test_zero_for_identical_and_positive_otherwise(random_sqz):
    g = torch.Generator().manual_seed(0)
    x = torch.rand(48, 40, 3, generator=g)
    y = torch.rand(48, 40, 3, generator=g)
    assert float(random_sqz(x, x)) == 0.0
    value = float(random_sqz(x, y))
    assert 0.0 < value < 10.0  # normalised: O(1)
    assert random_sqz.backbone_name == "squeezenet1.1"
    assert random_sqz.layers == ("conv1", "fire3", "fire5", "fire9") and random_sqz.scales == (1, 2)


def test_gradients_reach_pred_but_not_the_frozen_backbone(random_sqz):
    x = torch.rand(32, 32, 3, requires_grad=True)
    target = torch.rand(32, 32, 3, requires_grad=True)
    random_sqz.train()  # stays frozen and in eval mode
    assert not random_sqz.training and not any(m.training for m in random_sqz.modules())
    random_sqz(x, target).backward()
    assert x.grad is not None and x.grad.abs().sum() > 0
    assert target.grad is None  # the target is a constant
    assert all(not p.requires_grad and p.grad is None for p in random_sqz.parameters())


def test_gradient_matches_finite_differences_in_float64(tmp_path):
    cfg = PerceptualLossConfig(
        backbone="squeezenet", weights_path=write_random_mat(tmp_path / "w.mat"), layers=("conv1", "fire3")
    )
    loss = PerceptualLoss(cfg).double()
    g = torch.Generator().manual_seed(1)
    x = torch.rand(16, 16, 3, generator=g, dtype=torch.float64, requires_grad=True)
    y = torch.rand(16, 16, 3, generator=g, dtype=torch.float64)
    (grad,) = torch.autograd.grad(loss(x, y), x)
    h = 1e-6
    for _ in range(4):
        v = torch.randn(16, 16, 3, generator=g, dtype=torch.float64)
        with torch.no_grad():
            fd = (loss(x + h * v, y) - loss(x - h * v, y)) / (2 * h)
        assert float(fd) == pytest.approx(float((grad * v).sum()), rel=1e-4, abs=1e-8)


@pytest.mark.data
def test_more_blur_gives_a_larger_loss_with_the_shared_weights():
    loss = PerceptualLoss(PerceptualLossConfig(backbone="squeezenet", weights_path=_shared_mat()))
    img = torch.zeros(96, 96, 3)
    img[24:72, 24:72, 0] = 1.0
    img[:, ::6, 1] = 0.7
    img[::5, :, 2] = 0.4
    values = [float(loss(blurred(img, k), img)) for k in (3, 5, 9, 15)]
    assert all(a < b for a, b in zip(values, values[1:])), values
    assert float(loss(img, img)) == 0.0


@pytest.mark.data
def test_the_real_squeezenet_mat_loads_and_auto_never_picks_it_by_itself(no_weights, monkeypatch):
    mat = _shared_mat()
    cache = no_weights / "cache" / "metegs" / "weights"
    cache.mkdir(parents=True)
    (cache / "squeezenet1.1-caffe.mat").symlink_to(mat)
    assert try_load_perceptual(PerceptualLossConfig())[0] is None  # auto never picks the stand-in by itself
    mat = cache / "squeezenet1.1-caffe.mat"
    loss, reason = try_load_perceptual(PerceptualLossConfig(backbone="squeezenet"))
    assert reason is None and loss.backbone_name == "squeezenet1.1" and loss.source == str(mat)
    feats = loss.extractor.features(SqueezeNetFeatures.preprocess(torch.rand(1, 3, 64, 64)))
    assert feats["fire9"].shape[1] == 512 and torch.isfinite(feats["fire9"]).all()


def test_user_cache_and_env_var_are_searched(no_weights, monkeypatch):
    cache = no_weights / "cache" / "metegs" / "weights"
    cache.mkdir(parents=True)
    write_random_mat(cache / "squeezenet1.1-caffe.mat")
    loss, reason = try_load_perceptual(PerceptualLossConfig(backbone="squeezenet"))
    assert reason is None and Path(loss.source) == cache / "squeezenet1.1-caffe.mat"
    other = write_random_mat(no_weights / "elsewhere.mat", seed=5)
    monkeypatch.setenv(perc.PERCEPTUAL_ENV, str(other))
    loss, _ = try_load_perceptual(PerceptualLossConfig())
    assert Path(loss.source) == other


def test_missing_weights_give_a_reason_naming_where_it_looked(no_weights):
    loss, reason = try_load_perceptual(PerceptualLossConfig(backbone="squeezenet"))
    assert loss is None and "squeezenet1.1" in reason and "shared" not in reason  # only the package and caches
    assert str(no_weights / "cache" / "metegs" / "weights") in reason
    loss, reason = try_load_perceptual(PerceptualLossConfig())
    assert loss is None
    assert str(no_weights / "hub" / "checkpoints") in reason  # the VGG16 hub cache
    assert "vgg16-397923af.pth" in reason and "--perceptual.backbone squeezenet" in reason
    assert "weights_path" in reason and perc.PERCEPTUAL_ENV in reason and "leave download on" in reason
    assert "tests never download" in reason  # it tried, as torchvision would, and says why it failed
    loss, reason = try_load_perceptual(PerceptualLossConfig(backbone="vgg16", download=False))
    assert loss is None and "SqueezeNet" not in reason and "tests never download" not in reason


def test_explicit_missing_path_does_not_fall_back(no_weights, monkeypatch):
    cache = no_weights / "cache" / "metegs" / "weights"
    cache.mkdir(parents=True)
    write_random_mat(cache / "squeezenet1.1.mat")
    loss, reason = try_load_perceptual(PerceptualLossConfig(weights_path=no_weights / "nope.mat"))
    assert loss is None and "nope.mat" in reason and "does not exist" in reason
    monkeypatch.setenv(perc.PERCEPTUAL_ENV, str(no_weights / "empty-dir"))
    (no_weights / "empty-dir").mkdir()
    loss, reason = try_load_perceptual(PerceptualLossConfig())
    assert loss is None and perc.PERCEPTUAL_ENV in reason and "empty-dir" in reason


def test_corrupted_files_raise_errors_naming_the_file(no_weights):
    bad = no_weights / "broken.mat"
    bad.write_bytes(b"MATLAB 5.0 MAT-file, truncated")
    with pytest.raises(DataError, match="broken.mat"):
        try_load_perceptual(PerceptualLossConfig(weights_path=bad))
    wrong = write_random_mat(no_weights / "wrong.mat", break_layer="fire4/expand3x3")
    with pytest.raises(DataError, match=r"wrong\.mat.*fire4/expand3x3"):
        try_load_perceptual(PerceptualLossConfig(weights_path=wrong))
    bad_pth = no_weights / "hub" / "checkpoints" / "vgg16-397923af.pth"
    bad_pth.parent.mkdir(parents=True)
    bad_pth.write_bytes(b"not a checkpoint")
    with pytest.raises(DataError, match="vgg16-397923af.pth"):
        try_load_perceptual(PerceptualLossConfig())


def test_vgg16_from_the_hub_cache_is_preferred(no_weights):
    torch.manual_seed(0)
    state = {f"features.{k}": v.half() for k, v in lp.vgg16_features().state_dict().items()}
    path = no_weights / "hub" / "checkpoints" / "vgg16-397923af.pth"
    path.parent.mkdir(parents=True)
    torch.save(state, path)
    cache = no_weights / "cache" / "metegs" / "weights"
    cache.mkdir(parents=True)
    write_random_mat(cache / "squeezenet1.1.mat")
    loss, reason = try_load_perceptual(PerceptualLossConfig(layers=("relu1_2", "relu2_2")))
    assert reason is None and loss.backbone_name == "vgg16" and loss.source == str(path)
    x = torch.rand(24, 24, 3, requires_grad=True)
    value = loss(x, torch.rand(24, 24, 3))
    value.backward()
    assert float(value.detach()) > 0 and x.grad.abs().sum() > 0 and float(loss(x, x).detach()) == 0.0
    assert len(loss.extractor.features) == 9  # truncated after relu2_2
    assert try_load_perceptual(PerceptualLossConfig(backbone="squeezenet"))[0].backbone_name == "squeezenet1.1"


def test_vgg16_downloads_on_first_use_once_per_process_and_never_when_off(no_weights, monkeypatch):
    calls = []

    def offline(url, **kwargs):
        calls.append(url)
        raise OSError("network unreachable")

    monkeypatch.setattr(torch.hub, "load_state_dict_from_url", offline)
    assert try_load_perceptual(PerceptualLossConfig(backbone="vgg16", download=False))[0] is None and not calls
    loss, reason = try_load_perceptual(PerceptualLossConfig(backbone="vgg16"))
    assert loss is None and calls == [backbones.BACKBONES["vgg"].url]
    assert "download" in reason and "network unreachable" in reason
    cache = no_weights / "cache" / "metegs" / "weights"
    cache.mkdir(parents=True)
    write_random_mat(cache / "squeezenet1.1.mat")
    loss, reason = try_load_perceptual(PerceptualLossConfig())  # auto: no SqueezeNet fallback, and no second try
    assert loss is None and "network unreachable" in reason and len(calls) == 1
    monkeypatch.setattr(backbones, "FAILED_DOWNLOADS", {})  # a new process, online
    state = {f"features.{k}": v for k, v in lp.vgg16_features().state_dict().items()}
    monkeypatch.setattr(torch.hub, "load_state_dict_from_url", lambda url, **kwargs: calls.append(url) or state)
    loss, reason = try_load_perceptual(PerceptualLossConfig())
    assert reason is None and loss.backbone_name == "vgg16" and loss.source.startswith(backbones.BACKBONES["vgg"].url)


def test_bad_config_is_an_error(tmp_path):
    mat = write_random_mat(tmp_path / "w.mat")
    with pytest.raises(ConfigError, match="relu1_2"):
        PerceptualLoss(PerceptualLossConfig(weights_path=mat, layers=("relu1_2",)))
    with pytest.raises(ConfigError, match="backbone='vgg16'"):
        PerceptualLoss(PerceptualLossConfig(backbone="vgg16", weights_path=mat))
    with pytest.raises(ConfigError, match="scales"):
        PerceptualLoss(PerceptualLossConfig(weights_path=mat, scales=(0,)))


def test_setup_builds_the_loss(tmp_path):
    mat = write_random_mat(tmp_path / "w.mat")
    loss = PerceptualLossConfig(weights_path=mat).setup()
    assert isinstance(loss, PerceptualLoss)
    with pytest.raises(ValueError, match="equal shape"):
        loss(torch.rand(8, 8, 3), torch.rand(8, 9, 3))


def test_tiny_images_still_give_every_layer(random_sqz):
    x = torch.rand(8, 10, 3, requires_grad=True)
    value = random_sqz(x, torch.rand(8, 10, 3))
    value.backward()
    assert torch.isfinite(value.detach()) and float(value.detach()) > 0 and torch.isfinite(x.grad).all()


def test_cached_target_features_give_the_same_loss_and_gradient(random_sqz):
    g = torch.Generator().manual_seed(3)
    target = torch.rand(40, 56, 3, generator=g)
    pred = torch.rand(40, 56, 3, generator=g, requires_grad=True)
    direct = random_sqz(pred, target)
    (grad_direct,) = torch.autograd.grad(direct, pred)
    cached = random_sqz(pred, target_features=random_sqz.target_features(target))
    (grad_cached,) = torch.autograd.grad(cached, pred)
    assert torch.equal(direct, cached) and torch.equal(grad_direct, grad_cached)
    with pytest.raises(ValueError):
        random_sqz(pred)
