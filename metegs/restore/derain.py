"""Single-image rain-streak removal by image decomposition and sparse coding (Kang et al. 2012).

L.-W. Kang, C.-W. Lin, Y.-H. Fu, "Automatic Single-Image-Based Rain Streaks Removal via Image
Decomposition", IEEE Transactions on Image Processing 21(4):1742-1755, 2012. The method, as here:

1. the bilateral filter splits the luma Y into a low-frequency part ``Y_LF`` (rain streaks are thin and
   are smoothed away) and a high-frequency part ``Y_HF = Y − Y_LF`` that holds the streaks and the
   scene's edges and texture;
2. a dictionary ``D_HF`` is learned from the p x p patches of ``Y_HF`` (sparse representation);
3. every atom gets a HOG descriptor and K-means (K = 2) splits the atoms into two sub-dictionaries;
4. the rain sub-dictionary is the cluster whose atoms have the smaller variance of gradient orientation
   (streaks share one direction, scene structure does not);
5. morphological component analysis: every patch of ``Y_HF`` is sparse-coded over ``[D_G | D_R]`` with
   orthogonal matching pursuit, and only its geometric part ``D_G θ_G`` is kept; overlapping patches are
   averaged into ``Y_HF^G``;
6. the derained luma is ``Y_LF + Y_HF^G``; the chroma of the input is kept.

Where this implementation departs from the paper, and why:

- the dictionary is learned by MOD (method of optimal directions, Engan et al. 1999) alternating with OMP
  coding, instead of Mairal et al.'s online ℓ1 dictionary learning (SPAMS): the same sparse model, learned
  by a batch algorithm that needs nothing beyond numpy;
- the orientation spread of an atom is the circular variance of its doubled gradient angles weighted by
  gradient magnitude (orientations are axial, modulo 180°);
- patch size and dictionary size follow the image: p = 16 px with 1024 atoms (the paper's setting) from
  ``large_width_px`` up, else p = 8 px with 256 atoms (the same 4x over-completeness), so that the
  small images of CPU training still hold enough patches; patches for the reconstruction are taken with a
  stride of p/4 instead of 1, which leaves the average of the overlaps nearly unchanged at a 16th of the
  cost.

Assumptions (the method's): streaks are thin, bright and mostly of one orientation (as wind-driven rain
is within one exposure); they live in the high frequencies; scene texture of the streaks' orientation is
removed with them (the known weakness of the method). It does nothing for fog, and it is blind: it also
"removes" one cluster of atoms from a photo without rain.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
import torch

from metegs.config import InstantiateConfig
from metegs.restore.base import check_image


@dataclass
class KangDerainConfig(InstantiateConfig):
    """Rain-streak removal by bilateral decomposition, dictionary learning and HOG clustering (Kang et al. 2012)."""

    _target: type = field(default_factory=lambda: KangDerain, repr=False)
    patch_px: int = 0
    """Patch side p; 0: 16 from ``large_width_px`` up (the paper), else 8."""
    large_width_px: int = 320
    """Image width from which the paper's 16-px patches are used (with ``patch_px`` 0)."""
    atoms_per_dim: int = 4
    """Dictionary size as a multiple of p² (1024 atoms for 16 x 16 patches in the paper: 4)."""
    sparsity: int = 8
    """Non-zero coefficients per patch (OMP)."""
    train_patches: int = 3000
    """Patches drawn (seeded) from the image to learn the dictionary."""
    iterations: int = 10
    """MOD iterations."""
    bilateral_sigma_space_px: float = 0.0
    """Spatial σ of the bilateral filter, px; 0: p / 4 (wider than a streak, narrower than a patch)."""
    bilateral_sigma_color: float = 0.3
    """Range σ of the bilateral filter on luma in [0, 1] (large: streak contrast is smoothed away)."""
    seed: int = 0
    """Seed of the patch sampling and dictionary initialisation."""


