"""The viewer's parts without a browser or a trained run: cameras, weather mapping, met timeline, the training hook,
video writing and the command-line flags."""

from __future__ import annotations

import math
import threading
import time
from datetime import timedelta

import numpy as np
import pytest
import torch

from metegs.cameras import Cameras
from metegs.gaussians.model import GaussianModel
from metegs.viewer.camera import ViewPose, interpolate_poses, orbit_order, pose_of, render_height, start_pose
from metegs.viewer.export import write_video
from metegs.viewer.training import TrainingControl
from metegs.viewer.weather import (
    CLEAR_VISIBILITY_M,
    MetTimeline,
    ViewerWeather,
    WeatherValues,
    blend_values,
    reference_image,
    sweep_rates,
)
from metegs.weather.conditions import ConditionsConfig


def orbit_cameras(n: int = 6, width: int = 64, height: int = 48) -> Cameras:
    c2ws = []
    for k in range(n):
        a = 2 * math.pi * k / n
        eye = np.array([6 * math.cos(a), 6 * math.sin(a), 2.0])
        z = -eye / np.linalg.norm(eye)
        x = np.cross(z, [0, 0, 1.0])
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        c2w = np.eye(4)
        c2w[:3, :3] = np.stack([x, y, z], axis=1)
        c2w[:3, 3] = eye
        c2ws.append(c2w)
    return Cameras.create(np.stack(c2ws), 50.0, 50.0, width / 2, height / 2, width, height, exposure_time_s=1 / 250)


def test_pose_round_trip():
    cams = orbit_cameras()
    pose = pose_of(cams, 2)
    again = pose.cameras(48)
    assert torch.allclose(again.camera_to_worlds[0], cams.camera_to_worlds[2], atol=1e-5)
    assert int(again.width[0]) == 64 and float(again.fy[0]) == pytest.approx(50.0, rel=1e-5)
    assert float(again.fx[0]) == pytest.approx(50.0, rel=1e-5)


def test_render_height_caps_and_budgets():
    assert render_height(1280, 720, 640) == 360
    assert render_height(1280, 720, 4096) == 720
    assert render_height(1280, 720, 4096, pixels=1280 * 720 / 4) == 360
    assert render_height(10, 10, 4096, pixels=1) == 16


def test_path_through_views():
    cams = orbit_cameras(6)
    order = orbit_order(cams, np.array([0, 0, 1.0]))
    assert sorted(order) == list(range(6))
    poses = [pose_of(cams, i) for i in order]
    assert interpolate_poses(poses, 0.0).position == pytest.approx(poses[0].position)
    mid = interpolate_poses(poses, 0.5 / 6)  # halfway between the first two
    expected = (np.array(poses[0].position) + np.array(poses[1].position)) / 2
    assert np.allclose(mid.position, expected)
    assert np.linalg.norm(mid.wxyz) == pytest.approx(1.0)
    back = start_pose(poses[0], np.zeros(3))
    assert np.linalg.norm(back.position) > np.linalg.norm(poses[0].position)


def test_weather_values_map_to_theta_with_the_runs_camera():
    cams = orbit_cameras()
    images = [torch.rand(48, 64, 3) for _ in range(len(cams))]
    w = ViewerWeather(["rain-streaks", "fog-analytic"], cams, images, np.array([0, 0, 1.0]), 1.0, ConditionsConfig())
    light = w.set_values(WeatherValues(precip_mm_h=1.0))
    heavy = w.set_values(WeatherValues(precip_mm_h=60.0, visibility_m=400.0))
    assert light.rain.intensity_class == "light" and heavy.rain.intensity_class == "violent"
    assert heavy.rain.expected_count > light.rain.expected_count and heavy.fog.active and not light.fog.active
    long = w.set_values(WeatherValues(precip_mm_h=60.0, exposure_s=1 / 15))
    assert long.rain.streak_length_m > heavy.rain.streak_length_m
    models = w.models_for(pose_of(cams, 0).cameras(24))
    assert [m.name for m in models] == ["rain-streaks", "fog-analytic"]
    assert all(m.active for m in models)
    assert reference_image(images).shape == (48 * len(cams), 64, 3)
    assert "moderate" in WeatherValues(precip_mm_h=5.0).describe()


