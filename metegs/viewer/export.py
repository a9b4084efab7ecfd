"""What the viewer writes: the current view as PNG, the clean scene as PLY and weather-sweep videos
(`metegs.video`: H.264 MP4 that browsers play, with GIF and PNG-frame fallbacks)."""

from __future__ import annotations

import copy
from collections.abc import Iterable
from dataclasses import replace
from datetime import datetime
from pathlib import Path

import numpy as np
import viser

from metegs.gaussians.ply import save_ply
from metegs.meteo import intensity_class
from metegs.video import caption, save_png, to_uint8, write_video
from metegs.viewer.camera import (
    interpolate_poses,
    orbit_order,
    pose_of,
    render_height,
)
from metegs.viewer.render import Snapshot, render_frame
from metegs.viewer.weather import (
    sweep_rates,
)

__all__ = ["save_png", "save_scene_ply", "write_video"]


def save_scene_ply(
    path: Path, snapshot: Snapshot, comments: Iterable[str] = (), world_to_file: np.ndarray | None = None
) -> Path:
    """The clean scene Gaussians of ``snapshot`` as an INRIA-layout PLY (no weather Gaussians), turned by
    ``world_to_file`` [3, 3] when given (see `save_ply`)."""
    save_ply(snapshot.state, path, comments=comments, world_to_file=world_to_file)
    return Path(path)


class ViewerExports:
    """The exports of `metegs.viewer.server.Viewer` (into its ``output_dir``)."""

    def export_png(self, client: viser.ClientHandle | None = None) -> Path:
        """The current view at full resolution -> OUTPUT/view-<time>.png."""
        pose, canvas = self._client_pose(client)
        image = self.render(pose, render_height(canvas[0], canvas[1], int(self.max_side.value)))
        path = save_png(self.output_dir / f"view-{_stamp()}-{self.mode}.png", image)
        self._exported(client, path, "view saved")
        return path

    def export_ply(self, client: viser.ClientHandle | None = None) -> Path:
        """The clean scene Gaussians (never weather) -> OUTPUT/scene-step-N.ply."""
        snap = self.snapshot
        path = save_scene_ply(self.output_dir / f"scene-step-{snap.step:06d}.ply", snap, **self.trainer.ply_layout())
        self._exported(client, path, "clean scene saved", download=False)
        return path

    def export_sweep(
        self,
        client: viser.ClientHandle | None = None,
        frames: int | None = None,
        path_kind: str | None = None,
        fmt: str | None = None,
    ) -> Path:
        """A camera-path video of a rain sweep (``From`` -> ``To`` mm/h, log-spaced) with the other sliders' weather."""
        frames = int(frames or self.sweep_frames.value)
        path_kind = path_kind or self.sweep_path.value
        fmt = fmt or self.sweep_format.value
        height = int(self.sweep_height.value)
        base = self.current_values()
        rates = sweep_rates(frames, float(self.sweep_low.value), float(self.sweep_high.value))
        ds = self.trainer.dataset
        if path_kind == "current view":
            pose = self._client_pose(client)[0]
            poses = [pose] * frames
        else:
            train = ds.cameras[ds.train_indices]
            order = orbit_order(train, self.up)
            aspect = float(train.width[0]) / float(train.height[0])
            keys = [pose_of(train, i, aspect) for i in order]
            poses = [interpolate_poses(keys, i / frames) for i in range(frames)]
        weather = copy.copy(self.weather)  # same models and scene, its own θ
        self.sweep_progress.visible = True

        def frames_iter():
            for i, (rate, pose) in enumerate(zip(rates, poses)):
                weather.set_values(replace(base, precip_mm_h=rate))
                camera = pose.cameras(height, self.device)
                self._use_threads()
                rgb = to_uint8(render_frame(self.rasterizer, self.snapshot, camera, self.background, weather))
                self.sweep_progress.value = 100.0 * (i + 1) / frames
                yield caption(rgb, f"{rate:.3g} mm/h  {intensity_class(rate)}")

        out = self.output_dir / f"sweep-{_stamp()}.{fmt}"
        try:
            written = write_video(out, frames_iter(), fps=float(self.sweep_fps.value))
        finally:
            self.sweep_progress.visible = False
        self._exported(client, written, "weather sweep saved", download=written.is_file())
        return written

    def _exported(self, client, path: Path, title: str, download: bool = True) -> None:
        self.exports.append(path)
        self.export_md.content = f"{title}: `{path}`"
        if self.console is not None:
            self.console.print(f"viewer: {title}: {path}")
        if client is not None:
            client.add_notification(title, str(path), auto_close_seconds=6.0)
            if download and path.is_file() and path.stat().st_size < 200 * 2**20:
                client.send_file_download(path.name, path.read_bytes())


def _stamp() -> str:
    return datetime.now().strftime("%Y%m%d-%H%M%S-%f")[:-3]
