"""The browser viewer: a viser server whose scene view is rendered by the run's own rasteriser.

`Viewer` holds the server, the scene (frustums, thumbnails) and the connected browsers; its parts live beside it:
`metegs.viewer.frames` (the render thread and its scheduling: quick frames while the camera moves, full ones when it
stops, copies of the scene between training steps (through `TrainingControl`, a ``Trainer.step_hooks`` entry) within
``render_share`` of the wall time), `metegs.viewer.panels` (weather, training and export panels, whose callbacks only
change state and wake the render thread) and `metegs.viewer.export` (PNG, PLY and sweep videos).
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch
import viser

from metegs.render.select import make_rasterizer
from metegs.viewer.camera import (
    ViewPose,
    look_at_point,
    pose_of,
    start_pose,
    thumbnail,
)
from metegs.viewer.export import ViewerExports
from metegs.viewer.frames import FrameStats, ViewerFrames, _Client, _Job
from metegs.viewer.panels import ViewerPanels
from metegs.viewer.render import Snapshot
from metegs.viewer.training import TrainingControl
from metegs.viewer.weather import (
    run_weather,
)


@dataclass
class ViewerConfig:
    """Where the viewer listens and how hard it works."""

    host: str = "127.0.0.1"
    """Address to bind (0.0.0.0 exposes the viewer to the network)."""
    port: int = 7007
    """Port (the next free one when it is taken; 0: any free port)."""
    max_side: int = 1024
    """Longest side of a full-resolution frame, px (the browser canvas, capped)."""
    preview_seconds: float = 0.08
    """Time budget of a frame while the camera moves (its resolution follows)."""
    live_refresh_s: float = 6.0
    """While training runs, a still view is re-rendered with the newest Gaussians this often (each frame sent costs
    a browser without a GPU about a quarter of a second of drawing: docs/benchmark.md)."""
    same_frame_level: float = 0.5
    """A re-render of a still view that differs from the frame shown by less than this mean |difference| (8-bit
    levels) is not sent (every frame sent costs the browser a burst of WebGL redraws)."""
    panel_refresh_s: float = 2.0
    """While training runs, the training panel (numbers and curves) is updated this often."""
    render_share: float = 0.15
    """While training runs, the viewer renders at most this fraction of the wall time (on one thread)."""
    torch_threads_while_training: int = 1
    """While training runs with the `cpu` backend, torch's own ops (losses, Adam, autograd) use this many threads and
    the rasteriser's kernels keep the run's (their pool does not wait for a thread the browser holds up); 0: as
    configured. The run's own `torch_threads`, when set, takes precedence."""
    jpeg_quality: int = 90
    """JPEG quality of the frames sent to the browser."""
    thumbnail_px: int = 96
    """Longest side of the training-view thumbnails on the frustums."""
    output_dir: Path | None = None
    """Where exports go; None: RUN_DIR/viewer."""