def test_timeline_of_the_shipped_storm():
    t = MetTimeline(ConditionsConfig())
    assert len(t) >= 24
    hour = t.hour(t.capture_index, 1 / 60)
    assert hour.values.precip_mm_h == pytest.approx(6.8, rel=0.03) and "moderate" in hour.label
    rates = [t.hour(i, 1 / 60).values.precip_mm_h for i in range(len(t))]
    assert max(rates) > 50  # the 72.5 mm/h burst is on the timeline


def test_timeline_between_hours_blends_the_two_hours_weather():
    t = MetTimeline(ConditionsConfig())
    i = t.capture_index
    a, b = t.hour(i, 1 / 60).values, t.hour(i + 1, 1 / 60).values
    time, half = t.at(i + 0.5, 1 / 60)
    assert time == t.times[i] + timedelta(minutes=30)
    assert half.precip_mm_h == pytest.approx((a.precip_mm_h + b.precip_mm_h) / 2)
    assert t.at(i, 1 / 60)[1] == a and t.at(i + 1, 1 / 60)[1] == b
    assert t.at(-5, 1 / 60)[0] == t.times[0] and t.at(len(t) + 5, 1 / 60)[0] == t.times[-1]  # clamped


def test_blended_visibility_is_geometric_and_clear_air_counts_as_the_sliders_top():
    fog, clear = WeatherValues(visibility_m=200.0), WeatherValues(visibility_m=None)
    assert blend_values(fog, WeatherValues(visibility_m=800.0), 0.5).visibility_m == pytest.approx(400.0)
    assert blend_values(fog, clear, 0.5).visibility_m == pytest.approx((200.0 * CLEAR_VISIBILITY_M) ** 0.5)
    assert blend_values(fog, clear, 1.0).visibility_m is None


def test_sweep_rates_are_log_spaced():
    r = sweep_rates(5, 1.0, 100.0)
    assert r[0] == pytest.approx(1.0) and r[-1] == pytest.approx(100.0) and r[2] == pytest.approx(10.0)


class _FakeTrainer:
    def __init__(self):
        self.step = 0
        self.model = GaussianModel.random_in_box(np.zeros(3), np.ones(3), 20, sh_degree=1)

    def run(self, control, steps):
        for _ in range(steps):
            time.sleep(0.002)
            self.step += 1
            control(self, {"loss": 1.0 / self.step, "psnr": float(self.step)})


def test_training_control_pause_step_resume():
    trainer, control = _FakeTrainer(), TrainingControl()
    thread = threading.Thread(target=trainer.run, args=(control, 200), daemon=True)
    control.pause()
    thread.start()
    deadline = time.perf_counter() + 10
    while not control.blocked and time.perf_counter() < deadline:
        time.sleep(0.01)
    assert control.blocked and trainer.step == 1  # paused after the first step
    control.request_snapshot()
    while control.snapshot is None and time.perf_counter() < deadline:
        time.sleep(0.01)
    assert control.snapshot is not None and control.snapshot.step == 1 and len(control.snapshot) == 20
    control.step_once()
    while trainer.step < 2 and time.perf_counter() < deadline:
        time.sleep(0.01)
    time.sleep(0.1)
    assert trainer.step == 2 and control.blocked
    control.resume()
    thread.join(timeout=10)
    assert trainer.step == 200 and len(control.history) == 200 and control.iterations_per_second() > 0


def test_training_control_never_blocks_after_finish():
    trainer, control = _FakeTrainer(), TrainingControl()
    control.pause()
    control.finished()
    trainer.run(control, 3)
    assert trainer.step == 3


def test_video_writer_falls_back(tmp_path, monkeypatch):
    import metegs.video as export

    frames = [np.full((24, 32, 3), 40 * i, np.uint8) for i in range(4)]
    mp4 = write_video(tmp_path / "a.mp4", frames, fps=4)
    assert mp4.is_file() and mp4.stat().st_size > 0
    monkeypatch.setattr(export, "_write_mp4", lambda *a: False)
    gif = write_video(tmp_path / "b.mp4", frames, fps=4)
    assert gif.suffix == ".gif" and gif.stat().st_size > 0
    monkeypatch.setattr(export, "_write_gif", lambda *a: False)
    folder = write_video(tmp_path / "c.mp4", frames, fps=4)
    assert folder.is_dir() and len(list(folder.glob("frame-*.png"))) == 4


