"""Rotate Gaussians rigidly (positions, orientations and view-dependent colour), and the rotation that stands a
scene upright in common splat viewers.

The INRIA 3DGS outputs, and the COLMAP worlds they come from, have their up direction along −y (the OpenCV
camera's y points down the image), and viewers made for them (SuperSplat) show such files upright. A scene whose
world is z-up (the built-in scene, Blender and nerfstudio captures) would lie on its back there, so `scene.ply` is
written in that y-down convention (`upright_rotation`) and the rotation is recorded in its header, from which
`metegs.gaussians.ply.load_ply` undoes it.
"""

from __future__ import annotations

from collections.abc import Mapping
from functools import lru_cache

import numpy as np
import torch

from metegs.cameras import rotation_to_quat_wxyz
from metegs.gaussians.sh import MAX_SH_DEGREE, eval_sh, num_sh_bases

FILE_UP = np.array([0.0, -1.0, 0.0])
"""Up direction of the files splat viewers show upright: −y (the INRIA 3DGS / COLMAP convention)."""


def upright_rotation(up: np.ndarray) -> np.ndarray:
    """[3, 3] rotation, a signed permutation of the axes, that takes the world axis nearest to ``up`` [3] to
    `FILE_UP` with the least turn (identity when that axis already is −y; a y-up world turns half about x)."""
    up = np.asarray(up, np.float64)
    axis = int(np.argmax(np.abs(up)))
    source = np.zeros(3)
    source[axis] = np.sign(up[axis]) or 1.0
    if np.allclose(source, FILE_UP):
        return np.eye(3)
    if np.allclose(source, -FILE_UP):  # half a turn about x keeps the handedness
        return np.diag([1.0, -1.0, -1.0])
    # a quarter turn about the axis perpendicular to both
    k = np.cross(source, FILE_UP)
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.round(np.eye(3) + kx + kx @ kx)  # Rodrigues at 90°: I + K + K²


def sh_basis(dirs: torch.Tensor, degree: int = MAX_SH_DEGREE) -> torch.Tensor:
    """[N, (degree+1)²] real SH basis (the 3DGS convention of `eval_sh`, without its +0.5) at unit dirs [N, 3]."""
    k = num_sh_bases(degree)
    coeffs = torch.zeros(k, k, 3, dtype=dirs.dtype)
    coeffs[torch.arange(k), torch.arange(k), 0] = 1.0
    columns = [eval_sh(degree, coeffs[None, j].expand(len(dirs), k, 3), dirs)[:, 0] - 0.5 for j in range(k)]
    return torch.stack(columns, 1)


@lru_cache(maxsize=16)
def _sh_rotation_cached(rotation: tuple[float, ...], degree: int) -> torch.Tensor:
    r = torch.tensor(rotation, dtype=torch.float64).reshape(3, 3)
    sample = torch.randn(64, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    dirs = torch.nn.functional.normalize(sample, dim=1)
    before = sh_basis(dirs, degree)  # Y(d)
    after = sh_basis(dirs @ r, degree)  # Y(Rᵀd): what the rotated coefficients must give at d
    return torch.linalg.lstsq(before, after).solution  # c' = M c with Y(d)·c' = Y(Rᵀd)·c for every d


def sh_rotation(rotation: np.ndarray, degree: int = MAX_SH_DEGREE) -> torch.Tensor:
    """[(degree+1)², (degree+1)²] float64 matrix M that rotates SH coefficients: colour(R·d) of the rotated
    coefficients M·c equals colour(d) of c. Block-diagonal by degree (each band is closed under rotation); exact,
    from a least-squares fit over 64 directions."""
    return _sh_rotation_cached(tuple(float(v) for v in np.asarray(rotation, np.float64).reshape(-1)), degree)


def quat_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product a ⊗ b of wxyz quaternions, broadcast: [..., 4] x [..., 4] -> [..., 4]."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        -1,
    )


def is_rotation(rotation: np.ndarray) -> bool:
    """True for a proper [3, 3] rotation matrix (orthonormal to 1e-6, determinant +1)."""
    r = np.asarray(rotation, np.float64)
    return r.shape == (3, 3) and np.allclose(r @ r.T, np.eye(3), atol=1e-6) and np.linalg.det(r) > 0


def rotate_state(state: Mapping[str, torch.Tensor], rotation: np.ndarray) -> dict[str, torch.Tensor]:
    """Gaussians turned by ``rotation`` [3, 3] about the world origin: means [N, 3] and quats [N, 4] (wxyz) rotated,
    shN [N, K-1, 3] rotated so that each Gaussian shows the same colour towards the rotated directions; the
    other tensors as they were. ``state``: a ``state_tensors()``-style dict."""
    r = np.asarray(rotation, np.float64)
    if not is_rotation(r):
        raise ValueError(f"rotate_state: not a rotation matrix: {r.tolist()}")
    out = dict(state)
    means = state["means"]
    out["means"] = (means.double() @ torch.as_tensor(r, dtype=torch.float64).T.to(means.device)).to(means.dtype)
    q = state["quats"]
    turn = rotation_to_quat_wxyz(torch.as_tensor(r)).to(q.device)
    out["quats"] = quat_multiply(turn, q.double()).to(q.dtype)
    shn = state["shN"]
    k = shn.shape[1] + 1
    if k > 1:
        degree = int(round(k**0.5)) - 1
        m = sh_rotation(r, degree).to(shn.device)[1:, 1:]  # the DC term is the same in every direction
        out["shN"] = torch.einsum("ij,njc->nic", m, shn.double()).to(shn.dtype)
    return out