def omp(D: torch.Tensor, X: torch.Tensor, sparsity: int) -> torch.Tensor:
    """Batched orthogonal matching pursuit. D [m, K] (unit columns), X [m, N] -> codes [K, N]."""
    m, K = D.shape
    N = X.shape[1]
    T = max(1, min(sparsity, K, m))
    gram = D.T @ D
    dtx = D.T @ X
    cols = torch.arange(N)
    sel = torch.zeros((N, T), dtype=torch.long)
    codes = torch.zeros((K, N), dtype=X.dtype)
    corr = dtx.abs()
    eye = torch.eye(T, dtype=X.dtype)
    for t in range(T):
        if t:
            corr[sel[:, :t].T, cols[None, :]] = -1.0  # never pick an atom twice
        sel[:, t] = corr.argmax(dim=0)
        s = sel[:, : t + 1]
        g = gram[s[:, :, None], s[:, None, :]] + 1e-6 * eye[: t + 1, : t + 1]
        b = dtx[s, cols[:, None]]
        coef = torch.linalg.solve(g, b[..., None])[..., 0]
        codes.zero_()
        codes[s.T, cols[None, :]] = coef.T
        if t + 1 < T:
            corr = (D.T @ (X - D @ codes)).abs()
    return codes


def learn_dictionary(
    X: torch.Tensor, atoms: int, sparsity: int, iterations: int, rng: np.random.Generator
) -> torch.Tensor:
    """MOD dictionary learning: X [m, N] -> D [m, atoms] with unit columns."""
    m, N = X.shape
    pool = np.flatnonzero((X.norm(dim=0) > 1e-6).numpy())
    noise = lambda shape: torch.from_numpy(rng.standard_normal(shape).astype(np.float32)).to(X.dtype)  # noqa: E731
    if pool.size == 0:  # a flat image: any dictionary will do
        D = noise((m, atoms))
        return D / D.norm(dim=0, keepdim=True)
    D = X[:, torch.from_numpy(rng.choice(pool, atoms, replace=pool.size < atoms))].clone()
    D += 1e-3 * noise(tuple(D.shape))
    D /= D.norm(dim=0, keepdim=True)
    eye = torch.eye(atoms, dtype=X.dtype)
    for _ in range(iterations):
        A = omp(D, X, sparsity)
        D = torch.linalg.solve(A @ A.T + 1e-6 * eye, A @ X.T).T  # D = X Aᵀ (A Aᵀ)⁻¹
        n = D.norm(dim=0)
        unused = n < 1e-8
        if bool(unused.any()):  # re-seed atoms no patch uses with random patches
            D[:, unused] = X[:, torch.from_numpy(rng.choice(pool, int(unused.sum())))]
            n = D.norm(dim=0)
        D /= n.clamp_min(1e-12)[None, :]
    return D


def patch_positions(size: int, p: int, stride: int) -> np.ndarray:
    """Top-left corners along one axis covering [0, size) with p-long patches (the last one flush)."""
    last = size - p
    pos = list(range(0, last + 1, stride))
    if pos[-1] != last:
        pos.append(last)
    return np.asarray(pos)


def extract_patches(img: np.ndarray, p: int, ys: np.ndarray, xs: np.ndarray) -> np.ndarray:
    """[p², len(ys)·len(xs)] column patches of a 2D image."""
    windows = np.lib.stride_tricks.sliding_window_view(img, (p, p))
    return windows[ys[:, None], xs[None, :]].reshape(-1, p * p).T


def assemble_patches(cols: np.ndarray, shape: tuple[int, int], p: int, ys: np.ndarray, xs: np.ndarray) -> np.ndarray:
    """Average overlapping column patches [p², N] back into an image of ``shape``."""
    out = np.zeros(shape, dtype=np.float64)
    weight = np.zeros(shape, dtype=np.float64)
    patches = cols.T.reshape(len(ys), len(xs), p, p)
    for i, y in enumerate(ys):
        for j, x in enumerate(xs):
            out[y : y + p, x : x + p] += patches[i, j]
            weight[y : y + p, x : x + p] += 1.0
    return (out / np.maximum(weight, 1.0)).astype(np.float32)


def orientation_spread(atom: np.ndarray) -> float:
    """Circular variance in [0, 1] of an atom's gradient orientations (axial: angles doubled), by magnitude."""
    gy, gx = np.gradient(atom.astype(np.float64))
    mag = np.hypot(gx, gy)
    total = mag.sum()
    if total <= 1e-12:
        return 1.0
    angle2 = 2.0 * np.arctan2(gy, gx)
    resultant = np.hypot((mag * np.cos(angle2)).sum(), (mag * np.sin(angle2)).sum()) / total
    return float(1.0 - resultant)