def _top_level_boxes(path) -> list[str]:
    """The MP4's top-level box types in file order (``moov`` before ``mdat``: ``+faststart``)."""
    data, boxes, i = path.read_bytes(), [], 0
    while i + 8 <= len(data):
        size, kind = int.from_bytes(data[i : i + 4], "big"), data[i + 4 : i + 8].decode("latin-1")
        if size == 1:
            size = int.from_bytes(data[i + 8 : i + 16], "big")
        boxes.append(kind)
        if size < 8:
            break
        i += size
    return boxes


def test_mp4_is_h264_for_browsers(tmp_path):
    imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg", reason="H.264 export needs imageio-ffmpeg")

    ramp = np.linspace(0, 80, 67)[None, :, None] + np.zeros((49, 67, 3))  # odd sizes: cropped to even
    frames = [(ramp + 25 * i).astype(np.uint8) for i in range(7)]  # each frame brighter than the last
    path = write_video(tmp_path / "sweep.mp4", frames, fps=7)
    assert path == tmp_path / "sweep.mp4"
    reader = imageio_ffmpeg.read_frames(str(path))
    meta = next(reader)
    assert meta["codec"].startswith("h264") and meta["pix_fmt"].startswith("yuv420p"), meta
    assert tuple(meta["size"]) == (66, 48) and meta["fps"] == pytest.approx(7)
    decoded = [np.frombuffer(f, np.uint8).reshape(48, 66, 3) for f in reader]
    assert len(decoded) == 7
    for got, sent in zip(decoded, frames):  # the right frames in order, up to the lossy coding
        assert np.abs(got.astype(float) - sent[:48, :66]).mean() < 3
    boxes = _top_level_boxes(path)
    assert boxes.index("moov") < boxes.index("mdat"), boxes
    assert not list(tmp_path.glob(".sweep.mp4.*")), "a temporary file was left"


def test_mp4_without_imageio_ffmpeg_falls_back_to_mp4v_and_says_so(tmp_path, monkeypatch):
    import sys

    import metegs.video as export

    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)  # `import imageio_ffmpeg` raises ImportError
    monkeypatch.setattr(export, "_warned_mp4v", False)
    frames = [np.full((24, 32, 3), 40 * i, np.uint8) for i in range(4)]
    if not export._write_mp4v(tmp_path / "probe.mp4", frames, 4):
        pytest.skip("this OpenCV build cannot write mp4v")
    with pytest.warns(export.BrowserVideoWarning, match=r"browsers.*pip install imageio-ffmpeg"):
        mp4 = write_video(tmp_path / "a.mp4", frames, fps=4)
    assert mp4 == tmp_path / "a.mp4" and mp4.stat().st_size > 0
    assert mp4.read_bytes()[4:8] == b"ftyp"
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error", export.BrowserVideoWarning)  # said once, not on every export
        assert write_video(tmp_path / "b.mp4", frames, fps=4).stat().st_size > 0


def test_command_line_flags():
    import tyro

    from metegs.cli.train import parse_args
    from metegs.cli.view import ViewArgs

    config = parse_args(["3dgs", "--viewer", "--viewer-port", "8123"])
    assert config.viewer and config.viewer_port == 8123 and config.viewer_host == "127.0.0.1"
    assert not parse_args(["3dgs"]).viewer
    args = tyro.cli(ViewArgs, args=["some/run", "--host", "0.0.0.0", "--port", "9000"])
    assert args.host == "0.0.0.0" and args.port == 9000
    assert tyro.cli(ViewArgs, args=["some/run"]).host == "127.0.0.1"


def test_live_viewer_sets_a_short_openmp_spin_before_torch_loads(monkeypatch):
    import subprocess
    import sys

    from metegs.cli.train import LIVE_VIEWER_ENV, thread_env

    monkeypatch.delenv("GOMP_SPINCOUNT", raising=False)
    assert thread_env(["3dgs", "--viewer"]) == LIVE_VIEWER_ENV
    assert thread_env(["3dgs"]) == {}
    monkeypatch.setenv("GOMP_SPINCOUNT", "INFINITE")  # the user's own setting wins
    assert "GOMP_SPINCOUNT" not in thread_env(["3dgs", "--viewer"])
    # libgomp reads the variable once, when torch loads: metegs-train's module must not load torch itself
    probe = "import sys, metegs.cli.train; print('torch' in sys.modules)"
    assert (
        subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True).stdout.strip()
        == "False"
    )


def test_pose_dataclass_is_hashable():
    p = ViewPose((1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 1.0, 1.5)
    assert hash(p) == hash(ViewPose((1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 1.0, 1.5))
