"""The complete configuration of a training run: what `metegs-train <method>` builds and saves as config.yml."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Literal

import tyro

from metegs.config import InstantiateConfig
from metegs.data.config import DatasetConfig
from metegs.densify.adc import ADCConfig
from metegs.engine.optim import OptimConfig
from metegs.errors import ConfigError
from metegs.gaussians.sh import MAX_SH_DEGREE
from metegs.losses.photometric import PhotometricLossConfig
from metegs.validate import FRACTION, NON_NEGATIVE, POSITIVE, Range, check_config
from metegs.weather.conditions import ConditionsConfig


@dataclass
class ModelConfig:
    """The scene Gaussians: SH degree and initialisation."""

    sh_degree: Annotated[int, Range(0, MAX_SH_DEGREE)] = 3
    """Maximum SH degree (raised by one every `sh-degree-every` of the run)."""
    sh_degree_every: Annotated[float, FRACTION] = 1000 / 30000
    """Fraction of the run between SH degree increments (1000 of 30k steps in 3DGS)."""
    init_opacity: Annotated[float, Range(0, 1, lo_open=True, hi_open=True)] = 0.1
    """Opacity of the initial Gaussians."""
    init_scale_multiplier: Annotated[float, POSITIVE] = 1.0
    """Multiplier of the initial scales (mean distance to the 3 nearest points)."""
    init_random_points: Annotated[int, Range(1)] = 20000
    """Number of random initial Gaussians when the scene has no points (placed where training views overlap); also
    the most points a plane sweep starts from."""
    random_init: bool = False
    """Ignore the scene's points and start from random Gaussians."""
    triangulate: bool = True
    """When the scene has photo files and poses but no points (LLFF, nerfstudio, Blender), triangulate SfM
    points from the training views with pycolmap (known poses; cached in the scene folder): where the weather
    models measure the scene's geometry, and the start with --model.no-sweep-init."""
    sweep_init: bool = True
    """Start a capture with poses but no points from a plane sweep of the training views (cached) where its
    triangulated points are sparse or fail (rain streaks take SIFT's features): coarser points, but more (the
    Ethiopian head: 20000 against SIFT's 3049, 3DGS +1.15 dB). Off: from the triangulated points, and from the
    sweep only where triangulation fails; off with --model.no-triangulate: from random Gaussians."""
    sweep_below_coverage: Annotated[float, FRACTION] = 0.55
    """With sweep-init, where triangulation works too: start from the sweep only while the triangulated points cover
    less than this share of the training views (cells of 1/32 of the longer side) and the sweep's cover more, else
    from those points. The Ethiopian head's 3066 cover 0.45 and gain from the sweep; the fox's 9941 cover 0.70 and
    lose 1.1 dB by it under its own heavy rain. 1: the sweep wherever it finds points."""


