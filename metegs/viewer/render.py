"""Frames for the viewer: a detached copy of the scene Gaussians and a render of it, clean or with weather."""

from __future__ import annotations

import itertools
import threading

import torch

from metegs.cameras import Cameras
from metegs.gaussians.model import GaussianModel, GaussianSet
from metegs.render.base import RenderSettings
from metegs.viewer.weather import ViewerWeather
from metegs.weather.compose import render_with_weather

_ids = itertools.count(1)


class Snapshot:
    """The scene Gaussians at one training step, detached from training (safe to render from another thread).

    Taking one only copies the parameters (cheap, in the training thread); the activated Gaussians are computed on
    first use, by the thread that renders.
    """

    def __init__(self, state: dict[str, torch.Tensor], sh_degree: int, active_sh_degree: int, step: int):
        self.state = state
        """Parameter copies (``GaussianModel.state_tensors()`` layout: what PLY export writes)."""
        self.sh_degree = sh_degree
        """Maximum SH degree of the model."""
        self.active_sh_degree = active_sh_degree
        """SH degree rendered."""
        self.step = step
        """Training step the copy was taken at."""
        self.id = next(_ids)
        """Increases with every snapshot taken in this process."""
        self._gaussians: GaussianSet | None = None
        self._lock = threading.Lock()

    @classmethod
    def of(cls, model: GaussianModel, step: int) -> Snapshot:
        """Copy ``model`` now (call it where nothing is modifying the model: between training steps)."""
        with torch.no_grad():
            return cls(model.state_tensors(), model.max_sh_degree, model.active_sh_degree, step)

    @property
    def gaussians(self) -> GaussianSet:
        """Activated Gaussians at the active SH degree, ready to rasterise."""
        with self._lock:
            if self._gaussians is None:
                with torch.no_grad():
                    model = GaussianModel.from_state(self.state, self.sh_degree)
                    model.active_sh_degree = self.active_sh_degree
                    g = model.activated()
                    self._gaussians = GaussianSet(
                        *(t.detach() for t in (g.means, g.quats, g.scales, g.opacities, g.sh))
                    )
            return self._gaussians

    def __len__(self) -> int:
        return int(self.state["means"].shape[0])


@torch.no_grad()
def render_frame(
    rasterizer,
    snapshot: Snapshot,
    camera: Cameras,
    background: torch.Tensor,
    weather: ViewerWeather | None = None,
) -> torch.Tensor:
    """Render ``snapshot`` from one camera -> [H, W, 3] in [0, 1]; with ``weather``, through its models."""
    settings = RenderSettings(background=background, sh_degree=None)
    if weather is None:
        return rasterizer.render(snapshot.gaussians, camera, settings).rgb.clamp(0, 1)
    models = weather.models_for(camera)
    return render_with_weather(rasterizer, snapshot.gaussians, models, 0, camera, settings).rgb.clamp(0, 1)
