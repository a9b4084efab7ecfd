"""The browser viewer: a viser server whose scene view is rendered by the run's own rasteriser.

One background thread renders for every connected browser: a quick low-resolution frame while the camera moves, the
full frame once it stops (a full frame whose camera moved meanwhile is dropped, never shown). GUI callbacks only
change state and wake that thread. During live training it takes copies of the scene between steps (through
`TrainingControl`, a ``Trainer.step_hooks`` entry), renders on one thread and sleeps so that it uses at most
``render_share`` of the wall time.
"""

from __future__ import annotations

import copy
import math
import threading
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from datetime import datetime
from pathlib import Path

import numpy as np
import torch
import viser

from metegs.errors import MetegsError
from metegs.meteo import intensity_class
from metegs.render.select import make_rasterizer
from metegs.video import caption, to_uint8
from metegs.viewer.camera import (
    ViewPose,
    interpolate_poses,
    look_at_point,
    orbit_order,
    pose_of,
    render_height,
    start_pose,
    thumbnail,
)
from metegs.viewer.export import save_png, save_scene_ply, write_video
from metegs.viewer.render import Snapshot, render_frame
from metegs.viewer.training import TrainingControl
from metegs.viewer.weather import (
    CLEAR_VISIBILITY_M,
    STORM_SWEEP_MM_H,
    WeatherValues,
    format_exposure,
    run_weather,
    sweep_rates,
)

MOVING_S = 0.25
"""The camera counts as moving until this long after its last change."""
RAIN_OFF_LOG = -1.5
"""Bottom of the rain slider (log10 mm/h): no rain."""
RAIN_MAX_LOG = math.log10(200.0)
VIS_MIN_LOG, VIS_MAX_LOG = math.log10(50.0), math.log10(CLEAR_VISIBILITY_M)
EXPOSURE_MIN_LOG, EXPOSURE_MAX_LOG = math.log10(1 / 4000), math.log10(1 / 4)


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


@dataclass
class _Client:
    client: viser.ClientHandle
    pose: ViewPose | None = None
    canvas: tuple[int, int] = (0, 0)
    cam_version: int = 0
    cam_time: float = 0.0
    shown_key: tuple | None = None
    shown_full: bool = False
    shown_time: float = 0.0
    shown_image: np.ndarray | None = None
    frames: int = 0


@dataclass
class _Job:
    run: Callable[[], None]
    name: str = "job"


@dataclass
class FrameStats:
    """The last frame sent (for the GUI and the tests)."""

    width: int = 0
    height: int = 0
    seconds: float = 0.0
    full: bool = False
    mode: str = "clean"
    count: int = 0
    dropped: int = 0
    unchanged: int = 0
    history: list = field(default_factory=list)


