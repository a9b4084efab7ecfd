"""Pinhole cameras in the OpenCV convention (x right, y down, z forward), camera-to-world.

Convention converters live here and nowhere else.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch

from metegs.errors import DataError

# OpenGL/Blender camera axes (x right, y up, z back) -> OpenCV (x right, y down, z forward): flip y and z.
_GL_TO_CV = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))


def opengl_to_opencv(c2w: torch.Tensor) -> torch.Tensor:
    """Camera-to-world in OpenGL camera axes -> OpenCV camera axes. c2w: [..., 4, 4]."""
    return c2w @ _GL_TO_CV.to(c2w)


def opencv_to_opengl(c2w: torch.Tensor) -> torch.Tensor:
    """Camera-to-world in OpenCV camera axes -> OpenGL camera axes. c2w: [..., 4, 4]."""
    return c2w @ _GL_TO_CV.to(c2w)


def to_homogeneous(c2w_3x4: torch.Tensor) -> torch.Tensor:
    """[..., 3, 4] -> [..., 4, 4] with the row (0, 0, 0, 1) appended."""
    bottom = torch.zeros(*c2w_3x4.shape[:-2], 1, 4, dtype=c2w_3x4.dtype, device=c2w_3x4.device)
    bottom[..., 0, 3] = 1.0
    return torch.cat([c2w_3x4, bottom], dim=-2)


def rotation_to_quat_wxyz(R: torch.Tensor) -> torch.Tensor:
    """Rotation matrix [3, 3] -> unit quaternion (w, x, y, z) [4]."""
    m = R.double()
    t = m.trace()
    if t > 0:
        s = torch.sqrt(t + 1.0) * 2
        q = torch.stack([0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s])
    else:
        i = int(torch.argmax(torch.diagonal(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = torch.sqrt(1.0 + m[i, i] - m[j, j] - m[k, k]) * 2
        q = torch.empty(4, dtype=torch.float64)
        q[0] = (m[k, j] - m[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (m[j, i] + m[i, j]) / s
        q[1 + k] = (m[k, i] + m[i, k]) / s
    return (q / q.norm()).to(R.dtype)


def quat_wxyz_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    """Hamilton quaternions (w, x, y, z), normalised here: [..., 4] -> rotation matrices [..., 3, 3]."""
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(*q.shape[:-1], 3, 3)


@dataclass
class Cameras:
    """N pinhole cameras. All tensors have leading dimension N; poses are camera-to-world, OpenCV axes."""

    camera_to_worlds: torch.Tensor
    """[N, 4, 4] float32 camera-to-world matrices (OpenCV axes)."""
    fx: torch.Tensor
    """[N] focal length in pixels along x."""
    fy: torch.Tensor
    """[N] focal length in pixels along y."""
    cx: torch.Tensor
    """[N] principal point x in pixels (pixel centres at +0.5)."""
    cy: torch.Tensor
    """[N] principal point y in pixels."""
    width: torch.Tensor
    """[N] int64 image widths in pixels."""
    height: torch.Tensor
    """[N] int64 image heights in pixels."""
    exposure_time_s: torch.Tensor | None = None
    """[N] exposure times in seconds, or None when unknown."""

    @staticmethod
    def create(
        camera_to_worlds: torch.Tensor | np.ndarray,
        fx,
        fy,
        cx,
        cy,
        width,
        height,
        exposure_time_s=None,
    ) -> Cameras:
        """Build cameras from arrays or scalars (scalars are broadcast to all N views)."""
        c2w = torch.as_tensor(
            np.asarray(camera_to_worlds, dtype=np.float32)
            if isinstance(camera_to_worlds, np.ndarray)
            else camera_to_worlds
        ).float()
        if c2w.shape[-2:] == (3, 4):
            c2w = to_homogeneous(c2w)
        n = c2w.shape[0]

        def vec(v, dtype):
            return torch.as_tensor(v, dtype=dtype).reshape(-1).expand(n).clone()

        exp = None if exposure_time_s is None else vec(exposure_time_s, torch.float32)
        return Cameras(
            c2w,
            vec(fx, torch.float32),
            vec(fy, torch.float32),
            vec(cx, torch.float32),
            vec(cy, torch.float32),
            vec(width, torch.int64),
            vec(height, torch.int64),
            exp,
        )

    def __len__(self) -> int:
        return self.camera_to_worlds.shape[0]

    def __getitem__(self, idx) -> Cameras:
        if isinstance(idx, int):
            idx = [idx]
        pick = lambda t: None if t is None else t[idx]  # noqa: E731
        return Cameras(*(pick(getattr(self, f)) for f in self.__dataclass_fields__))

    @staticmethod
    def cat(parts: list[Cameras]) -> Cameras:
        """Concatenate cameras along the view dimension (optional fields kept only if every part has them)."""
        fields = {}
        for name in Cameras.__dataclass_fields__:
            values = [getattr(c, name) for c in parts]
            fields[name] = None if any(v is None for v in values) else torch.cat(values)
        return Cameras(**fields)

    def to(self, device: torch.device | str) -> Cameras:
        move = lambda t: None if t is None else t.to(device)  # noqa: E731
        return Cameras(*(move(getattr(self, f)) for f in self.__dataclass_fields__))

    @property
    def device(self) -> torch.device:
        return self.camera_to_worlds.device

    def world_to_cameras(self) -> torch.Tensor:
        """[N, 4, 4] world-to-camera (view) matrices, computed in float64 for accuracy."""
        return torch.linalg.inv(self.camera_to_worlds.double()).float()

    def intrinsics(self) -> torch.Tensor:
        """[N, 3, 3] intrinsic matrices K."""
        K = torch.zeros(len(self), 3, 3, dtype=self.fx.dtype, device=self.device)
        K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2], K[:, 2, 2] = self.fx, self.fy, self.cx, self.cy, 1.0
        return K

    @property
    def centers(self) -> torch.Tensor:
        """[N, 3] camera centres in world coordinates."""
        return self.camera_to_worlds[:, :3, 3]

    def project(self, points: torch.Tensor) -> torch.Tensor:
        """Pixel position and depth of points [P, 3] in every view -> [C, P, 3] (u, v, z; u and v hold no meaning
        where z ≤ 0)."""
        w2c = self.world_to_cameras()
        p = torch.einsum("cij,pj->cpi", w2c[:, :3, :3], points) + w2c[:, None, :3, 3]
        z = p[..., 2]
        u = self.fx[:, None] * p[..., 0] / z.clamp_min(1e-6) + self.cx[:, None]
        v = self.fy[:, None] * p[..., 1] / z.clamp_min(1e-6) + self.cy[:, None]
        return torch.stack([u, v, z], dim=-1)

    def sees(self, points: torch.Tensor) -> torch.Tensor:
        """Which views see each point inside their image and in front. points [P, 3] -> [C, P] bool."""
        u, v, z = self.project(points).unbind(-1)
        return (z > 1e-3) & (u >= 0) & (u < self.width[:, None]) & (v >= 0) & (v < self.height[:, None])

    def resized(self, width: int, height: int) -> Cameras:
        """Cameras for images resized to ``width`` x ``height`` (all views); intrinsics scale with the size."""
        sx = width / self.width.double()
        sy = height / self.height.double()
        return replace(
            self,
            fx=(self.fx.double() * sx).float(),
            cx=(self.cx.double() * sx).float(),
            fy=(self.fy.double() * sy).float(),
            cy=(self.cy.double() * sy).float(),
            width=torch.full_like(self.width, width),
            height=torch.full_like(self.height, height),
        )

    def validate(self, source: str = "cameras") -> None:
        """Raise DataError naming ``source`` if any camera is impossible (non-finite, bad focal, bad pose)."""
        n = len(self)
        if self.camera_to_worlds.shape != (n, 4, 4):
            raise DataError(source, f"camera_to_worlds must be [N, 4, 4], got {tuple(self.camera_to_worlds.shape)}")
        for name in ("fx", "fy", "cx", "cy"):
            t = getattr(self, name)
            if not torch.isfinite(t).all():
                raise DataError(source, f"non-finite intrinsic {name} in view(s) {_bad(~torch.isfinite(t))}")
        for name in ("fx", "fy", "width", "height"):
            t = getattr(self, name)
            if (t <= 0).any():
                raise DataError(source, f"{name} must be positive; bad view(s) {_bad(t <= 0)}")
        if not torch.isfinite(self.camera_to_worlds).all():
            raise DataError(source, "non-finite camera pose")
        R = self.camera_to_worlds[:, :3, :3].double()
        err = (R @ R.transpose(1, 2) - torch.eye(3, dtype=R.dtype)).abs().amax(dim=(1, 2))
        bad = (err > 1e-3) | (torch.linalg.det(R) < 0)
        if bad.any():
            raise DataError(source, f"camera rotation is not a proper rotation in view(s) {_bad(bad)}")


def _bad(mask: torch.Tensor) -> str:
    idx = mask.nonzero().flatten().tolist()
    return ", ".join(map(str, idx[:10])) + (" ..." if len(idx) > 10 else "")


def look_at_point(cameras: Cameras) -> torch.Tensor:
    """Least-squares point closest to all optical axes. -> [3]."""
    c = cameras.centers.double()
    d = cameras.camera_to_worlds[:, :3, 2].double()
    d = d / d.norm(dim=1, keepdim=True)
    eye = torch.eye(3, dtype=torch.float64, device=c.device)
    P = eye[None] - d[:, :, None] * d[:, None, :]
    A = P.sum(0)
    b = (P @ c[:, :, None]).sum(0)
    if torch.linalg.matrix_rank(A) < 3:  # parallel axes (forward-facing): a point in front of the mean camera
        return (c.mean(0) + d.mean(0) * c.std(0).norm().clamp_min(1.0)).float()
    return torch.linalg.solve(A, b).flatten().float()
