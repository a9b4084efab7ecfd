"""The clean scene fitted again: a fresh 3DGS trained on blind MeteGS's clean renders of its training views.

Blind MeteGS fits the photos of its training views more closely than it carries to new views: on the Lund street
under the independent 200 m fog its clean renders of the training views score 15.70 dB against the clean photos
(the photos DCP restores: 14.34), its test views 12.80 (the restoration's 3DGS: 12.82). Gaussians free to take the
haze in put the far street too near, and test views that look from where no training photo stood (the walk's ends)
see it so. The clean renders hold what the weather models took out; 3DGS fitted to them afresh, from the scene's
points, carried to the test views better there: 0.34 dB on average over the street's six heavy cells; a trial
outside the trainer gained nothing on the instant-ngp fox, whose views circle one object (`docs/benchmark.md`, "The
clean scene fitted again")."""

from __future__ import annotations

from dataclasses import replace

import torch

from metegs.engine.compare import baseline_config
from metegs.engine.config import TrainConfig

REFIT_FOLDER = "refit"
"""Sub-folder of the run that the refit 3DGS writes its own config, checkpoints and metrics to."""


def refit_config(config: TrainConfig) -> TrainConfig:
    """`3dgs` with the run's data, schedule, seed and hardware (`baseline_config`): per-view exposure off, as the
    renders share one tone; no evaluation along the way and no test renders of its own."""
    return replace(baseline_config(config), view_exposure="off", eval_every=0.0, save_renders=False)


def clean_training_views(trainer) -> dict[int, torch.Tensor]:
    """``trainer``'s clean renders (the scene without its weather, in the scene's own tone) of its training views ->
    {view: [H, W, 3] in [0, 1]}."""
    with torch.no_grad():
        return {i: trainer.render(i).rgb.clamp(0.0, 1.0) for i in trainer.dataset.train_indices}


def refit_clean_scene(trainer):
    """Train `3dgs` into ``RUN/refit`` on ``trainer``'s clean renders of its training views (`clean_training_views`),
    from the scene's points as 3DGS on photos starts -> that Trainer, trained."""
    from metegs.engine.trainer import Trainer

    renders = clean_training_views(trainer)
    refit = Trainer(
        refit_config(trainer.config),
        run_dir=trainer.run_dir / REFIT_FOLDER,
        console=trainer.console,
        scene=trainer.scene,
    )
    for i, image in renders.items():
        refit.dataset.images[i] = image.to(refit.dataset.images[i])
    refit.decide(
        "photos",
        f"the clean renders of the {len(renders)} training views by the {trainer.config.method} run in "
        f"{trainer.run_dir}, not the photos of `data` (this config.yml trains 3dgs on those)",
    )
    refit.train()
    return refit