class Viewer:
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

    def _build_gui(self) -> None:
        gui = self.server.gui
        gui.configure_theme(control_width="large", dark_mode=False, show_logo=False)
        c = self.trainer.config
        gui.add_markdown(f"**metegs** · `{c.method}` · {self.trainer.scene.parser} scene · backend `{c.backend}`")
        self.status_md = gui.add_markdown("waiting for the browser's camera ...")
        tabs = gui.add_tab_group()
        with tabs.add_tab("Weather", viser.Icon.CLOUD_RAIN):
            self._build_weather_gui()
        if self.live:
            with tabs.add_tab("Training", viser.Icon.PLAYER_PLAY):
                self._build_training_gui()
        with tabs.add_tab("Export", viser.Icon.DOWNLOAD):
            self._build_export_gui()
        with tabs.add_tab("View", viser.Icon.CAMERA):
            self.show_cameras = gui.add_checkbox(
                "Training cameras", True, hint="Frustums of the views; click one to jump"
            )
            self.show_cameras.on_update(lambda _: self._set_frustums_visible(self.show_cameras.value))
            self.max_side = gui.add_slider("Max resolution (px)", 128, 2048, 64, int(self.config.max_side))
            self.max_side.on_update(lambda _: self._changed())
            view_ids = [str(i) for i in range(len(self.trainer.dataset))]
            self.view_pick = gui.add_dropdown("Jump to view", view_ids, initial_value=view_ids[0])
            self.view_pick.on_update(lambda e: e.client and self.jump_to_view(e.client, int(self.view_pick.value)))

    def _build_weather_gui(self) -> None:
        gui = self.server.gui
        v = self.run_values
        self.weather_on = gui.add_checkbox("Weather render", self.mode == "weather", hint="Off: the clean scene")
        self.weather_on.on_update(lambda _: self._set_mode("weather" if self.weather_on.value else "clean"))
        self.rain = gui.add_slider(
            "Rain (log mm/h)",
            RAIN_OFF_LOG,
            round(RAIN_MAX_LOG, 2),
            0.01,
            _rain_to_slider(v.precip_mm_h),
            marks=((RAIN_OFF_LOG, "off"), (-1.0, "0.1"), (0.4, "2.5"), (1.0, "10"), (1.7, "50"), (2.3, "200")),
            hint="Precipitation rate, log10 mm/h; WMO classes: light < 2.5 ≤ moderate < 10 ≤ heavy < 50 ≤ violent",
        )
        self.rain_md = gui.add_markdown("")
        self.visibility = gui.add_slider(
            "Visibility (log m)",
            round(VIS_MIN_LOG, 2),
            round(VIS_MAX_LOG, 2),
            0.01,
            _vis_to_slider(v.visibility_m),
            marks=((2.0, "100"), (3.0, "1k"), (3.7, "5k"), (round(VIS_MAX_LOG, 2), "clear")),
            hint="Meteorological visibility, log10 m; the top is clear air (no fog)",
        )
        self.wind = gui.add_slider("Wind (m/s)", 0.0, 30.0, 0.5, min(30.0, round(v.wind_speed_m_s * 2) / 2))
        self.wind_dir = gui.add_slider(
            "Wind from (°)",
            0,
            360,
            5,
            int(round((v.wind_dir_deg or 0.0) / 5) * 5) % 360,
            hint="Direction the wind blows from, clockwise from north (north: the training views' mean direction)",
        )
        self.exposure = gui.add_slider(
            "Exposure (log s)",
            round(EXPOSURE_MIN_LOG, 2),
            round(EXPOSURE_MAX_LOG, 2),
            0.01,
            round(math.log10(min(max(v.exposure_s, 1 / 4000), 1 / 4)), 2),
            marks=((-3.0, "1/1000"), (-2.4, "1/250"), (-1.78, "1/60"), (-1.18, "1/15")),
            hint="Exposure time, log10 s: longer exposures draw longer, fainter streaks",
        )
        self.theta_md = gui.add_markdown("")
        for handle in (self.rain, self.visibility, self.wind, self.wind_dir, self.exposure):
            handle.on_update(lambda _: self._weather_changed(switch_on=True))
        self.hour = None
        if self.timeline is not None and len(self.timeline) > 0:
            n = len(self.timeline)
            self.hour = gui.add_slider(
                "Met record hour",
                0,
                max(n - 1, 1),
                1,
                self.timeline.capture_index,
                hint=f"Hours of {self.timeline.source}: jump to the weather of that hour",
                disabled=n < 2,
            )
            self.hour_md = gui.add_markdown("")
            self.hour.on_update(lambda _: self._jump_to_hour(int(self.hour.value)))
            self._describe_hour(self.timeline.capture_index)
        reset = gui.add_button("Run's weather", hint="Back to the weather the run was trained with")
        reset.on_click(lambda _: self._set_values(self.run_values, switch_on=True))
        if self.weather_note:
            gui.add_markdown(f"_{self.weather_note}_")
        self._describe_weather()

    def _build_training_gui(self) -> None:
        gui = self.server.gui
        self.pause_btn = gui.add_button("Pause", icon=viser.Icon.PLAYER_PAUSE)
        self.pause_btn.on_click(lambda _: self._toggle_pause())
        self.step_btn = gui.add_button("Step", icon=viser.Icon.PLAYER_TRACK_NEXT, disabled=True)
        self.step_btn.on_click(lambda _: self.control.step_once())
        self.train_md = gui.add_markdown("training starts ...")
        scales = {"x": {"time": False, "auto": True}, "y": {"auto": True}}
        empty = (np.zeros(1), np.zeros(1))
        self.loss_plot = gui.add_uplot(
            empty,
            ({"label": "step"}, {"label": "loss", "stroke": "#d9480f", "width": 2}),
            title="loss",
            scales=scales,
            aspect=2.0,
        )
        self.psnr_plot = gui.add_uplot(
            (np.zeros(1), np.zeros(1), np.zeros(1)),
            (
                {"label": "step"},
                {"label": "train PSNR", "stroke": "#1c7ed6", "width": 2},
                {"label": "test PSNR", "stroke": "#2b8a3e", "width": 2, "points": {"show": True, "size": 6}},
            ),
            title="PSNR (dB)",
            scales=scales,
            aspect=2.0,
        )
        self._panel_time = 0.0

    def _build_export_gui(self) -> None:
        gui = self.server.gui
        png = gui.add_button("Save view (PNG)", icon=viser.Icon.PHOTO)
        png.on_click(lambda e: self._submit(lambda: self.export_png(e.client), "png"))
        ply = gui.add_button("Save clean scene (PLY)", icon=viser.Icon.BOX)
        ply.on_click(lambda e: self._submit(lambda: self.export_ply(e.client), "ply"))
        with gui.add_folder("Weather sweep video"):
            self.sweep_low = gui.add_number("From (mm/h)", STORM_SWEEP_MM_H[0], min=0.05, max=500.0, step=0.05)
            self.sweep_high = gui.add_number("To (mm/h)", STORM_SWEEP_MM_H[1], min=0.05, max=500.0, step=0.05)
            self.sweep_frames = gui.add_slider("Frames", 4, 240, 1, 48)
            self.sweep_fps = gui.add_slider("Frames per second", 1, 60, 1, 12)
            self.sweep_height = gui.add_slider("Height (px)", 64, 1080, 8, 360)
            self.sweep_path = gui.add_dropdown(
                "Camera path", ("training views", "current view"), initial_value="training views"
            )
            self.sweep_format = gui.add_dropdown("Format", ("mp4", "gif"), initial_value="mp4")
            go = gui.add_button("Render sweep", icon=viser.Icon.MOVIE)
            go.on_click(lambda e: self._submit(lambda: self.export_sweep(e.client), "sweep"))
            self.sweep_progress = gui.add_progress_bar(0.0, visible=False)
        self.export_md = gui.add_markdown(f"exports go to `{self.output_dir}`")

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
    def current_values(self) -> WeatherValues:
        """The weather the sliders show."""
        vis = 10 ** float(self.visibility.value)
        return WeatherValues(
            precip_mm_h=_slider_to_rain(float(self.rain.value)),
            visibility_m=None if float(self.visibility.value) >= self.visibility.max - 1e-6 else vis,
            wind_speed_m_s=float(self.wind.value),
            wind_dir_deg=float(self.wind_dir.value) % 360.0,
            exposure_s=10 ** float(self.exposure.value),
        )

    def _weather_changed(self, switch_on: bool = False) -> None:
        if self._suspend:
            return
        values = self.current_values()
        try:
            with self._lock:
                self.weather.set_values(values)
                self._weather_version += 1
        except MetegsError as exc:
            self.theta_md.content = f"**cannot map this weather:** {exc}"
            return
        self._describe_weather()
        if switch_on and self.mode != "weather":
            self.weather_on.value = True  # calls _set_mode
        self._wake.set()

    def set_weather(self, values: WeatherValues, switch_on: bool = True) -> None:
        """Move the sliders to ``values`` (and re-render once)."""
        self._set_values(values, switch_on)

    def _set_values(self, values: WeatherValues, switch_on: bool) -> None:
        self._suspend = True
        try:
            self.rain.value = _rain_to_slider(values.precip_mm_h)
            self.visibility.value = _vis_to_slider(values.visibility_m)
            self.wind.value = min(30.0, round(values.wind_speed_m_s * 2) / 2)
            if values.wind_dir_deg is not None:
                self.wind_dir.value = int(round(values.wind_dir_deg / 5) * 5) % 360
            self.exposure.value = round(math.log10(min(max(values.exposure_s, 1 / 4000), 1 / 4)), 2)
        finally:
            self._suspend = False
        self._weather_changed(switch_on=switch_on)

    def _jump_to_hour(self, index: int) -> None:
        if self.timeline is None:
            return
        try:
            hour = self.timeline.hour(index, 10 ** float(self.exposure.value))
        except MetegsError as exc:
            self.hour_md.content = f"**{exc}**"
            return
        values = hour.values
        if values.visibility_m is None:  # records such as PRSA have none: keep the slider's
            values = replace(values, visibility_m=self.current_values().visibility_m)
        self._describe_hour(index)
        self._set_values(values, switch_on=True)

    def _describe_hour(self, index: int) -> None:
        try:
            self.hour_md.content = self.timeline.hour(index, 10 ** float(self.exposure.value)).label
        except MetegsError as exc:
            self.hour_md.content = f"**{exc}**"

    def _describe_weather(self) -> None:
        from metegs.weather.conditions import describe

        values = self.current_values()
        p = values.precip_mm_h
        cls = "no rain" if p <= 0 else f"**{intensity_class(p)}** (WMO)"
        self.rain_md.content = f"{p:.3g} mm/h · {cls}" if p > 0 else "no rain"
        vis = "clear" if values.visibility_m is None else f"{values.visibility_m:,.0f} m"
        self.theta_md.content = (
            f"visibility {vis} · wind {values.wind_speed_m_s:.1f} m/s from {values.wind_dir_deg:.0f}° · "
            f"exposure {format_exposure(values.exposure_s)}  \nθ: {describe(self.weather.theta)}"
        )
        caps = [getattr(c, "max_count", None) for c in self.weather.configs]
        caps = [c for c in caps if c is not None]
        if caps and self.weather.theta.rain.active and self.weather.theta.rain.count > min(caps):
            self.theta_md.content += f" (drawn: {min(caps):,} per view, opacity raised to keep the coverage)"

    def _set_mode(self, mode: str) -> None:
        with self._lock:
            self.mode = mode
            self._weather_version += 1
        self._wake.set()

    def _changed(self) -> None:
        with self._lock:
            self._weather_version += 1
        self._wake.set()

    # --- training ----------------------------------------------------------------------------------
    def _toggle_pause(self) -> None:
        if self.control is None:
            return
        if self.control.paused:
            self.control.resume()
            self.pause_btn.label, self.pause_btn.icon = "Pause", viser.Icon.PLAYER_PAUSE
            self.step_btn.disabled = True
        else:
            self.control.pause()
            self.pause_btn.label, self.pause_btn.icon = "Resume", viser.Icon.PLAYER_PLAY
            self.step_btn.disabled = False
        self._wake.set()

    def training_finished(self) -> None:
        """Training is over (call on the training thread): take the final scene, stop throttling."""
        if self.control is not None:
            self.control.finished()
        with self._lock:
            self.snapshot = Snapshot.of(self.trainer.model, self.trainer.step)
        if self.live:
            self.pause_btn.disabled = True
            self.step_btn.disabled = True
            self._update_training_panel(force=True)
        self._wake.set()

    def _training_active(self) -> bool:
        return self.control is not None and self.control.running and not self.control.paused

    def _update_training_panel(self, force: bool = False) -> None:
        if not self.live:
            return
        now = time.perf_counter()
        if not force and now - self._panel_time < self.config.panel_refresh_s:
            return
        self._panel_time = now
        ctl, t = self.control, self.trainer
        hist = ctl.history
        state = "done" if ctl._closed else ("paused" if ctl.paused else "running")
        last = hist[-1] if hist else None
        text = f"**{state}** · step {ctl.step} / {t.config.max_steps} · {ctl.iterations_per_second():.2f} it/s · "
        text += f"{ctl.num_gaussians or len(self.snapshot):,} Gaussians"
        if last is not None:
            text += f"  \nloss {last.loss:.4f} · train PSNR {last.psnr:.2f} dB"
        evals = [h for h in list(t.history) if "psnr" in h]
        if evals:
            text += f" · test PSNR {evals[-1]['psnr']:.2f} dB (step {evals[-1]['step']})"
        self.train_md.content = text
        if len(hist) >= 2:
            pick = np.unique(np.linspace(0, len(hist) - 1, min(len(hist), 400)).round().astype(int))
            steps = np.array([hist[i].step for i in pick], dtype=np.float64)
            loss = _ema(np.array([h.loss for h in hist]))[pick]
            psnr = _ema(np.array([h.psnr for h in hist]))[pick]
            test = np.full_like(steps, np.nan)
            for e in evals:
                test[int(np.argmin(np.abs(steps - e["step"])))] = e["psnr"]
            self.loss_plot.data = (steps, loss)
            self.psnr_plot.data = (steps, psnr, test)

    # --- the render thread -------------------------------------------------------------------------
    def _submit(self, run: Callable[[], None], name: str) -> None:
        with self._lock:
            self._jobs.append(_Job(run, name))
        self._wake.set()

    def _loop(self) -> None:
        torch.set_flush_denormal(True)  # per thread: tiny transmittances otherwise slow CPU arithmetic
        while not self._stop.is_set():
            try:
                self._update_training_panel()
                self._refresh_snapshot()
                job = None
                with self._lock:
                    if self._jobs:
                        job = self._jobs.pop(0)
                if job is not None:
                    self._use_threads()
                    job.run()
                    continue
                task = self._next_task()
                if task is None:
                    self._wake.wait(0.1)
                    self._wake.clear()
                    continue
                seconds = self._render_task(*task)
                if self._training_active() and seconds > 0:
                    self._stop.wait(seconds * (1.0 / max(self.config.render_share, 1e-3) - 1.0))
            except Exception as exc:  # keep serving; show what went wrong
                self.last_error = "".join(traceback.format_exception(exc))
                if self.console is not None:
                    self.console.print(f"[yellow]viewer:[/] {exc}")
                try:
                    self.status_md.content = f"**viewer error:** {exc}"
                except Exception:
                    pass
                self._stop.wait(0.5)

    def _use_threads(self) -> None:
        """One thread while training runs (training keeps the rest), all of them otherwise."""
        n = 1 if self._training_active() else self._threads
        if torch.get_num_threads() != n:
            torch.set_num_threads(n)

    def _refresh_snapshot(self) -> None:
        ctl = self.control
        if ctl is None or not ctl.running:
            return
        snap = ctl.snapshot
        if snap is not None and snap.id > self.snapshot.id:
            with self._lock:
                self.snapshot = snap
        now = time.perf_counter()
        due = now - self._snapshot_time >= self.config.live_refresh_s
        if due and not ctl.snapshot_pending and ctl.step != self.snapshot.step:  # nothing new while paused
            self._snapshot_time = now
            ctl.request_snapshot()

    def _next_task(self):
        now = time.perf_counter()
        with self._lock:
            for st in self._clients.values():
                if st.pose is None or st.canvas[0] <= 0:
                    continue
                key = (st.cam_version, self._weather_version, self.snapshot.id)
                moving = now - st.cam_time < MOVING_S
                if st.shown_key == key and (st.shown_full or moving):
                    continue
                if (
                    st.shown_key is not None
                    and st.shown_key[:2] == key[:2]
                    and st.shown_full
                    and now - st.shown_time < self.config.live_refresh_s
                ):
                    continue  # only the Gaussians changed: refresh at the live rate
                return st, key, moving, st.pose, st.canvas, self.mode
        return None

    def _render_task(self, st: _Client, key: tuple, moving: bool, pose: ViewPose, canvas: tuple[int, int], mode: str):
        max_side = int(self.max_side.value)
        full_h = render_height(canvas[0], canvas[1], max_side)
        height = full_h
        if moving:
            budget = self.config.preview_seconds / self._cost_per_px[mode]
            height = min(full_h, render_height(canvas[0], canvas[1], max_side, budget))
        full = height >= full_h
        self._use_threads()
        t0 = time.perf_counter()
        image = self.render(pose, height, mode)
        seconds = time.perf_counter() - t0
        pixels = image.shape[0] * image.shape[1]
        self._cost_per_px[mode] = 0.7 * self._cost_per_px[mode] + 0.3 * seconds / max(pixels, 1)
        with self._lock:
            superseded = full and st.cam_version != key[0]
            if superseded:  # the camera moved while this frame was drawn: show the next one instead
                self.stats.dropped += 1
                return seconds
            same = (
                st.shown_full
                and full
                and st.shown_key is not None
                and st.shown_key[:2] == key[:2]
                and st.shown_image is not None
                and st.shown_image.shape == image.shape
                and np.abs(st.shown_image.astype(np.int16) - image).mean() < self.config.same_frame_level
            )
            st.shown_key, st.shown_full, st.shown_time = key, full, time.perf_counter()
            if same:  # only the Gaussians changed, and not visibly: keep the frame the browser has
                self.stats.unchanged += 1
                return time.perf_counter() - t0
            st.shown_image = image
            st.frames += 1
            if self._clients.get(st.client.client_id) is not st:  # the browser left meanwhile
                return time.perf_counter() - t0
        st.client.scene.set_background_image(image, format="jpeg", jpeg_quality=self.config.jpeg_quality)
        s = self.stats
        s.width, s.height, s.seconds, s.full, s.mode = image.shape[1], image.shape[0], seconds, full, mode
        s.count += 1
        s.history = (s.history + [(time.time(), s.width, s.height, seconds, full, mode)])[-50:]
        step = f" · step {self.snapshot.step}" if self.live else ""
        self.status_md.content = (
            f"{mode} · {s.width}×{s.height} px ({'full' if full else 'preview'}) · {1000 * seconds:.0f} ms"
            f" · {len(self.snapshot):,} Gaussians{step}"
        )
        return time.perf_counter() - t0  # what the throttle counts: render, encoding and sending

    def render(self, pose: ViewPose, height: int, mode: str | None = None) -> np.ndarray:
        """A frame of ``pose`` ``height`` px tall -> uint8 [H, W, 3] (the current weather unless ``mode`` is "clean")."""
        mode = mode or self.mode
        camera = pose.cameras(height, self.device)
        with self._lock:
            snapshot, weather = self.snapshot, (self.weather if mode == "weather" else None)
        return to_uint8(render_frame(self.rasterizer, snapshot, camera, self.background, weather))

    # --- exports (run on the render thread) --------------------------------------------------------
    def _client_pose(self, client: viser.ClientHandle | None) -> tuple[ViewPose, tuple[int, int]]:
        st = self._clients.get(client.client_id) if client is not None else None
        if st is None or st.pose is None:
            st = next((s for s in self._clients.values() if s.pose is not None), None)
        if st is None:
            ds = self.trainer.dataset
            i = ds.train_indices[0]
            return pose_of(ds.cameras, i), (int(ds.cameras.width[i]), int(ds.cameras.height[i]))
        return st.pose, st.canvas

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

    # --- lifetime ----------------------------------------------------------------------------------
    def wait_for_frames(self, count: int = 1, timeout: float = 60.0) -> bool:
        """Block until ``count`` frames have been sent in total (tests, scripts)."""
        deadline = time.perf_counter() + timeout
        while self.stats.count < count and time.perf_counter() < deadline:
            time.sleep(0.05)
        return self.stats.count >= count

    def settled(self) -> bool:
        """Every browser shows a full frame of its current camera, weather and Gaussians."""
        now = time.perf_counter()
        with self._lock:
            states = [st for st in self._clients.values() if st.pose is not None]
            return bool(states) and all(
                st.shown_key == (st.cam_version, self._weather_version, self.snapshot.id)
                and st.shown_full
                and now - st.cam_time >= MOVING_S
                for st in states
            )

    def wait_settled(self, timeout: float = 60.0) -> bool:
        """Block until `settled()` (tests, scripts)."""
        deadline = time.perf_counter() + timeout
        while not self.settled() and time.perf_counter() < deadline:
            time.sleep(0.05)
        return self.settled()

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


def _rain_to_slider(mm_h: float) -> float:
    if mm_h <= 10**RAIN_OFF_LOG:
        return RAIN_OFF_LOG
    return round(min(max(math.log10(mm_h), RAIN_OFF_LOG + 0.01), RAIN_MAX_LOG), 2)


def _slider_to_rain(value: float) -> float:
    return 0.0 if value <= RAIN_OFF_LOG + 1e-6 else 10**value


def _vis_to_slider(visibility_m: float | None) -> float:
    if visibility_m is None:
        return round(VIS_MAX_LOG, 2)
    return round(min(max(math.log10(visibility_m), VIS_MIN_LOG), VIS_MAX_LOG), 2)


def _ema(x: np.ndarray, alpha: float = 0.1) -> np.ndarray:
    out = np.empty_like(x, dtype=np.float64)
    acc = None
    for i, v in enumerate(x):
        acc = v if acc is None or not np.isfinite(acc) else (1 - alpha) * acc + alpha * v
        out[i] = acc
    return out


def _stamp() -> str:
    return datetime.now().strftime("%Y%m%d-%H%M%S-%f")[:-3]


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
