"""The browser viewer (viser): the scene rendered by the run's rasteriser, clean or with met-driven weather.

    metegs-train metegs-full --viewer          # live: watch, pause / step, curves
    metegs-view outputs/synthetic/metegs-full/<run>

`Viewer` serves a trainer's scene; `start_live_viewer` attaches one to a trainer before ``train()``.
"""

from metegs.viewer.server import Viewer, ViewerConfig, announce, start_live_viewer

__all__ = ["Viewer", "ViewerConfig", "announce", "start_live_viewer"]
