"""The plain-3DGS baseline of a MeteGS run is 3dgs as its own method config defines it."""

from metegs.engine.compare import baseline_config
from metegs.methods import gaussian_splatting, metegs_full


def test_baseline_prunes_as_3dgs_not_as_the_metegs_run():
    run = metegs_full()
    run.densify.prune_opacity = 0.02  # the run's own pruning must not leak into the baseline
    base = baseline_config(run)
    assert base.method == "3dgs"
    assert base.densify.prune_opacity == gaussian_splatting().densify.prune_opacity == 0.1
    assert metegs_full().densify.prune_opacity == 0.005  # Deblurring-3DGS's base threshold t_p
    assert base.max_steps == run.max_steps and base.seed == run.seed


def test_baseline_takes_the_photos_tones_as_the_run_does():
    assert gaussian_splatting().view_exposure == "auto"  # plain 3dgs learns each photo's exposure
    run = metegs_full()
    assert run.view_exposure == "auto" and baseline_config(run).view_exposure == "auto"
    run.view_exposure = "off"
    assert baseline_config(run).view_exposure == "off"
