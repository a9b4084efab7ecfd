"""The viewer's frames: one background thread renders for every connected browser (a quick low-resolution frame while
the camera moves, the full frame once it stops; a full frame whose camera moved meanwhile is dropped, never shown)
and, during live training, takes copies of the scene between steps and keeps to its share of the wall time."""

from __future__ import annotations

import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch
import viser

from metegs.video import to_uint8
from metegs.viewer.camera import (
    ViewPose,
    pose_of,
    render_height,
)
from metegs.viewer.render import render_frame

MOVING_S = 0.25
"""The camera counts as moving until this long after its last change."""


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


class ViewerFrames:
    """Render scheduling and threads of `metegs.viewer.server.Viewer`."""

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

    def _client_pose(self, client: viser.ClientHandle | None) -> tuple[ViewPose, tuple[int, int]]:
        st = self._clients.get(client.client_id) if client is not None else None
        if st is None or st.pose is None:
            st = next((s for s in self._clients.values() if s.pose is not None), None)
        if st is None:
            ds = self.trainer.dataset
            i = ds.train_indices[0]
            return pose_of(ds.cameras, i), (int(ds.cameras.width[i]), int(ds.cameras.height[i]))
        return st.pose, st.canvas

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