@dataclass
class TrainConfig(InstantiateConfig):
    """A training run. Top-level flags are shared by every method."""

    _target: type = field(default_factory=lambda: _trainer_class(), repr=False)
    method: tyro.conf.Suppress[str] = "3dgs"
    """Registry name of the method this config came from."""
    data: Path | None = None
    """Scene folder (format detected from its contents); None uses the built-in synthetic scene."""
    parser: str | None = None
    """Force a data parser by registry name (e.g. colmap, nerfstudio, llff, blender, synthetic)."""
    output_dir: Path = Path("outputs")
    """Runs are written to <output-dir>/<scene>/<method>/<experiment-name>/."""
    experiment_name: str | None = None
    """Name of the run folder; None uses a timestamp."""
    max_steps: Annotated[int, Range(1)] = 3000
    """Number of training steps (one view per step)."""
    budget_minutes: Annotated[float | None, POSITIVE] = None
    """Fit the whole command (with its baseline runs) into about this many minutes of wall time: a few timed steps
    choose the largest image size (longer side at most 1600 px) that holds at least half of `max-steps`, and the steps
    that fit (at most `max-steps`); the choice is printed and config.yml records it as `max-steps` and the size."""
    seed: int = 0
    """Seed of every random choice (initialisation, view order, densification)."""
    backend: str = "auto"
    """Rasteriser backend: auto, torch, or another registered one (auto: the fastest available)."""
    device: str = "auto"
    """Torch device: auto (cuda if available, else cpu), cpu, cuda, cuda:1, ..."""
    threads: Annotated[int, NON_NEGATIVE] = 0
    """CPU threads for torch (0: torch's default)."""
    torch_threads: Annotated[int, NON_NEGATIVE] = 0
    """With the `cpu` backend: threads of torch's own ops (losses, Adam, autograd) while the rasteriser's kernels keep
    `threads` on metegs' pool, which never waits for a descheduled thread (0: the same; the kernels then share torch's
    OpenMP team, faster alone). The live viewer sets 1 while a browser shares the cores."""
    load_checkpoint: Path | None = None
    """Resume from this checkpoint file (.ckpt) of an earlier run."""
    degrade: str = "off"
    """Degrade a clean scene in memory before training, with the weather of `conditions` (the clean images become
    the references): off, auto (the method's weather kinds on the built-in synthetic scene, off for scenes from
    files) or weather kinds joined with + (rain, fog, rain+fog, +drops; a plugin's, e.g. snow+fog)."""
    degrade_family: Literal["physical", "independent"] = "physical"
    """Weather generator of `degrade`: metegs's own weather models from θ, or the independent family (2D streak
    layers, heterogeneous fog, blurred drops; made without them, so the method cannot fit its own generator)."""
    conditions: ConditionsConfig = field(default_factory=ConditionsConfig)
    """The weather of the capture (met record and time, or explicit values)."""
    view_exposure: Literal["auto", "on", "off"] = "auto"
    """Learn a gain and an offset per colour channel for each training photo (exposure, white balance), averaging
    to one and zero, so no photo's tone is baked into the scene; auto: on for photos, off for rendered scenes
    (the built-in one, Blender), whose views share one exposure."""
    background: Literal["black", "white", "random"] = "black"
    """Background colour behind the Gaussians during training (evaluation uses black, or white for 'white')."""
    drop_gaussians: Annotated[float, Range(0, 1, hi_open=True)] = 0.0
    """Leave a random share of the Gaussians out of each training step's renders, the rest's opacity scaled by
    1 / (1 - share) (DropGaussian), growing from 0 to this at the last step, on photos without visible weather:
    Gaussians seen from few views are fitted by more of them (0.1 suits sparse walk-through captures); 0: off."""
    eval_every: Annotated[float, FRACTION] = 0.25
    """Evaluate the test views every this fraction of the run (0: only at the end)."""
    checkpoint_every: Annotated[int, NON_NEGATIVE] = 1000
    """Save a checkpoint every this many steps (0: only at the end)."""
    save_renders: bool = True
    """Save test-view renders as PNG at the end."""
    lpips_net: Literal["alex", "vgg"] = "alex"
    """Backbone of the LPIPS metric (weights from the torch hub cache or METEGS_LPIPS_BACKBONE)."""
    lpips_download: bool = True
    """Download the LPIPS backbone weights into the torch hub cache on first use, as torchvision does (off: LPIPS is
    null with the reason unless the weights are already there)."""
    progress: bool = True
    """Show a live progress bar."""
    viewer: bool = False
    """Open the browser viewer (viser) while training: watch, pause / step, drive the weather; it stays open after."""
    viewer_host: str = "127.0.0.1"
    """Address the viewer binds to (0.0.0.0 exposes it to the network)."""
    viewer_port: Annotated[int, Range(0, 65535)] = 7007
    """Port of the viewer (the next free one when it is taken)."""
    dataset: DatasetConfig = field(default_factory=DatasetConfig)
    """How views are read, scaled and split."""
    model: ModelConfig = field(default_factory=ModelConfig)
    """Scene Gaussians."""
    optim: OptimConfig = field(default_factory=OptimConfig)
    """Learning rates."""
    densify: ADCConfig = field(default_factory=ADCConfig)
    """Densification."""
    loss: PhotometricLossConfig = field(default_factory=PhotometricLossConfig)
    """Photometric loss."""

    def __post_init__(self) -> None:
        check_config(self)
        name = self.experiment_name
        if name is not None and (not name.strip() or name in (".", "..") or any(c in name for c in "/\\\0")):
            raise ConfigError(f"--experiment-name {name!r}: expected a folder name (no path separators, not . or ..)")


def _trainer_class():
    from metegs.engine.trainer import Trainer

    return Trainer
