"""The scene Gaussian parameters (pre-activation, as optimised) and the activated set a rasteriser draws."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from metegs.gaussians.sh import num_sh_bases, rgb_to_sh

PARAM_NAMES = ("means", "scales", "quats", "opacities", "sh0", "shN")
"""Parameter groups: means [N,3], log-scales [N,3], quaternions wxyz [N,4], opacity logits [N],
SH DC [N,1,3], higher SH [N,K-1,3]."""


@dataclass
class GaussianSet:
    """Activated Gaussians ready to rasterise (all tensors share N; gradients flow back to the parameters)."""

    means: torch.Tensor
    """[N, 3] world positions."""
    quats: torch.Tensor
    """[N, 4] rotations (w, x, y, z); need not be normalised."""
    scales: torch.Tensor
    """[N, 3] standard deviations along the local axes (linear, > 0)."""
    opacities: torch.Tensor
    """[N] opacities in (0, 1)."""
    sh: torch.Tensor
    """[N, K, 3] SH coefficients (K = 1 for a constant colour)."""

    def __len__(self) -> int:
        return self.means.shape[0]

    @staticmethod
    def cat(sets: list[GaussianSet]) -> GaussianSet:
        """Concatenate sets; SH bases are zero-padded to the largest K."""
        k = max(s.sh.shape[1] for s in sets)
        pad = lambda sh: torch.cat([sh, sh.new_zeros(sh.shape[0], k - sh.shape[1], 3)], 1)  # noqa: E731
        return GaussianSet(
            torch.cat([s.means for s in sets]),
            torch.cat([s.quats for s in sets]),
            torch.cat([s.scales for s in sets]),
            torch.cat([s.opacities for s in sets]),
            torch.cat([pad(s.sh) for s in sets]),
        )


def inverse_sigmoid(x: torch.Tensor) -> torch.Tensor:
    x = x.clamp(1e-6, 1 - 1e-6)
    return torch.log(x / (1 - x))


def knn_mean_distance(points: torch.Tensor, k: int = 3, chunk: int = 4096) -> torch.Tensor:
    """Mean distance of each point to its ``k`` nearest neighbours. points: [P, 3] -> [P]."""
    p = points.shape[0]
    if p <= 1:
        return torch.ones(p, dtype=points.dtype, device=points.device)
    k = min(k, p - 1)
    out = []
    for start in range(0, p, chunk):
        d = torch.cdist(points[start : start + chunk], points)
        d = d.topk(k + 1, dim=1, largest=False).values[:, 1:]
        out.append(d.mean(dim=1))
    return torch.cat(out)


class GaussianModel(nn.Module):
    """Scene Gaussians as optimised parameters (log-scales, logit opacities, wxyz quaternions, SH)."""

    def __init__(self, params: dict[str, torch.Tensor], sh_degree: int = 3):
        super().__init__()
        self.max_sh_degree = sh_degree
        self.active_sh_degree = 0
        self.params = nn.ParameterDict({k: nn.Parameter(params[k].contiguous()) for k in PARAM_NAMES})

    # --- construction -------------------------------------------------------------------------------
    @staticmethod
    def empty_params(n: int, sh_degree: int, device: torch.device | str = "cpu") -> dict[str, torch.Tensor]:
        return {
            "means": torch.zeros(n, 3, device=device),
            "scales": torch.zeros(n, 3, device=device),
            "quats": torch.tensor([1.0, 0, 0, 0], device=device).repeat(n, 1),
            "opacities": torch.zeros(n, device=device),
            "sh0": torch.zeros(n, 1, 3, device=device),
            "shN": torch.zeros(n, num_sh_bases(sh_degree) - 1, 3, device=device),
        }

    @classmethod
    def from_points(
        cls,
        points: np.ndarray | torch.Tensor,
        colors: np.ndarray | torch.Tensor | None = None,
        sh_degree: int = 3,
        init_opacity: float = 0.1,
        scale_multiplier: float = 1.0,
        device: torch.device | str = "cpu",
    ) -> GaussianModel:
        """Isotropic Gaussians at ``points`` [P, 3] with ``colors`` [P, 3] in [0, 1] (grey if None),
        scale = mean distance to the 3 nearest neighbours (as in 3DGS), opacity ``init_opacity``."""
        pts = torch.as_tensor(np.asarray(points), dtype=torch.float32, device=device)
        n = pts.shape[0]
        cols = (
            torch.full((n, 3), 0.5, device=device)
            if colors is None
            else torch.as_tensor(np.asarray(colors), dtype=torch.float32, device=device)
        )
        params = cls.empty_params(n, sh_degree, device)
        dist = knn_mean_distance(pts).clamp_min(1e-7) * scale_multiplier
        params["means"] = pts.clone()
        params["scales"] = torch.log(dist)[:, None].repeat(1, 3)
        params["opacities"] = inverse_sigmoid(torch.full((n,), init_opacity, device=device))
        params["sh0"] = rgb_to_sh(cols.clamp(0, 1))[:, None, :]
        return cls(params, sh_degree)

    @classmethod
    def random_in_box(
        cls, low: np.ndarray, high: np.ndarray, n: int, sh_degree: int = 3, seed: int = 0, **kwargs
    ) -> GaussianModel:
        """``n`` Gaussians uniformly in the box [low, high] with random colours."""
        g = torch.Generator().manual_seed(seed)
        lo, hi = torch.as_tensor(low, dtype=torch.float32), torch.as_tensor(high, dtype=torch.float32)
        pts = lo + (hi - lo) * torch.rand(n, 3, generator=g)
        return cls.from_points(pts, torch.rand(n, 3, generator=g), sh_degree, **kwargs)

    # --- access ------------------------------------------------------------------------------------
    def __len__(self) -> int:
        return self.params["means"].shape[0]

    @property
    def device(self) -> torch.device:
        return self.params["means"].device

    @property
    def means(self) -> torch.Tensor:
        return self.params["means"]

    def activated(self) -> GaussianSet:
        """The Gaussians for the rasteriser, SH truncated to the active degree."""
        k = num_sh_bases(self.active_sh_degree)
        sh = torch.cat([self.params["sh0"], self.params["shN"][:, : k - 1]], dim=1)
        return GaussianSet(
            means=self.params["means"],
            quats=self.params["quats"],
            scales=torch.exp(self.params["scales"]),
            opacities=torch.sigmoid(self.params["opacities"]),
            sh=sh,
        )

    def state_tensors(self) -> dict[str, torch.Tensor]:
        """Detached copies of the parameters (for checkpoints and export)."""
        return {k: v.detach().clone() for k, v in self.params.items()}

    @classmethod
    def from_state(cls, state: dict[str, torch.Tensor], sh_degree: int | None = None) -> GaussianModel:
        """Rebuild a model from ``state_tensors()`` (the SH degree follows from shN if not given)."""
        k = state["shN"].shape[1] + 1
        degree = int(round(k**0.5)) - 1 if sh_degree is None else sh_degree
        return cls({n: state[n] for n in PARAM_NAMES}, degree)
