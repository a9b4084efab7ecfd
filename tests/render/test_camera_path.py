"""Camera paths: interpolation through the views, a spiral looking at the focus, nerfstudio camera_path.json."""

import json
import math

import numpy as np
import pytest
import torch

from metegs.cameras import Cameras, opengl_to_opencv
from metegs.errors import DataError
from metegs.render.camera_path import interpolate, read_camera_path, spiral


def orbit(n=4) -> Cameras:
    """``n`` cameras on an arc around the origin, looking at it (OpenCV axes, world +z up)."""
    poses = []
    for a in np.linspace(0.0, 1.5, n):
        eye = np.array([4 * math.cos(a), 4 * math.sin(a), 1.0])
        forward = -eye / np.linalg.norm(eye)
        right = np.cross(forward, [0.0, 0.0, 1.0])
        right /= np.linalg.norm(right)
        m = np.eye(4)
        m[:3, :3] = np.stack([right, np.cross(forward, right), forward], axis=1)
        m[:3, 3] = eye
        poses.append(m)
    return Cameras.create(np.stack(poses), 50.0, 50.0, 32.0, 24.0, 64, 48)


def test_interpolation_passes_through_every_view_in_order():
    cams = orbit(4)
    path = interpolate(cams, 3 * 3 + 1)  # three frames per gap: the views are frames 0, 3, 6, 9
    assert len(path) == 10 and int(path.width[0]) == 64 and float(path.fx[0]) == 50.0
    torch.testing.assert_close(path.camera_to_worlds[::3], cams.camera_to_worlds, atol=1e-5, rtol=0)
    R = path.camera_to_worlds[:, :3, :3].double()
    torch.testing.assert_close(
        R @ R.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(10, 3, 3), atol=1e-5, rtol=0
    )
    steps = (path.centers[1:] - path.centers[:-1]).norm(dim=1)
    assert steps.max() < 3 * steps.min()  # smooth: no jumps between the views


def test_spiral_looks_at_the_focus_from_around_the_mean_view():
    cams = orbit(5)
    focus = torch.tensor([0.2, -0.1, 0.3])
    path = spiral(cams, 12, focus)
    forward = path.camera_to_worlds[:, :3, 2].double()
    to_focus = focus.double() - path.centers.double()
    cos = (forward * to_focus).sum(1) / to_focus.norm(dim=1)
    assert torch.all(cos > 1 - 1e-6)
    offsets = (path.centers - cams.centers.mean(0)).norm(dim=1)
    assert float(offsets.std()) < 1e-4 and float(offsets.mean()) > 0  # a circle around the mean camera
    assert torch.all(path.camera_to_worlds[:, 2, 1] < 0)  # image "down" stays down (world -z)


def test_nerfstudio_camera_path_file(tmp_path):
    gl = torch.eye(4)
    gl[:3, 3] = torch.tensor([1.0, 2.0, 3.0])
    keys = [{"camera_to_world": gl.reshape(-1).tolist(), "fov": 60.0}] * 3
    path = tmp_path / "camera_path.json"
    path.write_text(json.dumps({"render_width": 80, "render_height": 60, "seconds": 1.5, "camera_path": keys}))
    cams, fps = read_camera_path(path)
    assert len(cams) == 3 and fps == pytest.approx(2.0)
    assert float(cams.fy[0]) == pytest.approx(30.0 / math.tan(math.radians(30.0)))
    torch.testing.assert_close(cams.camera_to_worlds[0], opengl_to_opencv(gl))
    for bad, field in (
        ({"camera_path": []}, "non-empty 'camera_path'"),
        ({"render_width": 80, "camera_path": keys}, "render_height"),
        ({"render_width": 80, "render_height": 60, "camera_path": [{"fov": 40}]}, r"camera_path\[0\]"),
        ({"render_width": 80, "render_height": 60, "camera_path": [{**keys[0], "fov": 200}]}, "fov in"),
    ):
        path.write_text(json.dumps(bad))
        with pytest.raises(DataError, match=field):
            read_camera_path(path)
