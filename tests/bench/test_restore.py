"""The per-view 2D restorers: dark channel prior dehazing, Kang et al. deraining, the learned slots."""

import os
import warnings

import numpy as np
import pytest
import torch

from metegs.errors import ConfigError
from metegs.restore import (
    ChainRestorer,
    make_restorer,
    restorer_config,
    restorer_for_kinds,
    restorer_names,
)
from metegs.restore.dehaze import dark_channel, estimate_airlight


def psnr(a, b):
    return float(10 * np.log10(1.0 / max(np.mean((np.asarray(a) - np.asarray(b)) ** 2), 1e-12)))


def textured(h=48, w=64, seed=0):
    """A colourful image whose every patch has a dark channel (the dark channel prior holds)."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w] / 8.0
    img = np.stack([0.5 + 0.45 * np.sin(xx + yy), 0.5 + 0.45 * np.sin(1.3 * xx - 0.7 * yy + 2), 0.05 + 0.0 * xx], -1)
    return np.clip(img + 0.02 * rng.standard_normal(img.shape), 0, 1).astype(np.float32)


def test_an_opencv_without_its_contrib_module_is_named_before_any_photo(monkeypatch):
    """Another OpenCV package installed beside opencv-contrib shadows it (the lent GPU machines' image does)."""
    import cv2

    monkeypatch.delattr(cv2, "ximgproc", raising=False)
    with pytest.raises(ConfigError, match=r"contrib module \(cv2\.ximgproc\).*pip uninstall opencv-python"):
        make_restorer("dcp")


def test_dark_channel_prior_inverts_the_fog_model():
    clean = textured()
    A = np.array([0.85, 0.88, 0.9], np.float32)
    t = np.linspace(0.35, 0.8, clean.shape[1], dtype=np.float32)[None, :, None].repeat(clean.shape[0], 0)
    t[:6] = 0.01  # a band of dense haze (sky): where the prior finds the airlight
    foggy = clean * t + A * (1 - t)
    dcp = make_restorer("dcp")
    assert np.abs(estimate_airlight(foggy, dark_channel(foggy, 3)) - A).max() < 0.05
    restored = dcp.restore(foggy)
    assert restored.shape == clean.shape and restored.dtype == np.float32
    assert psnr(restored[6:], clean[6:]) > psnr(foggy[6:], clean[6:]) + 8


def test_dcp_scales_its_patch_and_radius_with_the_image():
    dcp = make_restorer("dcp")
    small = dcp.transmission(textured(24, 32))[0]
    big = dcp.transmission(textured(240, 320))[0]
    assert small.shape == (24, 32) and big.shape == (240, 320)
    assert np.isfinite(small).all() and np.isfinite(big).all()


def streaks(image, seed=0, n=40, length=10, value=0.95):
    """Thin bright slanted streaks, mostly of one orientation (as rain within an exposure)."""
    rng = np.random.default_rng(seed)
    out = image.copy()
    h, w = image.shape[:2]
    for _ in range(n):
        y, x = rng.integers(0, h - length), rng.integers(0, w - 4)
        for k in range(length):
            xx = x + k // 4
            out[y + k, xx] = 0.6 * out[y + k, xx] + 0.4 * value
    return out


def test_kang_derain_removes_most_of_the_streaks():
    yy, xx = np.mgrid[0:48, 0:64] / 12.0
    clean = np.stack([0.4 + 0.2 * np.sin(xx), 0.35 + 0.2 * np.cos(yy), 0.3 + 0.1 * np.sin(xx + yy)], -1).astype(
        np.float32
    )
    rainy = streaks(clean)
    derain = make_restorer("kang2012", iterations=4, train_patches=1500)
    restored = derain.restore(rainy)
    assert restored.shape == clean.shape and np.isfinite(restored).all()
    assert 0 < derain.last_info["rain_atoms"] < derain.last_info["atoms"]
    assert psnr(restored, clean) > psnr(rainy, clean) + 1.0


def test_kang_derain_is_reproducible_and_handles_tiny_images():
    img = textured(24, 32)
    a = make_restorer("kang2012", iterations=2).restore(img)
    b = make_restorer("kang2012", iterations=2).restore(img)
    assert np.array_equal(a, b)
    tiny = textured(5, 6)
    assert np.array_equal(make_restorer("kang2012").restore(tiny), tiny)


def test_restorers_reject_bad_images():
    with pytest.raises(Exception, match="RGB image"):
        make_restorer("dcp").restore(np.zeros((4, 4), np.float32))
    with pytest.raises(Exception, match="NaN"):
        make_restorer("dcp").restore(np.full((4, 4, 3), np.nan, np.float32))


def test_kinds_choose_and_chain_restorers():
    assert restorer_for_kinds("fog").name == "dcp"
    assert restorer_for_kinds("rain", options={"kang2012": {"iterations": 1}}).name == "kang2012"
    chain = restorer_for_kinds("rain+fog")
    assert isinstance(chain, ChainRestorer) and chain.name == "kang2012+dcp"
    assert chain.removes == {"rain", "fog"}
    out = restorer_for_kinds("rain+fog", options={"kang2012": {"iterations": 1}}).restore(textured(24, 32))
    assert out.shape == (24, 32, 3) and np.isfinite(out).all()
    with pytest.raises(ConfigError):
        restorer_for_kinds("snow")


def test_names_and_options_are_checked():
    assert {"dcp", "kang2012", "restormer", "dehazeformer"} <= set(restorer_names())
    with pytest.raises(ConfigError, match="unknown restorer"):
        restorer_config("nope")
    with pytest.raises(ConfigError, match="unknown config field"):
        restorer_config("dcp", {"omegaa": 1})
    assert restorer_config("dcp", {"omega": 0.8}).omega == 0.8


@pytest.mark.parametrize(
    "slot,env", [("restormer", "METEGS_RESTORMER_WEIGHTS"), ("dehazeformer", "METEGS_DEHAZEFORMER_WEIGHTS")]
)
def test_learned_slots_say_what_weights_to_give(monkeypatch, tmp_path, slot, env):
    monkeypatch.delenv(env, raising=False)
    with pytest.raises(ConfigError, match=env):
        make_restorer(slot)
    with pytest.raises(ConfigError, match="not found"):
        make_restorer(slot, weights=str(tmp_path / "missing.pth"))
    bad = tmp_path / "bad.ts"
    bad.write_bytes(b"not a model")
    with pytest.raises(Exception, match="TorchScript"), warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        make_restorer(slot, weights=str(bad))


class _Brighten(torch.nn.Module):
    def forward(self, x):
        assert x.shape[-1] % 8 == 0 and x.shape[-2] % 8 == 0  # padded to the network's multiple
        return x * 0.5 + 0.25


@pytest.mark.parametrize("slot", ["restormer", "dehazeformer"])
def test_learned_slot_runs_a_torchscript_network(monkeypatch, tmp_path, slot):
    path = tmp_path / "net.ts"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # torch.jit is deprecated, still what many users have
        torch.jit.script(_Brighten()).save(str(path))
    env = "METEGS_RESTORMER_WEIGHTS" if slot == "restormer" else "METEGS_DEHAZEFORMER_WEIGHTS"
    monkeypatch.setenv(env, str(path))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        restorer = make_restorer(slot)
    img = textured(21, 30)
    out = restorer.restore(img)
    assert out.shape == img.shape and np.isfinite(out).all()
    if slot == "restormer":  # [0, 1] in and out
        np.testing.assert_allclose(out, img * 0.5 + 0.25, atol=1e-6)
    else:  # [-1, 1]: (0.5(2x - 1) + 0.25 + 1)/2
        np.testing.assert_allclose(out, np.clip(((2 * img - 1) * 0.5 + 0.25 + 1) / 2, 0, 1), atol=1e-6)


def test_learned_slot_runs_an_exported_program(tmp_path):
    from torch.export import Dim

    h, w = Dim("h", min=1, max=512), Dim("w", min=1, max=512)
    program = torch.export.export(_Scale(), (torch.rand(1, 3, 24, 32),), dynamic_shapes={"x": {2: 8 * h, 3: 8 * w}})
    path = tmp_path / "net.pt2"
    torch.export.save(program, str(path))
    img = textured(21, 30)
    out = make_restorer("restormer", weights=str(path)).restore(img)
    np.testing.assert_allclose(out, img * 0.5, atol=1e-6)


class _Scale(torch.nn.Module):
    def forward(self, x):
        return x * 0.5


def test_learned_slot_loads_a_state_dict_with_an_arch(tmp_path):
    net = torch.nn.Conv2d(3, 3, 1)
    torch.nn.init.eye_(net.weight.data[:, :, 0, 0])
    torch.nn.init.zeros_(net.bias)
    path = tmp_path / "w.pth"
    torch.save({"params": net.state_dict()}, path)
    restorer = make_restorer(
        "restormer",
        weights=str(path),
        arch="torch.nn:Conv2d",
        arch_kwargs={"in_channels": 3, "out_channels": 3, "kernel_size": 1},
    )
    img = textured(16, 16)
    np.testing.assert_allclose(restorer.restore(img), img, atol=1e-6)
    with pytest.raises(ConfigError, match="cannot import"):
        make_restorer("restormer", weights=str(path), arch="nowhere.module:Net")


class _Counting:
    """A restorer that darkens by ``gain`` and counts its calls."""

    removes = frozenset({"fog"})

    def __init__(self, name="counting", gain=0.5):
        self.name, self.calls = name, 0
        self.config = {"gain": gain}

    def restore(self, image):
        self.calls += 1
        return image * self.config["gain"]


def test_restored_photos_are_kept_between_runs_per_photo_and_settings(tmp_path):
    from metegs.restore.cache import cached_restore

    img, other = textured(21, 30, seed=0), textured(21, 30, seed=1)
    first = _Counting()
    out, seconds, was_cached = cached_restore(first, img, tmp_path)
    assert not was_cached and first.calls == 1 and seconds >= 0
    np.testing.assert_array_equal(out, img * 0.5)
    again = _Counting()  # a later run: a new restorer object with the same settings
    out2, seconds2, was_cached = cached_restore(again, img, tmp_path)
    assert was_cached and again.calls == 0
    np.testing.assert_array_equal(out2, out)
    assert seconds2 == seconds  # the time its restoring took, not the reading's
    # another photo, another option, another restorer: restored anew, never another's result
    for restorer, photo, expected in (
        (_Counting(), other, other * 0.5),
        (_Counting(gain=0.25), img, img * 0.25),
        (_Counting(name="other"), img, img * 0.5),
    ):
        result, _, was_cached = cached_restore(restorer, photo, tmp_path)
        assert not was_cached and restorer.calls == 1
        np.testing.assert_array_equal(result, expected)
    assert len(list(tmp_path.glob("*.npz"))) == 4


def test_a_damaged_cache_entry_is_restored_again(tmp_path):
    from metegs.restore.cache import cached_restore

    img = textured(21, 30)
    cached_restore(_Counting(), img, tmp_path)
    (entry,) = tmp_path.glob("*.npz")
    whole = entry.read_bytes()
    for damaged in (whole[:100], whole[: len(whole) // 2], b"not an archive"):
        entry.write_bytes(damaged)
        restorer = _Counting()
        out, _, was_cached = cached_restore(restorer, img, tmp_path)
        assert not was_cached and restorer.calls == 1
        np.testing.assert_array_equal(out, img * 0.5)
        with np.load(entry) as replaced:
            np.testing.assert_array_equal(replaced["image"], img * 0.5)


def test_a_learned_restorers_cache_follows_its_weights_file(tmp_path):
    from metegs.restore.cache import cache_key

    path = tmp_path / "net.pt2"
    program = torch.export.export(_Scale(), (torch.rand(1, 3, 24, 32),))
    torch.export.save(program, str(path))
    img = textured(24, 32)
    key = cache_key(make_restorer("restormer", weights=str(path)), img)
    assert key == cache_key(make_restorer("restormer", weights=str(path)), img)
    torch.export.save(program, str(path))  # the file written again (new weights, say)
    os.utime(path, ns=(1, 1))
    assert key != cache_key(make_restorer("restormer", weights=str(path)), img)
