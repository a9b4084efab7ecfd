"""Reopen a finished (or interrupted) run folder from its config.yml and a checkpoint or scene.ply."""

from __future__ import annotations

import warnings
from dataclasses import replace
from pathlib import Path

from metegs.config import apply_overrides, load_yaml
from metegs.errors import ConfigError, DataError
from metegs.registry import registry


def run_folder(path: Path) -> Path:
    """The run folder ``path`` names: itself, or the folder of its ``config.yml`` (as nerfstudio users pass it)."""
    path = Path(path)
    return path.parent if path.suffix in (".yml", ".yaml") and not path.is_dir() else path


RETIRED_FIELDS = {
    "densify_through_fog": "densification no longer undoes the fog's attenuation (it grew the streaks of single "
    "photos in the far, foggy parts of the views)",
}
"""Top-level config fields that metegs no longer has, and why: a run folder saved with one still opens."""


def read_config_file(path: Path) -> dict:
    """The fields of a config YAML (a run's config.yml or a user's file): its ``metegs_version`` left out, and
    `RETIRED_FIELDS` left out with a warning that says why."""
    data = load_yaml(path)
    data.pop("metegs_version", None)
    for name in sorted(RETIRED_FIELDS.keys() & data.keys()):
        data.pop(name)
        warnings.warn(f"{path}: ignoring {name!r}: {RETIRED_FIELDS[name]}", stacklevel=2)
    return data


def load_run_config(run_dir: Path):
    """The TrainConfig saved in ``run_dir/config.yml`` (rebuilt on the method's defaults); ``run_dir`` may be the
    config.yml itself."""
    path = run_folder(run_dir) / "config.yml"
    if not path.is_file():
        raise DataError(path, "no config.yml: not a metegs run folder")
    data = read_config_file(path)
    method = data.pop("method", None)
    if method is None:
        raise ConfigError(f"{path}: the field 'method' is missing")
    try:
        return apply_overrides(registry("method").get(method)(), data)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from exc


def load_run(run_dir: Path, checkpoint: Path | None = None, ply: Path | None = None, device: str | None = None):
    """A Trainer set up as the run was, holding the Gaussians of ``ply``, ``checkpoint`` or the latest checkpoint."""
    from metegs.gaussians.ply import load_ply

    run_dir = run_folder(run_dir)
    config = load_run_config(run_dir)
    # the Gaussians go to the Trainer itself, which then skips building (maybe triangulating) the initial ones
    source = None if ply is not None else checkpoint or run_dir / "checkpoints"
    config = replace(config, load_checkpoint=source, progress=False, device=device or config.device)
    if ply is not None:
        return config.setup(run_dir=run_dir, model=load_ply(ply))
    trainer = config.setup(run_dir=run_dir)
    trainer.model.active_sh_degree = trainer.model.max_sh_degree
    return trainer
