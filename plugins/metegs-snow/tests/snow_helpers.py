"""Small cameras and θ for the snow tests (independent of metegs' own test helpers)."""

import torch
from metegs.cameras import Cameras
from metegs.meteo import CameraSpec, theta_from_values
from metegs.weather.base import WeatherScene

W = H = 48
F = 48.0
FAR_M = 4.0


def cameras(n: int = 1, shift: float = 0.05) -> Cameras:
    """Cameras at the origin (+ x shifts) looking down +z (OpenCV)."""
    c2w = torch.eye(4).repeat(n, 1, 1)
    c2w[:, 0, 3] = torch.arange(n) * shift
    return Cameras.create(c2w, F, F, W / 2, H / 2, W, H)


def scene(n_views: int = 1, up=(0.0, -1.0, 0.0), seed: int = 3, images=None) -> WeatherScene:
    """World up -y: the cameras look horizontally; up (0, 0, -1): they look straight down."""
    return WeatherScene(cameras(n_views), torch.tensor(up), 1.0, images, seed=seed)


def theta(rate_mm_h: float, wind_m_s: float = 0.0, wind_from_deg: float | None = None, exposure_s: float = 1 / 60):
    camera = CameraSpec.from_intrinsics(F, W, H, exposure_s=exposure_s, far_m=FAR_M)
    return theta_from_values(rate_mm_h, None, wind_m_s, wind_from_deg, camera=camera)
