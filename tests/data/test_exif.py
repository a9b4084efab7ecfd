"""Exposure times from the photos' EXIF reach the cameras (COLMAP, distorted or not) and θ's streak length."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

import metegs.builtins  # noqa: F401  (registers the parsers)
from metegs.data.config import DatasetConfig
from metegs.data.exif import EXIF_IFD, EXPOSURE_TIME, exposure_time_s, exposure_times_s
from metegs.data.parsers.base import parse_scene
from metegs.data.undistort import CACHE_DIR
from metegs.weather.conditions import camera_spec

from .test_colmap import H, W, make_model


def write_jpeg(path, exposure_s: float | None, value: int = 90) -> None:
    exif = Image.Exif() if exposure_s is None else _exif(exposure_s)
    Image.fromarray(np.full((H, W, 3), value, np.uint8)).save(path, format="JPEG", exif=exif)


def test_exposure_is_read_and_missing_ones_take_the_median(tmp_path):
    for name, t in [("a.jpg", 1 / 250), ("b.jpg", None), ("c.jpg", 1 / 60), ("d.jpg", 1 / 1000)]:
        write_jpeg(tmp_path / name, t)
    (tmp_path / "e.jpg").write_bytes(b"not an image")
    assert exposure_time_s(tmp_path / "a.jpg") == pytest.approx(1 / 250)
    assert exposure_time_s(tmp_path / "b.jpg") is None and exposure_time_s(tmp_path / "e.jpg") is None
    times = exposure_times_s([tmp_path / n for n in ("a.jpg", "b.jpg", "c.jpg", "d.jpg", "e.jpg")])
    assert times == pytest.approx([1 / 250, 1 / 250, 1 / 60, 1 / 1000, 1 / 250])  # median of the three found
    assert exposure_times_s([tmp_path / "b.jpg", tmp_path / "e.jpg"]) is None


@pytest.mark.parametrize("model,params", [("PINHOLE", None), ("OPENCV", [100.0, 102.0, 79.0, 61.0, -0.2, 0.05, 0, 0])])
def test_colmap_cameras_get_the_photos_exposure_and_theta_uses_their_median(tmp_path, model, params):
    rec = make_model(tmp_path, model, params, n_images=3, write_images=False)
    (tmp_path / "images").mkdir()
    names = sorted(im.name for im in rec.images.values())
    for name, t in zip(names, (1 / 500, 1 / 125, 1 / 250)):
        write_jpeg(tmp_path / "images" / name, t)  # JPEG bytes under the model's .png names: PIL reads them
    scene = parse_scene(tmp_path, None, DatasetConfig())
    assert scene.cameras.exposure_time_s.tolist() == pytest.approx([1 / 500, 1 / 125, 1 / 250])
    assert camera_spec(scene.cameras).exposure_s == pytest.approx(1 / 250)  # the median, not the first view's
    assert camera_spec(scene.cameras, exposure_s=0.5).exposure_s == 0.5  # an explicit value wins


def test_photos_without_exif_keep_the_default(tmp_path):
    make_model(tmp_path, n_images=2)  # PNG files without EXIF
    scene = parse_scene(tmp_path, None, DatasetConfig())
    assert scene.cameras.exposure_time_s is None
    assert camera_spec(scene.cameras).exposure_s == pytest.approx(1 / 60)


def test_distorted_nerfstudio_frames_keep_their_exif_exposure(tmp_path):
    from .test_nerfstudio import _write_distorted_scene

    _write_distorted_scene(tmp_path, fisheye=False, per_frame=False)
    for i, t in enumerate((1 / 200, 1 / 100)):  # the same pixels, now as JPEG with EXIF under the .png names
        Image.open(tmp_path / "images" / f"f{i}.png").convert("RGB").save(tmp_path / "images" / f"f{i}.png",
                                                                        format="JPEG", exif=_exif(t))  # fmt: skip
    scene = parse_scene(tmp_path, None, DatasetConfig())
    assert all(CACHE_DIR in p.parts for p in scene.image_paths)  # undistorted copies, which have no EXIF
    assert scene.cameras.exposure_time_s.tolist() == pytest.approx([1 / 200, 1 / 100])


def _exif(exposure_s: float) -> Image.Exif:
    exif = Image.Exif()
    exif.get_ifd(EXIF_IFD)[EXPOSURE_TIME] = exposure_s
    return exif
