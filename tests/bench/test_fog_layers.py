"""benchmarks/fog_layers.py: which fogs it runs, how it names an unknown one, and what it hands training (training
itself stubbed: each fog trains for minutes)."""

from __future__ import annotations

import json
import sys

import pytest


@pytest.fixture
def fog_layers(benchmark_script):
    return benchmark_script("fog_layers")


def _main(module, monkeypatch, *argv):
    calls = []
    monkeypatch.setattr(module, "run", lambda variant, layered, steps: calls.append((variant, layered, steps)) or {})
    monkeypatch.setattr(sys, "argv", ["fog_layers.py", *argv])
    module.main()
    return calls


def test_every_fog_runs_layered_and_uniform_when_none_is_named(fog_layers, monkeypatch, capsys):
    calls = _main(fog_layers, monkeypatch)
    fogs = ["physical", *sorted(n for n, v in fog_layers.VARIANTS.items() if v.fog)]
    assert "rain" not in fogs and "smog" in fogs  # a variant without fog has no profile to test
    assert calls == [(f, layered, 700) for f in fogs for layered in (True, False)]
    assert len(capsys.readouterr().out.splitlines()) == 2 * len(fogs)  # one JSON line a run


def test_named_fogs_run_in_order_with_their_steps(fog_layers, monkeypatch):
    calls = _main(fog_layers, monkeypatch, "smog", "physical", "--steps", "50")
    assert calls == [("smog", True, 50), ("smog", False, 50), ("physical", True, 50), ("physical", False, 50)]


@pytest.mark.parametrize("name", ["rain", "haze"])
def test_a_fog_it_does_not_have_is_named_with_the_choices(fog_layers, monkeypatch, capsys, name):
    with pytest.raises(SystemExit) as exit_:
        _main(fog_layers, monkeypatch, "fog", name)
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert f"unknown fog {name}" in err and "physical" in err and "smog-exp" in err


class _Trainer:
    decisions = {"fog-analytic layers": "on: stubbed"}

    def setup(self):
        return self

    def train(self):
        return {
            "psnr": 17.604,
            "ssim": 0.8153,
            "weather": {"fog-analytic": {"beta_per_m": [0.01], "scale_height_m": 40}},
        }


@pytest.mark.parametrize("variant", ["physical", "smog"])
@pytest.mark.parametrize("layered", [True, False])
def test_run_hands_training_the_fog_its_variant_draws(fog_layers, monkeypatch, variant, layered):
    from metegs.engine.metegs_trainer import MeteGSTrainer

    measure, seen = MeteGSTrainer._points_layers, {}

    def config(output_dir, size, steps, kinds, family, conditions, **overrides):
        seen.update(size=size, steps=steps, kinds=kinds, family=family, conditions=conditions, **overrides)
        seen["profile_from_uniform"] = MeteGSTrainer._points_layers is not measure
        return _Trainer()

    monkeypatch.setattr(fog_layers, "blind_config", config)
    row = fog_layers.run(variant, layered, 30)
    assert seen["profile_from_uniform"] is layered and MeteGSTrainer._points_layers is measure
    assert json.loads(json.dumps(row)) == {
        "variant": variant,
        "layered": layered,
        "psnr": 17.6,
        "ssim": 0.815,
        "beta_per_m": [0.01],
        "scale_height_m": 40,
        "layers": "on: stubbed",
    }
    assert seen["fog_analytic"].layered is layered and (seen["size"], seen["steps"]) == (160, 30)
    if variant == "physical":
        assert (seen["family"], seen["kinds"]) == ("physical", "fog")
        assert (seen["conditions"].precip_mm_h, seen["conditions"].visibility_m) == (0.0, 200.0)
    else:
        kinds, conditions = fog_layers.probe_weather(fog_layers.VARIANTS[variant])
        assert (seen["family"], seen["kinds"], seen["conditions"]) == ("independent", kinds, conditions)
        assert kinds == "rain+fog"


@pytest.mark.parametrize(("read", "learnt_from"), [(-2.0, 0.0), (0.0, 0.0), (2.0, 2.0), (None, None)])
def test_profile_from_uniform_reads_a_fog_denser_upwards_as_uniform(fog_layers, monkeypatch, read, learnt_from):
    """Inside `profile_from_uniform` a profile the points read denser upwards starts uniform (and so is learnt), one
    thinning upwards starts where they read it, and no reading stays none; outside, the reading is as measured."""
    from metegs.engine.metegs_trainer import MeteGSTrainer
    from metegs.weather.medium_fit import MediumFit

    fit = None if read is None else MediumFit(0.02, read, (0.8, 0.8, 0.8), observations=10, points=5)
    monkeypatch.setattr(MeteGSTrainer, "_points_layers", lambda self, fog: fit)
    with fog_layers.profile_from_uniform():
        inside = MeteGSTrainer._points_layers(None, None)
    assert (None if inside is None else inside.height_rate) == learnt_from
    assert inside is None or inside.beta_per_m == 0.02
    assert MeteGSTrainer._points_layers(None, None) is fit
