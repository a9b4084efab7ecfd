"""Rasterisers: the backend-independent interface and backend selection."""

from metegs.render.base import RenderOutput, RenderSettings
from metegs.render.select import make_rasterizer

__all__ = ["RenderOutput", "RenderSettings", "make_rasterizer"]
