"""The viewer on a trained tiny run: live pause / step, exports, and the browser (headless Chromium via Selenium)
moving the precipitation slider and playing the exported MP4.

Screenshots go to ``$METEGS_TEST_ARTIFACTS`` (else the test's tmp folder); their paths are printed.
"""

from __future__ import annotations

import importlib.util
import os
import shutil
import time
from pathlib import Path

import numpy as np
import pytest

from metegs.gaussians.ply import load_ply


def test_live_training_runs_torch_ops_serially_and_the_kernels_on_the_runs_threads(live_run):
    r = live_run
    assert r["threads_after"] == r["threads_before"]
    if r["backend"] == "cpu" and r["threads_before"] > 1:
        assert r["threads_during"] == [1, r["threads_before"]]


def test_live_training_pauses_and_steps(live_run):
    r = live_run
    assert r["viewer_error"] is None
    assert r["reached_step_5"] and r["blocked"]
    s0, s1 = r["paused_steps"]
    assert s0 == s1, "training went on while paused"
    assert r["stepped"] and r["after_step"] == r["expected_after_step"], "Step must run exactly one step"
    assert r["snapshot_while_paused"]
    assert r["final_step"] == 40 and r["history_len"] == 40
    assert r["panel"].startswith("**done**") and "Gaussians" in r["panel"]


@pytest.fixture(scope="module")
def viewer(live_run, tmp_path_factory):
    """`metegs-view RUN_DIR` (not blocking) on the trained run, any free port, exports into a tmp folder."""
    from metegs.cli.view import ViewArgs, main

    out = tmp_path_factory.mktemp("exports")
    v = main(ViewArgs(Path(live_run["run_dir"]), port=0, max_side=640, output_dir=out), block=False)
    yield v
    v.close()


def test_view_binds_to_localhost(viewer):
    assert viewer.config.host == "127.0.0.1"
    assert viewer.url == f"http://127.0.0.1:{viewer.port}" and viewer.port > 0


def test_exports(viewer):
    png = viewer.export_png()
    assert png.is_file() and png.stat().st_size > 0
    ply = viewer.export_ply()
    assert len(load_ply(ply)) == len(viewer.snapshot)
    video = viewer.export_sweep(frames=4, fmt="mp4")
    assert video.exists() and (video.is_dir() or video.stat().st_size > 0)
    assert video.suffix in (".mp4", ".gif", "")


def test_renders_weather_and_jumps(viewer):
    from metegs.viewer.camera import pose_of
    from metegs.viewer.weather import WeatherValues

    pose = pose_of(viewer.trainer.dataset.cameras, 0)
    clean = viewer.render(pose, 48, "clean").astype(float)
    viewer.set_weather(WeatherValues(precip_mm_h=0.0))
    dry = viewer.render(pose, 48, "weather").astype(float)
    viewer.set_weather(WeatherValues(precip_mm_h=80.0, visibility_m=300.0))
    assert viewer.mode == "weather" and "violent" in viewer.rain_md.content
    storm = viewer.render(pose, 48, "weather").astype(float)
    assert np.abs(storm - clean).mean() > np.abs(dry - clean).mean() + 1.0
    hour = viewer.timeline.capture_index
    viewer.hour.value = hour  # no change: nothing happens
    viewer._jump_to_hour(hour)
    assert viewer.current_values().precip_mm_h == pytest.approx(6.8, rel=0.03)


# --- the browser ----------------------------------------------------------------------------------
def _browser_paths() -> tuple[str | None, str | None]:
    chrome = next((p for p in map(shutil.which, ("chromium", "chromium-browser", "google-chrome")) if p), None)
    return chrome, shutil.which("chromedriver")


def _artifacts(tmp_path: Path) -> Path:
    folder = Path(os.environ.get("METEGS_TEST_ARTIFACTS") or tmp_path)
    folder.mkdir(parents=True, exist_ok=True)
    return folder


def _scene_region(png: bytes) -> np.ndarray:
    """The part of a screenshot that shows only the rendered scene (left of the control panel, below the
    notifications)."""
    import cv2

    image = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR).astype(np.float64)
    h, w = image.shape[:2]
    return image[int(0.3 * h) :, : int(0.65 * w)]


def _not_blank(region: np.ndarray) -> bool:
    return 5.0 < region.mean() < 250.0 and region.std() > 4.0


