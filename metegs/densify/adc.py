"""3DGS adaptive density control: clone / split / prune / opacity reset (INRIA, pruning at splatfacto's 0.1).

The schedule is given as fractions of the run, taken from the reference 30k-step schedule (refine
from step 500 to 15k, opacity reset every 3k), so that short CPU runs keep the same shape.
Order per step (as gsplat): statistics after backward, optimiser step, then refinement.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Annotated

import torch

from metegs.config import InstantiateConfig
from metegs.densify.surgery import append_rows, select_rows
from metegs.gaussians.model import GaussianModel, inverse_sigmoid
from metegs.render.base import RenderOutput
from metegs.validate import FRACTION, NON_NEGATIVE, POSITIVE, Range


@dataclass
class ADCConfig(InstantiateConfig):
    """Adaptive density control of 3DGS."""

    _target: type = field(default_factory=lambda: AdaptiveDensityControl, repr=False)
    grow_grad2d: Annotated[float, NON_NEGATIVE] = 2e-4
    """Clone/split Gaussians whose mean screen-space (NDC) position gradient exceeds this."""
    grow_scale3d: Annotated[float, NON_NEGATIVE] = 0.01
    """Clone if the largest scale is at most this fraction of the scene extent, else split."""
    split_samples: Annotated[int, Range(1)] = 2
    """Number of Gaussians a split one becomes."""
    split_scale_divisor: Annotated[float, POSITIVE] = 1.6
    """Scales of split Gaussians are divided by this (0.8 x split_samples in 3DGS)."""
    prune_opacity: Annotated[float, FRACTION] = 0.1
    """Prune Gaussians whose opacity falls below this (0.1 as nerfstudio's splatfacto; INRIA's 0.005 lets
    half-transparent Gaussians fit single views of a sparse capture, so test PSNR falls as runs grow)."""
    prune_scale3d: Annotated[float, POSITIVE] = 0.5
    """After the first opacity reset, prune Gaussians larger than this fraction of the scene extent (0.5 as
    splatfacto and OpenSplat; INRIA's and gsplat's 0.1 leaves holes past the edges of the training views, where
    views that look past the training photos need the large Gaussians)."""
    horizon: Annotated[int, NON_NEGATIVE] = 0
    """Steps that the schedule's fractions refer to (0: the whole run); a longer run densifies as a run of this
    many steps does, then only optimises what it grew."""
    refine_start: Annotated[float, FRACTION] = 500 / 30000
    """Start of refinement, as a fraction of the run."""
    refine_stop: Annotated[float, FRACTION] = 15000 / 30000
    """End of refinement, as a fraction of the run."""
    refine_every: Annotated[int, Range(1)] = 100
    """Refine every this many steps; shorter runs refine more often (about 10 times in the window), but never
    more than once per pass over the training views, so the averaged gradients see every view."""
    reset_every: Annotated[float, FRACTION] = 3000 / 30000
    """Opacity reset period, as a fraction of the run (0 disables); skipped when fewer than 3 refinements fit
    between resets (opacities need them to recover)."""
    reset_opacity: Annotated[float, FRACTION] = 0.01
    """Opacities are reset to min(opacity, this)."""
    pause_after_reset: Annotated[int, NON_NEGATIVE] = 0
    """Steps after a reset during which no refinement happens."""
    max_gaussians: Annotated[int, Range(1)] = 1_000_000
    """No growth beyond this many Gaussians."""


@dataclass
class DensifyState:
    """Running statistics since the last refinement."""

    grad_sum: torch.Tensor
    count: torch.Tensor
    max_radii: torch.Tensor

    @staticmethod
    def zeros(n: int, device) -> DensifyState:
        return DensifyState(torch.zeros(n, device=device), torch.zeros(n, device=device), torch.zeros(n, device=device))


class AdaptiveDensityControl:
    """Grows and prunes scene Gaussians from the 2D-mean gradients of the renders."""

    def __init__(
        self,
        config: ADCConfig,
        max_steps: int,
        extent: float,
        num_train_views: int = 1,
        prune_rule: Callable[[GaussianModel, float], torch.Tensor] | None = None,
    ):
        self.config = config
        self.extent = extent
        c = config
        span = min(max_steps, c.horizon) if c.horizon else max_steps
        self.start_step = int(round(c.refine_start * span))
        self.stop_step = int(round(c.refine_stop * span))
        self.every = max(num_train_views, 1, min(c.refine_every, (self.stop_step - self.start_step) // 10))
        reset = int(round(c.reset_every * span)) if c.reset_every > 0 else 0
        self.reset_every = reset if reset >= 3 * self.every else 0
        self.state: DensifyState | None = None
        self.prune_rule = prune_rule
        """Optional per-Gaussian opacity thresholds ``(model, prune_opacity) -> [N]`` used instead of the scalar
        ``prune_opacity`` (e.g. `metegs.densify.depth_prune.DepthAwarePruning`); its prunes are reported as
        ``prune_depth``."""

    def schedule(self) -> dict[str, int]:
        """The schedule in steps (for logs and tests)."""
        return {"start": self.start_step, "stop": self.stop_step, "every": self.every, "reset_every": self.reset_every}

    @torch.no_grad()
    def update_stats(self, model: GaussianModel, out: RenderOutput, num_scene: int | None = None) -> None:
        """Accumulate screen-space gradient norms of the first ``num_scene`` Gaussians (weather ones excluded)."""
        n = len(model) if num_scene is None else num_scene
        if self.state is None or self.state.grad_sum.shape[0] != len(model):
            self.state = DensifyState.zeros(len(model), model.device)
        grad = out.means2d.grad
        if grad is None:
            return
        grad = grad[:n] * torch.tensor([out.width / 2.0, out.height / 2.0], device=grad.device)
        visible = out.radii[:n] > 0
        norm = grad.norm(dim=-1)
        self.state.grad_sum[visible] += norm[visible]
        self.state.count[visible] += 1
        self.state.max_radii[visible] = torch.maximum(
            self.state.max_radii[visible], out.radii[:n][visible].float() / max(out.width, out.height)
        )

    @torch.no_grad()
    def step(self, model: GaussianModel, optimizers, step: int) -> dict[str, int]:
        """Refine and reset on schedule (call after the optimiser step). Returns counts of what changed."""
        c = self.config
        report = {}
        in_window = self.start_step <= step < self.stop_step
        since_reset = step % self.reset_every if self.reset_every else step
        if in_window and step > 0 and step % self.every == 0 and since_reset >= c.pause_after_reset:
            report = self.refine(model, optimizers, step)
        if self.reset_every and step > 0 and step % self.reset_every == 0 and step < self.stop_step:
            self.reset_opacity(model, optimizers)
            report["reset"] = 1
        return report

    @torch.no_grad()
    def refine(self, model: GaussianModel, optimizers, step: int) -> dict[str, int]:
        c = self.config
        params = model.params
        if self.state is None or self.state.grad_sum.shape[0] != len(model):
            self.state = DensifyState.zeros(len(model), model.device)
        avg = self.state.grad_sum / self.state.count.clamp_min(1)
        max_scale = torch.exp(params["scales"]).amax(dim=1)
        grow = (avg >= c.grow_grad2d) & (self.state.count > 0)
        room = c.max_gaussians - len(model)
        if room <= 0:
            grow[:] = False
        elif int(grow.sum()) > room:  # keep the largest gradients within the budget
            idx = grow.nonzero().flatten()
            keep = idx[avg[idx].topk(room).indices]
            grow[:] = False
            grow[keep] = True
        clone = grow & (max_scale <= c.grow_scale3d * self.extent)
        split = grow & ~clone
        n_clone, n_split = int(clone.sum()), int(split.sum())

        if n_clone:
            append_rows(params, optimizers, {k: params[k][clone] for k in params.keys()})
        if n_split:
            split_idx = split.nonzero().flatten()
            append_rows(params, optimizers, self._split_samples(model, split_idx))
        # Prune: the split originals, transparent Gaussians, and (after the first reset) huge ones.
        n = len(model)
        prune = torch.zeros(n, dtype=torch.bool, device=model.device)
        prune[: split.shape[0]] |= split
        if self.prune_rule is None:
            low_opacity = torch.sigmoid(params["opacities"]) < c.prune_opacity
        else:
            thresholds = self.prune_rule(model, c.prune_opacity).to(params["opacities"])
            low_opacity = torch.sigmoid(params["opacities"]) < thresholds
        prune |= low_opacity
        if self.reset_every and step > self.reset_every:
            prune |= torch.exp(params["scales"]).amax(dim=1) > c.prune_scale3d * self.extent
        prune |= ~torch.isfinite(params["means"]).all(dim=1)
        n_prune = int(prune.sum())
        if n_prune:
            select_rows(params, optimizers, ~prune)
        self.state = DensifyState.zeros(len(model), model.device)
        report = {"clone": n_clone, "split": n_split, "prune": n_prune}
        if self.prune_rule is not None:
            report["prune_depth"] = int(low_opacity.sum())
        return report

    def _split_samples(self, model: GaussianModel, idx: torch.Tensor) -> dict[str, torch.Tensor]:
        """``split_samples`` new Gaussians per index, drawn from the parent's distribution, scales shrunk."""
        from metegs.cameras import quat_wxyz_to_rotmat

        c = self.config
        p = model.params
        k = c.split_samples
        scales = torch.exp(p["scales"][idx])
        R = quat_wxyz_to_rotmat(p["quats"][idx])
        noise = torch.randn(k, idx.shape[0], 3, device=idx.device) * scales[None]
        means = (p["means"][idx][None] + torch.einsum("nij,knj->kni", R, noise)).reshape(-1, 3)
        new = {name: p[name][idx].repeat(k, *([1] * (p[name].dim() - 1))) for name in p.keys()}
        new["means"] = means
        new["scales"] = torch.log(scales / c.split_scale_divisor).repeat(k, 1)
        return new

    @torch.no_grad()
    def reset_opacity(self, model: GaussianModel, optimizers) -> None:
        """Set opacities to min(opacity, reset_opacity) and clear their Adam moments."""
        p = model.params["opacities"]
        p.data = torch.minimum(p.data, inverse_sigmoid(torch.tensor(self.config.reset_opacity)).to(p))
        state = optimizers["opacities"].state.get(p)
        if state:
            for key in ("exp_avg", "exp_avg_sq"):
                if key in state:
                    state[key].zero_()

    def state_dict(self) -> dict:
        return {} if self.state is None else {k: getattr(self.state, k) for k in ("grad_sum", "count", "max_radii")}

    def load_state_dict(self, d: dict) -> None:
        self.state = DensifyState(**d) if d else None