class Viewer(ViewerPanels, ViewerFrames, ViewerExports):
    """A viser server showing a trainer's scene: clean or with weather driven by the met sliders.

    ``live=True`` attaches a `TrainingControl` to ``trainer.step_hooks`` (pause, step, curves); call
    `training_finished()` when ``trainer.train()`` returns. ``close()`` stops the server.
    """

    def __init__(self, trainer, config: ViewerConfig | None = None, live: bool = False, console=None):
        self.trainer = trainer
        self.config = config or ViewerConfig()
        self.live = live
        self.console = console
        self.control: TrainingControl | None = None
        if live:
            self.control = TrainingControl()
            trainer.step_hooks.append(self.control)
        self.device = trainer.device
        self.rasterizer = make_rasterizer(trainer.config.backend, self.device)
        self.background = trainer.background(training=False)
        self.snapshot = Snapshot.of(trainer.model, trainer.step)
        self._snapshot_time = time.perf_counter()
        self._threads = torch.get_num_threads()
        if live and not trainer.config.torch_threads:  # applied by trainer.train() on the training thread
            trainer.config = replace(trainer.config, torch_threads=self.config.torch_threads_while_training)
        self._lock = threading.RLock()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._clients: dict[int, _Client] = {}
        self._jobs: list[_Job] = []
        self._cost_per_px = {"clean": 2e-6, "weather": 4e-6}
        self._weather_version = 0
        self._suspend = False
        self.stats = FrameStats()
        self.last_error: str | None = None
        self.exports: list[Path] = []

        self._setup_weather()
        self.server = viser.ViserServer(host=self.config.host, port=self.config.port, label="metegs", verbose=False)
        self._setup_scene()
        self._build_gui()
        self.server.on_client_connect(self._on_connect)
        self.server.on_client_disconnect(self._on_disconnect)
        self._thread = threading.Thread(target=self._loop, name="metegs-viewer", daemon=True)
        self._thread.start()

    # --- addresses ---------------------------------------------------------------------------------
    @property
    def port(self) -> int:
        return self.server.get_port()

    @property
    def url(self) -> str:
        host = self.config.host
        shown = "127.0.0.1" if host in ("0.0.0.0", "", "::") else host
        return f"http://{shown}:{self.port}"

    @property
    def output_dir(self) -> Path:
        return (
            Path(self.config.output_dir)
            if self.config.output_dir is not None
            else Path(self.trainer.run_dir) / "viewer"
        )

    # --- setup -------------------------------------------------------------------------------------
    def _setup_weather(self) -> None:
        run = run_weather(self.trainer)
        self.weather, self.run_values = run.weather, run.values
        self.timeline, self.weather_note = run.timeline, run.note
        self.mode = "weather" if getattr(self.trainer.config, "weather", ()) else "clean"

    def _setup_scene(self) -> None:
        t = self.trainer
        ds = t.dataset
        up = np.asarray(t.scene.up, dtype=np.float64)
        self.up = up / np.linalg.norm(up)
        self.server.scene.set_up_direction(tuple(float(v) for v in self.up))
        centres = ds.cameras.camera_to_worlds[:, :3, 3].double().cpu().numpy()
        means = self.snapshot.state["means"]
        self.centre = means.median(0).values.double().cpu().numpy() if len(means) else centres.mean(0)
        """What the view orbits: the median of the Gaussians."""
        self.extent = float(t.extent)
        self._frustums = []
        self._hidden_frustum = None
        train = set(ds.train_indices)
        scale = frustum_scale(centres, self.extent)
        for i in range(len(ds)):
            pose = pose_of(ds.cameras, i)
            image = thumbnail(ds.images[i], self.config.thumbnail_px)
            handle = self.server.scene.add_camera_frustum(
                f"/cameras/{'train' if i in train else 'test'}-{i:04d}",
                fov=pose.fov_y,
                aspect=pose.aspect,
                scale=scale,
                thickness=1.5,
                thickness_units="screen",
                color=(40, 110, 230) if i in train else (240, 140, 30),
                image=image,
                format="jpeg",
                wxyz=pose.wxyz,
                position=pose.position,
            )
            handle.on_click(lambda event, i=i: self.jump_to_view(event.client, i))
            self._frustums.append(handle)
        pose = start_pose(pose_of(ds.cameras, ds.train_indices[0]), self.centre)
        init = self.server.initial_camera
        init.position = pose.position
        init.look_at = tuple(look_at_point(pose, self.centre))
        init.up = tuple(float(v) for v in self.up)
        init.fov = pose.fov_y

    # --- clients and camera ------------------------------------------------------------------------
    def _on_connect(self, client: viser.ClientHandle) -> None:
        state = _Client(client)
        with self._lock:
            self._clients[client.client_id] = state
        client.camera.on_update(lambda cam: self._camera_changed(state))
        try:
            self._camera_changed(state)
        except AssertionError:  # no camera message yet: the first one will call back
            pass

    def _on_disconnect(self, client: viser.ClientHandle) -> None:
        with self._lock:
            self._clients.pop(client.client_id, None)

    def _camera_changed(self, state: _Client) -> None:
        cam = state.client.camera
        pose = ViewPose(
            wxyz=tuple(float(v) for v in cam.wxyz),
            position=tuple(float(v) for v in cam.position),
            fov_y=float(cam.fov),
            aspect=float(cam.aspect),
        )
        with self._lock:
            state.pose = pose
            state.canvas = (int(cam.image_width), int(cam.image_height))
            state.cam_version += 1
            state.cam_time = time.perf_counter()
            hidden = self._hidden_frustum
        if hidden is not None and np.linalg.norm(np.subtract(pose.position, hidden.position)) > 0.02 * self.extent:
            self._hidden_frustum = None  # moved away from the view it jumped to: show its frustum again
            hidden.visible = self.show_cameras.value
        self._wake.set()

    def jump_to_view(self, client: viser.ClientHandle | None, index: int) -> None:
        """Move ``client``'s camera (every client when None) to dataset view ``index``."""
        pose = pose_of(self.trainer.dataset.cameras, index)
        clients = [client] if client is not None else [s.client for s in list(self._clients.values())]
        previous, self._hidden_frustum = self._hidden_frustum, self._frustums[index]
        if previous is not None and previous is not self._hidden_frustum:
            previous.visible = self.show_cameras.value
        self._hidden_frustum.visible = False  # its thumbnail would cover the view
        for cl in clients:
            with cl.atomic():
                cl.camera.up_direction = tuple(float(v) for v in self.up)
                cl.camera.position = pose.position
                cl.camera.look_at = tuple(look_at_point(pose, self.centre))
                cl.camera.fov = pose.fov_y

    def _set_frustums_visible(self, visible: bool) -> None:
        for h in self._frustums:
            h.visible = visible and h is not self._hidden_frustum

    # --- weather -----------------------------------------------------------------------------------

    # --- training ----------------------------------------------------------------------------------

    # --- the render thread -------------------------------------------------------------------------

    # --- exports (run on the render thread) --------------------------------------------------------

    # --- lifetime ----------------------------------------------------------------------------------

    def serve_forever(self) -> None:
        """Keep serving until Ctrl+C."""
        try:
            while not self._stop.is_set():
                time.sleep(0.5)
        except KeyboardInterrupt:
            pass
        finally:
            self.close()

    def close(self) -> None:
        self._stop.set()
        self._wake.set()
        if self.control is not None:
            self.control.finished()
            if self.control in self.trainer.step_hooks:
                self.trainer.step_hooks.remove(self.control)
        self._thread.join(timeout=10.0)
        self.server.stop()