def _shown(driver, path: Path, after: np.ndarray | None = None, timeout: float = 30.0):
    """A screenshot (saved to ``path``) once the scene shows a non-blank frame (different from ``after`` when
    given), or the last one taken after ``timeout``."""
    deadline = time.perf_counter() + timeout
    while True:
        time.sleep(0.5)
        png = driver.get_screenshot_as_png()
        region = _scene_region(png)
        ready = _not_blank(region) and (after is None or np.abs(region - after).mean() > 2.0)
        if ready or time.perf_counter() > deadline:
            path.write_bytes(png)
            return png, region


def _wait_frame(viewer, count: int, mode: str, timeout: float = 90.0) -> bool:
    """Until a new frame of ``mode`` was sent and the browser's view is final (full resolution, current camera)."""
    deadline = time.perf_counter() + timeout
    while time.perf_counter() < deadline:
        s = viewer.stats
        if s.count > count and s.mode == mode and viewer.settled():
            return True
        time.sleep(0.05)
    return False


def _why_no_browser() -> str | None:
    chrome, driver_path = _browser_paths()
    if chrome is None or driver_path is None:
        return "the browser test needs Debian's chromium and chromium-driver (apt-get install chromium chromium-driver)"
    if importlib.util.find_spec("selenium") is None:
        return "the browser test needs selenium (pip install -e '.[dev]')"
    return None


def _headless_chrome():
    """A Selenium driver of headless Chromium (the callers skip through `_why_no_browser` first)."""
    from selenium import webdriver
    from selenium.webdriver.chrome.options import Options
    from selenium.webdriver.chrome.service import Service

    chrome, driver_path = _browser_paths()
    options = Options()
    options.binary_location = chrome
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage", "--window-size=1280,800"):
        options.add_argument(arg)
    return webdriver.Chrome(service=Service(driver_path), options=options)


@pytest.mark.skipif(_why_no_browser() is not None, reason=str(_why_no_browser()))
def test_browser_precipitation_slider(viewer, tmp_path, record_property):
    from selenium.webdriver.common.by import By
    from selenium.webdriver.common.keys import Keys

    from metegs.viewer.weather import WeatherValues

    viewer.set_weather(WeatherValues(precip_mm_h=2.0, exposure_s=1 / 60))
    folder = _artifacts(tmp_path)
    driver = _headless_chrome()
    try:
        count = viewer.stats.count
        driver.get(viewer.url)
        assert _wait_frame(viewer, count, "weather"), f"no full frame rendered: {viewer.last_error}"
        before_png, before = _shown(driver, folder / "viewer-first-frame.png")  # the page fades in on slow GL
        assert _not_blank(before), "the first frame is blank"

        # the precipitation slider, found by its label, moved with the keyboard as a user would
        label = driver.find_element(By.XPATH, "//label[normalize-space(.)='Precipitation (log mm/h)']")
        thumb = driver.find_element(By.CSS_SELECTOR, f"[id='{label.get_attribute('for')}'] [role=slider]")
        count = viewer.stats.count
        thumb.click()
        thumb.send_keys(Keys.END)
        # the slider's value reaches the server first; its on_update callback (re-map θ, describe it) runs after
        deadline = time.perf_counter() + 30
        while (
            viewer.current_values().precip_mm_h < 150 or "violent" not in viewer.rain_md.content
        ) and time.perf_counter() < deadline:
            time.sleep(0.05)
        assert viewer.current_values().precip_mm_h > 150, "the slider did not reach the server"
        assert "violent" in viewer.rain_md.content, viewer.rain_md.content
        assert _wait_frame(viewer, count, "weather"), f"no frame after the slider moved: {viewer.last_error}"
        after_png, after = _shown(driver, folder / "viewer-heavy-rain.png", after=before)
        changed = float(np.abs(after - before).mean())
        assert changed > 2.0, f"the render did not change (mean |diff| {changed:.2f})"
        assert _not_blank(after), "the heavy-rain frame is blank"

        # the clean view, toggled in the page
        count = viewer.stats.count
        toggle = driver.find_element(By.XPATH, "//label[normalize-space(.)='Weather render']")
        driver.find_element(By.ID, toggle.get_attribute("for")).click()
        assert _wait_frame(viewer, count, "clean"), "no clean frame after the toggle"
        clean_png, clean = _shown(driver, folder / "viewer-clean.png", after=after)
        assert _not_blank(clean) and np.abs(clean - after).mean() > 2.0, "the clean view is blank or unchanged"

        # jumping to a training view (what a click on its frustum does) moves the browser's camera there
        view = viewer.trainer.dataset.train_indices[-1]
        target = viewer.trainer.dataset.cameras.camera_to_worlds[view, :3, 3].numpy()
        viewer.jump_to_view(None, view)
        deadline = time.perf_counter() + 20
        while time.perf_counter() < deadline:
            pose = next(iter(viewer._clients.values())).pose
            if np.allclose(pose.position, target, atol=1e-3):
                break
            time.sleep(0.05)
        assert np.allclose(pose.position, target, atol=1e-3), "the browser's camera did not move to the view"
    finally:
        driver.quit()
    paths = {
        "first frame": folder / "viewer-first-frame.png",
        "heavy rain": folder / "viewer-heavy-rain.png",
        "clean": folder / "viewer-clean.png",
    }
    for name, path in paths.items():
        record_property(f"screenshot {name}", str(path))
    print("viewer screenshots: " + ", ".join(f"{k}: {v}" for k, v in paths.items()))
    print(f"render changed by {changed:.1f} grey levels on average after the slider moved")


