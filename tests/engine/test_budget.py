"""--budget-minutes: the image size and steps chosen from timed steps (the step times are stood in for here, so the
choices do not hang on this machine's speed)."""

import pytest
import yaml

from metegs.data.config import DatasetConfig, SyntheticSceneConfig
from metegs.engine import budget
from metegs.engine.config import TrainConfig
from metegs.errors import ConfigError

SECONDS_PER_PIXEL = 1e-5
"""The stand-in cost of a step: at 200x160 px 0.32 s, at 100x80 0.08 s (before `budget.GROWTH`)."""


@pytest.fixture
def priced_steps(monkeypatch):
    """Steps that cost `SECONDS_PER_PIXEL` per pixel of the run's images, without running them."""

    def timed_steps(trainer):
        w, h = trainer.dataset.sizes[0]
        return w * h * SECONDS_PER_PIXEL

    monkeypatch.setattr(budget, "timed_steps", timed_steps)


def config(tmp_path, minutes: float, **kw) -> TrainConfig:
    """A 100-step 3dgs run of a 200x160 scene under a budget (the sizes a budget may choose: 200x160 and 100x80)."""
    ds = DatasetConfig(synthetic=SyntheticSceneConfig(width=200, height=160, num_views=8, num_points=300))
    options = dict(max_steps=100, output_dir=tmp_path, experiment_name="run", device="cpu", progress=False, dataset=ds)
    return TrainConfig(**{**options, "budget_minutes": minutes, **kw})


def chosen(trainer) -> tuple[tuple[int, int], int]:
    return trainer.dataset.sizes[0], trainer.config.max_steps


def test_a_generous_budget_keeps_the_largest_size_and_every_step(tmp_path, priced_steps):
    # 100 steps at 200x160: 100 x 0.32 s x GROWTH 2 = 64 s of a 120 s budget
    trainer = config(tmp_path, 2.0).setup()
    assert chosen(trainer) == ((200, 160), 100)
    assert trainer.decisions["budget"].startswith("200x160 px, 100 steps in about ")
    assert trainer.config.budget_minutes is None  # planned once: config.yml reruns the same run


def test_a_budget_too_short_for_half_the_steps_halves_the_image(tmp_path, priced_steps):
    # 30 s hold ~45 steps at 200x160 (under half of 100), all 100 at 100x80 (16 s)
    trainer = config(tmp_path, 0.5).setup()
    assert chosen(trainer) == ((100, 80), 100)
    assert "100 steps would take: 200x160 " in trainer.decisions["budget"]


def test_at_the_smallest_size_a_short_budget_cuts_the_steps(tmp_path, priced_steps):
    # 6 s: 200x160 holds about 7 steps, 100x80 about 30
    trainer = config(tmp_path, 0.1).setup()
    (size, steps) = chosen(trainer)
    assert size == (100, 80)
    assert 10 <= steps < 40
    assert "cut from 100 to fit" in trainer.decisions["budget"]
    assert "100 steps would take: 200x160 " in trainer.decisions["budget"]


def test_a_budget_below_a_tenth_of_the_steps_is_refused(tmp_path, priced_steps):
    with pytest.raises(ConfigError, match=r"--budget-minutes 0.01 is too short: at 100x80 px, the smallest size"):
        config(tmp_path, 0.01).setup()


def test_a_size_set_by_the_user_stays_and_the_budget_sets_the_steps(tmp_path, priced_steps):
    run = config(tmp_path, 0.2)
    trainer = config(tmp_path, 0.2, dataset=DatasetConfig(synthetic=run.dataset.synthetic, auto_max_side=200)).setup()
    (size, steps) = chosen(trainer)
    assert size == (200, 160)
    assert 10 <= steps < 20  # 12 s at 0.64 s a step
    with pytest.raises(ConfigError, match=r"at 200x160 px, the size set, \d of 100 steps fit"):
        config(tmp_path, 0.1, dataset=trainer.config.dataset).setup()


def test_the_run_trains_the_planned_steps_and_records_them(tmp_path, priced_steps):
    trainer = config(tmp_path, 1.0, max_steps=20).setup()
    metrics = trainer.train()
    saved = yaml.safe_load((trainer.run_dir / "config.yml").read_text())
    assert (saved["max_steps"], saved["budget_minutes"], saved["dataset"]["auto_max_side"]) == (20, None, 200)
    assert metrics["history"][-1]["step"] == 20
    assert "budget" in yaml.safe_load((trainer.run_dir / "decisions.json").read_text())["decisions"]


def test_a_resumed_run_is_not_planned_again(tmp_path):
    with pytest.raises(ConfigError, match="a resumed run keeps its checkpoint's"):
        budget.plan_budget(None, config(tmp_path, 1.0, load_checkpoint=tmp_path / "x.ckpt"), None, 0.0)