def hog_features(D: np.ndarray, p: int) -> np.ndarray:
    """[K, F] HOG descriptors (Dalal & Triggs: 9 orientations, p/2 cells) of the atoms of D [p², K]."""
    from skimage.feature import hog

    feats = []
    for k in range(D.shape[1]):
        atom = D[:, k].reshape(p, p)
        span = atom.max() - atom.min()
        atom = (atom - atom.min()) / span if span > 1e-12 else np.zeros_like(atom)
        feats.append(hog(atom, orientations=9, pixels_per_cell=(p // 2, p // 2), cells_per_block=(1, 1)))
    return np.asarray(feats, dtype=np.float64)


def kmeans2(F: np.ndarray, iterations: int = 100) -> np.ndarray:
    """Two-cluster K-means labels [K] (deterministic: seeded with the two mutually farthest points found
    from the first one)."""
    a = int(np.argmax(((F - F[0]) ** 2).sum(1)))
    b = int(np.argmax(((F - F[a]) ** 2).sum(1)))
    centres = np.stack([F[a], F[b]])
    labels = np.zeros(len(F), dtype=np.int64)
    for _ in range(iterations):
        d = ((F[:, None, :] - centres[None]) ** 2).sum(-1)
        new = d.argmin(1)
        if (new == labels).all() and _ > 0:
            break
        labels = new
        for c in (0, 1):
            if (labels == c).any():
                centres[c] = F[labels == c].mean(0)
    return labels


class KangDerain:
    """Kang et al.'s deraining (see the module docstring)."""

    name = "kang2012"
    removes = frozenset({"rain"})

    def __init__(self, config: KangDerainConfig | None = None):
        self.config = config or KangDerainConfig()

    def patch_size(self, width: int) -> int:
        c = self.config
        return c.patch_px if c.patch_px > 0 else (16 if width >= c.large_width_px else 8)

    def split(self, luma: np.ndarray, p: int) -> tuple[np.ndarray, np.ndarray]:
        """(low-frequency, high-frequency) parts of the luma by the bilateral filter."""
        c = self.config
        sigma_space = c.bilateral_sigma_space_px if c.bilateral_sigma_space_px > 0 else p / 4.0
        d = int(2 * np.ceil(2 * sigma_space) + 1)
        low = cv2.bilateralFilter(luma, d, c.bilateral_sigma_color, sigma_space, borderType=cv2.BORDER_REFLECT)
        return low, luma - low

    def decompose(self, high: np.ndarray, p: int) -> tuple[np.ndarray, dict]:
        """The geometric (non-rain) part of the high frequencies [H, W] and what was found."""
        from metegs.render.cpu_backend import single_thread

        c = self.config
        rng = np.random.default_rng(c.seed)
        H, W = high.shape
        X_all = extract_patches(high, p, patch_positions(H, p, 1), patch_positions(W, p, 1))
        pick = rng.choice(X_all.shape[1], min(c.train_patches, X_all.shape[1]), replace=False)
        atoms = c.atoms_per_dim * p * p
        stride = max(1, p // 4)
        ys, xs = patch_positions(H, p, stride), patch_positions(W, p, stride)
        with single_thread():  # small products: threads that busy-wait on a loaded machine only slow them down
            train = torch.from_numpy(np.ascontiguousarray(X_all[:, pick], dtype=np.float32))
            D = learn_dictionary(train, atoms, c.sparsity, c.iterations, rng)
            Dn = D.numpy()
            labels = kmeans2(hog_features(Dn, p))
            spread = np.array([orientation_spread(Dn[:, k].reshape(p, p)) for k in range(atoms)])
            means = [spread[labels == k].mean() if (labels == k).any() else np.inf for k in (0, 1)]
            rain = int(np.argmin(means))
            X = torch.from_numpy(np.ascontiguousarray(extract_patches(high, p, ys, xs), dtype=np.float32))
            codes = omp(D, X, c.sparsity)
            codes[torch.from_numpy(labels == rain)] = 0.0
            geometric = assemble_patches((D @ codes).numpy(), (H, W), p, ys, xs)
        info = {"patch_px": p, "atoms": atoms, "rain_atoms": int((labels == rain).sum()), "spread": means}
        return geometric, info

    def restore(self, image: np.ndarray) -> np.ndarray:
        image = check_image(image, self.name)
        H, W = image.shape[:2]
        p = self.patch_size(W)
        if H < p or W < p:
            return image.copy()  # too small to hold one patch: nothing to decompose
        ycc = cv2.cvtColor(image, cv2.COLOR_RGB2YCrCb)
        luma = np.ascontiguousarray(ycc[..., 0])
        low, high = self.split(luma, p)
        geometric, self.last_info = self.decompose(high, p)
        ycc[..., 0] = low + geometric
        return np.clip(cv2.cvtColor(ycc, cv2.COLOR_YCrCb2RGB), 0.0, 1.0).astype(np.float32)
