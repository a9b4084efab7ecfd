"""The viewer's panels: the weather sliders and the met record's hours, the training panel (pause, step, curves) and
the export buttons; their callbacks only change state and wake the render thread (`ViewerFrames`)."""

from __future__ import annotations

import math
import time
from dataclasses import replace

import numpy as np
import viser

from metegs.errors import MetegsError
from metegs.meteo import intensity_class
from metegs.registry import registry
from metegs.viewer.render import Snapshot
from metegs.viewer.weather import (
    CLEAR_VISIBILITY_M,
    STORM_SWEEP_MM_H,
    WeatherValues,
    format_exposure,
)

RAIN_OFF_LOG = -1.5
"""Bottom of the rain slider (log10 mm/h): no rain."""
RAIN_MAX_LOG = math.log10(200.0)
VIS_MIN_LOG, VIS_MAX_LOG = math.log10(50.0), math.log10(CLEAR_VISIBILITY_M)
EXPOSURE_MIN_LOG, EXPOSURE_MAX_LOG = math.log10(1 / 4000), math.log10(1 / 4)


class ViewerPanels:
    """The GUI of `metegs.viewer.server.Viewer`."""

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
            "Precipitation (log mm/h)",
            RAIN_OFF_LOG,
            round(RAIN_MAX_LOG, 2),
            0.01,
            _rain_to_slider(v.precip_mm_h),
            marks=((RAIN_OFF_LOG, "off"), (-1.0, "0.1"), (0.4, "2.5"), (1.0, "10"), (1.7, "50"), (2.3, "200")),
            hint="Precipitation rate (water equivalent for snow), log10 mm/h; WMO rain classes: light < 2.5 ≤ "
            "moderate < 10 ≤ heavy < 50 ≤ violent",
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
        with gui.add_folder("Weather models", expand_by_default=False):
            self.model_boxes = {
                e.name: gui.add_checkbox(
                    e.name + ("" if e.source == "metegs" else f" [{e.source}]"),
                    e.name in self.weather.names,
                    hint=e.description or e.name,
                )
                for e in registry("weather").entries()
            }
        for box in self.model_boxes.values():
            box.on_update(lambda _: self._models_changed())
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

    def _models_changed(self) -> None:
        """Show the weather models whose boxes are ticked (in registry order)."""
        with self._lock:
            self.weather.set_models([name for name, box in self.model_boxes.items() if box.value])
            self._weather_version += 1
        self._describe_weather()
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
        self.rain_md.content = f"{p:.3g} mm/h · **{intensity_class(p)}** (WMO)" if p > 0 else "none"
        vis = "clear" if values.visibility_m is None else f"{values.visibility_m:,.0f} m"
        self.theta_md.content = (
            f"visibility {vis} · wind {values.wind_speed_m_s:.1f} m/s from {values.wind_dir_deg:.0f}° · "
            f"exposure {format_exposure(values.exposure_s)}  \nθ: {describe(self.weather.theta)}"
        )
        self.theta_md.content += "  \nmodels: " + (", ".join(f"`{n}`" for n in self.weather.names) or "none")

    def _set_mode(self, mode: str) -> None:
        with self._lock:
            self.mode = mode
            self._weather_version += 1
        self._wake.set()

    def _changed(self) -> None:
        with self._lock:
            self._weather_version += 1
        self._wake.set()

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