# --- the exported video in the browser ------------------------------------------------------------
def _video_state(driver, base: str, name: str, timeout: float = 30.0) -> dict:
    """Load ``base/name`` in a <video> on a page of ``base`` and wait until it has a current frame (readyState >= 2)
    or an error."""
    driver.get(f"{base}/")  # same origin as the video (Chromium blocks about:blank -> localhost media)
    driver.execute_script(
        "document.body.innerHTML = '';"
        "const v = document.createElement('video'); v.id = 'v'; v.muted = true; v.preload = 'auto';"
        "v.src = arguments[0]; document.body.appendChild(v); v.load();",
        name,
    )
    script = (
        "const v = document.getElementById('v');"
        "return {ready: v.readyState, duration: v.duration, width: v.videoWidth, height: v.videoHeight,"
        " error: v.error ? v.error.code : null};"
    )
    deadline = time.perf_counter() + timeout
    while True:
        state = driver.execute_script(script)
        if state["ready"] >= 2 or state["error"] is not None or time.perf_counter() > deadline:
            return state
        time.sleep(0.1)


@pytest.mark.skipif(_why_no_browser() is not None, reason=str(_why_no_browser()))
def test_browser_plays_the_exported_mp4(tmp_path, monkeypatch):
    """The sweep MP4 (H.264) plays in Chromium, served from localhost; OpenCV's mp4v, the old format, does not."""
    import functools
    import http.server
    import sys
    import threading
    import warnings

    pytest.importorskip("imageio_ffmpeg", reason="H.264 export needs imageio-ffmpeg (pip install 'metegs[video]')")
    import metegs.video as export

    rng = np.random.default_rng(0)
    frames = [rng.integers(0, 256, (49, 67, 3), dtype=np.uint8) for _ in range(8)]
    assert export.write_video(tmp_path / "sweep.mp4", frames, fps=8).name == "sweep.mp4"
    with monkeypatch.context() as m, warnings.catch_warnings():
        warnings.simplefilter("ignore", export.BrowserVideoWarning)
        m.setitem(sys.modules, "imageio_ffmpeg", None)  # the fallback: OpenCV's mp4v
        m.setattr(export, "_warned_mp4v", False)  # its once-a-process warning stays for real exports
        old = export.write_video(tmp_path / "sweep-mp4v.mp4", frames, fps=8)

    class Quiet(http.server.SimpleHTTPRequestHandler):
        def log_message(self, *args):
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(Quiet, directory=str(tmp_path)))
    threading.Thread(target=server.serve_forever, daemon=True).start()
    driver = _headless_chrome()
    try:
        base = f"http://127.0.0.1:{server.server_address[1]}"
        state = _video_state(driver, base, "sweep.mp4")
        assert state["error"] is None and state["ready"] >= 2, f"Chromium does not play the H.264 MP4: {state}"
        assert state["duration"] > 0 and (state["width"], state["height"]) == (66, 48), state
        if old.suffix == ".mp4":  # the control: the test would catch a file Chromium cannot play
            state = _video_state(driver, base, old.name)
            assert state["error"] is not None or state["ready"] < 2, f"mp4v played after all: {state}"
    finally:
        driver.quit()
        server.shutdown()
        server.server_close()
