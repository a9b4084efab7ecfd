"""Reopen a finished (or interrupted) run folder from its config.yml and a checkpoint or scene.ply."""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

from metegs.config import apply_overrides, load_yaml
from metegs.errors import ConfigError, DataError
from metegs.registry import registry

if TYPE_CHECKING:  # this module is imported by metegs-train before torch may load (the viewer's thread settings)
    import numpy as np

    from metegs.data.scene import SceneData


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
    for model, options in (data.pop("weather_options", None) or {}).items():  # now each model's own typed field
        data.setdefault(model.replace("-", "_"), {}).update(options)
    missing = [n for n in data.get("weather") or () if isinstance(n, str) and n not in registry("weather")]
    if missing:
        raise ConfigError(
            f"{path}: weather model(s) {', '.join(missing)} are not registered here: install the plugin that provides "
            f"them (`metegs-train --help` lists the registered ones: {', '.join(registry('weather').names())})"
        )
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
    from metegs.gaussians.ply import load_ply, world_to_file

    run_dir = run_folder(run_dir)
    config = load_run_config(run_dir)
    # the Gaussians go to the Trainer itself, which then skips building (maybe triangulating) the initial ones
    source = None if ply is not None else checkpoint or run_dir / "checkpoints"
    config = replace(config, load_checkpoint=source, progress=False, device=device or config.device)
    if ply is not None:
        trainer = config.setup(run_dir=run_dir, model=load_ply(ply))
        if world_to_file(ply) is None:  # another tool's file (or ours rewritten by one): which frame is it in?
            turn_back_if_upright(trainer, Path(ply))
        return trainer
    trainer = config.setup(run_dir=run_dir)
    trainer.model.active_sh_degree = trainer.model.max_sh_degree
    return trainer


def evaluate_run(trainer, split: str = "test", lpips_net: str = "alex") -> dict:
    """PSNR / SSIM / LPIPS of ``trainer``'s Gaussians on its ``split`` views against their clean references where
    the scene has them, as `metegs-eval` reports them (LPIPS null with the reason when its weights are missing)."""
    from metegs.eval.lpips import try_load_lpips
    from metegs.eval.metrics import evaluate_images

    ds = trainer.dataset
    idx = ds.test_indices if split == "test" else ds.train_indices
    if not idx:
        raise DataError(trainer.run_dir, f"the scene has no {split} views")
    model, reason = try_load_lpips(lpips_net, device=trainer.device)
    bg = trainer.background(training=False)
    references = [trainer.reference(i, bg) for i in idx]  # clean references when the scene has them
    metrics = evaluate_images(trainer.render_views(idx), references, lpips_model=model, lpips_reason=reason)
    metrics.update(
        split=split,
        reference="clean" if ds.clean_images is not None else "photo",
        test_tone=trainer.test_tone(),
        num_gaussians=len(trainer.model),
    )
    return metrics


def median_gap(means, points) -> float:
    """Median distance from the points ``means`` [N, 3] to their nearest of ``points`` [P, 3] (at most 2048 of
    each, evenly spread): how well a set of Gaussians lies on a scene's own points."""
    import torch

    a = means.detach().double().cpu()[:: max(1, len(means) // 2048)]
    b = torch.as_tensor(points, dtype=torch.float64)[:: max(1, len(points) // 2048)]
    return float(torch.cdist(a, b).amin(dim=1).median())


def turn_back_if_upright(trainer, ply: Path) -> None:
    """A PLY without metegs's turn comment is in its own frame: when it fits the run's scene only turned back from
    the splat viewers' y-down frame that metegs writes (a metegs scene.ply edited and saved by another tool),
    turn ``trainer``'s Gaussians back, with a warning that says so. Fit: the median gap to the scene's points (half
    as far, turned back); a scene without points cannot tell, and its file stays as it is."""
    import numpy as np

    from metegs.gaussians.rotate import rotate_state, upright_rotation

    rotation = upright_rotation(trainer.scene.up)
    points = trainer.scene.points
    if np.allclose(rotation, np.eye(3)) or points is None or len(points) == 0:
        return
    params = trainer.model.params
    turned = rotate_state({k: params[k].detach() for k in ("means", "quats", "shN")}, rotation.T)
    as_is, back = median_gap(params["means"], points), median_gap(turned["means"], points)
    if back < 0.5 * as_is:
        import torch

        with torch.no_grad():
            for k, v in turned.items():
                params[k].copy_(v)
        warnings.warn(
            f"{ply}: no 'metegs world_to_file' comment, but its Gaussians fit the run's scene only turned back "
            f"from the y-down frame metegs writes for splat viewers (median gap to the scene's points {back:.3g} "
            f"against {as_is:.3g}): turned back (a metegs scene.ply saved by another tool?)",
            stacklevel=3,
        )


MIN_ALPHA = 0.5
"""Rendered pixels with less accumulated opacity have unknown depth (they look into the distance)."""


def cameras_match(a, b, atol: float = 1e-4) -> bool:
    """Same number of views, same poses and the same field of view (sizes may differ)."""
    import torch

    if len(a) != len(b):
        return False
    same_pose = torch.allclose(a.camera_to_worlds.cpu(), b.camera_to_worlds.cpu(), atol=atol)
    fov_a, fov_b = a.fx.cpu() / a.width.cpu(), b.fx.cpu() / b.width.cpu()
    return bool(same_pose and torch.allclose(fov_a, fov_b, rtol=1e-3))


def surface_depth(rasterizer, gaussians, camera):
    """[H, W] z-depth of ``rasterizer``'s render of ``gaussians`` (activated) through one ``camera`` (on their device),
    NaN where the render's opacity is below ``MIN_ALPHA``."""
    import torch

    from metegs.render.base import RenderSettings

    with torch.no_grad():
        out = rasterizer.render(gaussians, camera, RenderSettings(background=(0.0, 0.0, 0.0), sh_degree=0))
    return torch.where(out.alpha >= MIN_ALPHA, out.depth, torch.full_like(out.depth, float("nan")))


def depths_from_run(
    run_dir: Path,
    scene: SceneData,
    checkpoint: Path | None = None,
    progress: Callable[[int], None] | None = None,
    device: str | None = None,
) -> tuple[list[np.ndarray], str]:
    """Depth of every view of ``scene`` rendered from a trained run at the scene's image sizes.

    Returns (depths [H, W] float32 in scene units with NaN where the render's opacity is below
    ``MIN_ALPHA``, a description of the source). The run must have been trained on the same cameras.
    """

    run_dir = Path(run_dir)
    trainer = load_run(run_dir, checkpoint, device=device)
    if not cameras_match(trainer.scene.cameras, scene.cameras):
        raise DataError(
            run_dir,
            f"the run was trained on other cameras ({len(trainer.scene.cameras)} views, data "
            f"{trainer.config.data}) than the scene to degrade ({len(scene)} views, {scene.source}); "
            "give the run of this dataset",
        )
    model = trainer.model.activated()
    depths = []
    for i in range(len(scene)):
        depth = surface_depth(trainer.rasterizer, model, scene.cameras[i].to(trainer.device))
        depths.append(depth.float().cpu().numpy())
        if progress is not None:
            progress(i)
    ckpt = checkpoint or "latest checkpoint"
    return depths, f"rendered from run {run_dir.resolve()} ({trainer.config.method}, {ckpt}, step {trainer.step})"
