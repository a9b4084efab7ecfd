"""Blind MeteGS ends with its clean scene fitted again: a fresh 3dgs run on its clean renders of the training views."""

import json

import pytest
import torch

import metegs.engine.refit as refit
from metegs.engine.refit import REFIT_FOLDER
from metegs.engine.trainer import Trainer
from metegs.weather.conditions import ConditionsConfig

from .test_metegs_trainer import tiny_metegs


def test_blind_training_ends_on_3dgs_fitted_to_its_clean_renders(tmp_path, monkeypatch):
    """The refit trains on the clean renders the run made of its training views (not the photos), its Gaussians
    become the run's scene (the run scores and saves what the refit does), and a resumed run keeps them."""
    seen = {}
    renders_of = refit.clean_training_views

    def renders(trainer):
        seen["renders"] = renders_of(trainer)
        return seen["renders"]

    train = Trainer.train

    def record(self):
        if self.config.method == "3dgs":
            seen["targets"] = {i: self.dataset.images[i].clone() for i in self.dataset.train_indices}
        return train(self)

    monkeypatch.setattr(refit, "clean_training_views", renders)
    monkeypatch.setattr(Trainer, "train", record)
    config = tiny_metegs(tmp_path, clean_supervision=False, refit=True)
    trainer = config.setup()
    assert trainer.refit_on and trainer.decisions["refit"].startswith("on (--refit): when training ends")
    photos = {i: trainer.dataset.images[i].clone() for i in trainer.dataset.train_indices}
    metrics = trainer.train()
    assert seen["targets"].keys() == seen["renders"].keys() == photos.keys()
    for i, target in seen["targets"].items():
        assert torch.equal(target, seen["renders"][i]) and not torch.allclose(target, photos[i], atol=0.02)
    refitted = json.loads((trainer.run_dir / REFIT_FOLDER / "metrics.json").read_text())
    said = json.loads((trainer.run_dir / REFIT_FOLDER / "decisions.json").read_text())["decisions"]["photos"]
    assert said.startswith("the clean renders of the 10 training views") and str(trainer.run_dir) in said
    assert metrics["num_gaussians"] == refitted["num_gaussians"] == len(trainer.model)
    assert metrics["psnr"] == pytest.approx(refitted["psnr"], abs=1e-6)
    assert metrics["train_seconds"] > refitted["train_seconds"]

    def must_not_refit(trainer):
        raise AssertionError("fitted again although the checkpoint holds the refit")

    monkeypatch.setattr(refit, "refit_clean_scene", must_not_refit)
    monkeypatch.setattr("metegs.engine.metegs_trainer.refit_clean_scene", must_not_refit)
    latest = sorted((trainer.run_dir / "checkpoints").glob("*.ckpt"))[-1]
    again = tiny_metegs(tmp_path / "again", clean_supervision=False, refit=True, load_checkpoint=latest).setup()
    assert again.refitted and len(again.model) == len(trainer.model)
    assert again.train()["psnr"] == pytest.approx(metrics["psnr"], abs=1e-6)


@pytest.mark.parametrize(
    ("options", "why"),
    [
        ({"clean_supervision": False}, "off (--refit adds it in blind runs)"),
        ({"refit": True}, "off: the clean references hold the scene"),
        (
            {
                "refit": True,
                "clean_supervision": False,
                "conditions": ConditionsConfig(precip_mm_h=0.0),
                "degrade": "off",
            },
            "off: no weather is taken out",
        ),
    ],
)
def test_the_refit_is_left_out_unless_asked_for_where_it_can_serve(tmp_path, options, why):
    """Off unless asked for; asked for, still off beside clean references and where no weather is taken out."""
    trainer = tiny_metegs(tmp_path, **options).setup()
    assert trainer.decisions["refit"].startswith(why) and not trainer.refit_on