def frustum_scale(centres: np.ndarray, extent: float) -> float:
    """Frustum size: small against both the scene and the spacing of the cameras."""
    if len(centres) < 2:
        return 0.03 * extent
    d = np.linalg.norm(centres[:, None] - centres[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    return float(min(0.03 * extent, 0.3 * np.median(d.min(axis=1))))


def start_live_viewer(trainer, console=None) -> Viewer:
    """The viewer of ``metegs-train --viewer``: bound to the run's ``viewer_host``/``viewer_port``, URL printed."""
    c = trainer.config
    viewer = Viewer(
        trainer,
        ViewerConfig(host=getattr(c, "viewer_host", "127.0.0.1"), port=getattr(c, "viewer_port", 7007)),
        live=True,
        console=console,
    )
    announce(viewer, console)
    return viewer


def announce(viewer: Viewer, console=None) -> None:
    """Print where the viewer listens (and a warning when it listens beyond this machine)."""
    from rich.console import Console

    console = console or Console(stderr=True)
    console.print(f"[bold]viewer[/]: {viewer.url}  (bound to {viewer.config.host}:{viewer.port})", highlight=False)
    if viewer.config.host not in ("127.0.0.1", "localhost", "::1"):
        console.print(
            f"[yellow]warning:[/] the viewer listens on {viewer.config.host}: anyone who can reach this machine can open it"
        )
