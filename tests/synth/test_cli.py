"""metegs-synth: degraded datasets in their own format, clean images alongside, weather.json, preview, atomic."""

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from rich.console import Console

from metegs.data.config import DatasetConfig, SyntheticSceneConfig
from metegs.data.parsers.base import parse_scene
from metegs.errors import ConfigError, DataError
from metegs.meteo import default_storm_path
from metegs.synth import writers
from metegs.synth.pipeline import SynthConfig, synthesise

TINY = DatasetConfig(synthetic=SyntheticSceneConfig(width=48, height=36, num_views=4, num_points=50))


def run(output: Path, **kw) -> Path:
    kw.setdefault("capture_width_px", 0)  # θ at the tiny stored size: few streaks, fast tests
    args = SynthConfig(output=output, dataset=kw.pop("dataset", TINY), **kw)
    return synthesise(args, Console(file=open("/dev/null", "w")))


def images(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


@pytest.fixture(scope="module")
def storm(tmp_path_factory) -> Path:
    """The synthetic scene degraded with explicit heavy rain and fog."""
    out = tmp_path_factory.mktemp("synth") / "storm"
    run(out, precip_mm_h=30.0, visibility_m=400.0, exposure_s=1 / 30, rain_far_m=4.0, seed=7)
    return out


def test_synthetic_scene_becomes_a_nerfstudio_dataset_that_reads_back(storm):
    names = {p.name for p in storm.iterdir()}
    assert {"transforms.json", "images", "images_clean", "depths", "points.ply", "weather.json", "preview.png"} <= names
    back = parse_scene(storm, None, DatasetConfig())
    src = parse_scene(None, None, TINY)
    assert back.parser == "nerfstudio" and len(back) == 4
    assert back.clean_image_paths is not None and back.depths is not None
    assert back.train_indices == src.train_indices and back.test_indices == src.test_indices
    np.testing.assert_allclose(back.cameras.camera_to_worlds, src.cameras.camera_to_worlds, atol=1e-5)
    np.testing.assert_array_equal(back.depths[1], src.depths[1])
    assert back.points is not None and len(back.points) == len(src.points)
    clean = cv2.imread(str(back.clean_image_paths[0]))[..., ::-1] / 255.0
    assert np.abs(clean - src.images[0]).max() <= 0.5 / 255 + 1e-6  # the clean image, 8-bit
    rainy = cv2.imread(str(back.image_paths[0]))[..., ::-1] / 255.0
    assert np.abs(rainy - src.images[0]).mean() > 0.01


def test_weather_json_and_preview(storm):
    weather = json.loads((storm / "weather.json").read_text())
    assert weather["kinds"] == "rain+fog" and weather["seed"] == 7 and weather["format"] == "nerfstudio"
    assert weather["metres_per_unit"] == parse_scene(None, None, TINY).metric_scale
    assert weather["record"]["values"]["precip_mm_h"] == 30.0
    views = weather["views"]
    assert len(views) == 4 and [v["image"] for v in views] == [f"images/view_{i:03d}.png" for i in range(4)]
    assert views[0]["theta"]["rain"]["intensity_class"] == "heavy"
    assert views[0]["theta"]["fog"]["visibility_m"] == 400.0
    assert all(v["num_rain_gaussians"] > 0 and v["fog"] for v in views)
    sheet = cv2.imread(str(storm / "preview.png"))
    assert sheet is not None and sheet.shape[0] > 2 * 36 and sheet.shape[1] > 4 * 48


def test_same_seed_same_bytes_other_seed_other_rain(storm, tmp_path):
    again = run(tmp_path / "again", precip_mm_h=30.0, visibility_m=400.0, exposure_s=1 / 30, rain_far_m=4.0, seed=7)
    assert images(again / "images") == images(storm / "images")
    assert (again / "weather.json").read_bytes() == (storm / "weather.json").read_bytes()
    other = run(tmp_path / "other", precip_mm_h=30.0, visibility_m=400.0, exposure_s=1 / 30, rain_far_m=4.0, seed=8)
    a, b = images(storm / "images"), images(other / "images")
    assert all(a[k] != b[k] for k in a)
    assert images(other / "images_clean") == images(storm / "images_clean")


def test_refuses_to_overwrite_and_replaces_with_overwrite(storm, tmp_path):
    out = tmp_path / "o"
    out.mkdir()
    (out / "keep.txt").write_text("x")
    with pytest.raises(ConfigError, match="exists"):
        run(out, kinds="fog", visibility_m=300.0)
    assert (out / "keep.txt").exists()
    run(out, kinds="fog", visibility_m=300.0, overwrite=True)
    assert not (out / "keep.txt").exists() and (out / "weather.json").exists()
    assert json.loads((out / "weather.json").read_text())["kinds"] == "fog"


def test_an_interrupted_run_leaves_nothing(tmp_path, monkeypatch):
    calls = []

    def failing(self, i, degraded, clean):
        calls.append(i)
        if len(calls) == 3:
            raise RuntimeError("disk full")

    monkeypatch.setattr(writers.DatasetWriter, "write_view", failing)
    with pytest.raises(RuntimeError, match="disk full"):
        run(tmp_path / "out", precip_mm_h=5.0)
    assert list(tmp_path.iterdir()) == []


def test_shipped_storm_by_default_and_record_errors(tmp_path):
    out = run(tmp_path / "default", kinds="rain")
    weather = json.loads((out / "weather.json").read_text())
    assert weather["record"]["file"].startswith(str(default_storm_path()))
    assert weather["views"][0]["theta"]["rain"]["precip_mm_per_h"] == pytest.approx(6.8)
    assert weather["views"][0]["time"].startswith("2013-08-11T07:40")
    with pytest.raises(DataError, match="outside the record"):
        run(tmp_path / "x", time=("2020-01-01T00:00Z",))
    bad = tmp_path / "bad.csv"
    bad.write_text("a,b\n1,2\n")
    with pytest.raises(DataError, match="bad.csv"):
        run(tmp_path / "y", record=bad, time=("2020-01-01T00:00Z",))
    with pytest.raises(ConfigError, match="--time is needed"):
        run(tmp_path / "z", record=default_storm_path())
    with pytest.raises(ConfigError, match="not both"):
        run(tmp_path / "w", record=default_storm_path(), time=("2013-08-11T07:40Z",), precip_mm_h=3.0)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.csv", "default"]


def test_several_capture_times_are_spread_over_the_views(tmp_path):
    out = run(tmp_path / "t", record=default_storm_path(), time=("2013-08-11T06:40Z", "2013-08-11T09:40Z"))
    views = json.loads((out / "weather.json").read_text())["views"]
    times = [v["time"][:16] for v in views]
    assert times == ["2013-08-11T06:40"] * 2 + ["2013-08-11T09:40"] * 2
    rates = [v["theta"]["rain"]["precip_mm_per_h"] for v in views]
    assert rates[0] == rates[1] != rates[2] == rates[3]


def write_llff(root: Path, n: int = 3) -> None:
    rows = []
    for i in range(n):
        m = np.zeros((3, 5))
        m[:, :3] = [[0, 1, 0], [1, 0, 0], [0, 0, -1]]
        m[:, 3] = [0.1 * i, 0.0, -4.0]
        m[:, 4] = [36, 48, 45]
        rows.append(np.concatenate([m.reshape(-1), [1.0, 10.0]]))
    np.save(root / "poses_bounds.npy", np.array(rows))
    (root / "images_4").mkdir()
    (root / "masks_4").mkdir()
    rng = np.random.default_rng(0)
    for i in range(n):
        cv2.imwrite(str(root / "images_4" / f"im_{i}.jpg"), rng.integers(0, 255, (36, 48, 3), dtype=np.uint8))
        cv2.imwrite(str(root / "masks_4" / f"im_{i}.png"), np.full((36, 48), 255, np.uint8))
    (root / "LICENSE.md").write_text("CC BY\n")


def test_llff_needs_depth_and_is_written_as_llff(tmp_path):
    from metegs.files import staged_output
    from metegs.synth.writers import DatasetWriter
    from metegs.weather.degrade import degrade_scene

    src = tmp_path / "scene"
    src.mkdir()
    write_llff(src)
    with pytest.raises(DataError, match="no depth"):
        run(tmp_path / "out", data=src, precip_mm_h=10.0)
    scene = parse_scene(src, None, DatasetConfig())
    from metegs.meteo import theta_from_values
    from metegs.weather.conditions import camera_spec

    theta = theta_from_values(
        50.0, visibility_m=50.0, fog_kind="fog", camera=camera_spec(scene.cameras, capture_width_px=0, far_m=3.0)
    )
    depths = [np.full((36, 48), 3.0, np.float32)] * 3
    rainy, _ = degrade_scene(scene, theta, depths=depths, metres_per_unit=1.0)
    with staged_output(tmp_path / "out") as tmp:
        w = DatasetWriter(scene, tmp)
        for i in range(3):
            w.write_view(i, rainy.images[i], rainy.clean_images[i])
        w.finish()
    out = tmp_path / "out"
    assert sorted(p.name for p in out.iterdir()) == [
        "LICENSE.md",
        "images_4",
        "images_4_clean",
        "masks_4",
        "poses_bounds.npy",
    ]
    back = parse_scene(out, None, DatasetConfig())
    assert back.parser == "llff" and back.names == scene.names and back.mask_paths is not None
    assert [p.name for p in back.clean_image_paths] == ["im_0.jpg", "im_1.jpg", "im_2.jpg"]
    assert all(c.read_bytes() == s.read_bytes() for c, s in zip(back.clean_image_paths, scene.image_paths))
    assert all(r.read_bytes() != s.read_bytes() for r, s in zip(back.image_paths, scene.image_paths))
    np.testing.assert_allclose(back.cameras.camera_to_worlds, scene.cameras.camera_to_worlds)


def write_masked_nerfstudio(src: Path, **top_level) -> None:
    """Three random 48x36 views looking down -z at the origin (OpenGL), each with an all-white mask, as a nerfstudio
    scene in ``src``; ``top_level`` adds keys to its transforms.json (a lens distortion, a point cloud file)."""
    (src / "images").mkdir(parents=True)
    (src / "masks").mkdir()
    rng = np.random.default_rng(0)
    frames = []
    for i in range(3):
        cv2.imwrite(str(src / "images" / f"im_{i}.jpg"), rng.integers(0, 255, (36, 48, 3), dtype=np.uint8))
        cv2.imwrite(str(src / "masks" / f"im_{i}.png"), np.full((36, 48), 255, np.uint8))
        c2w = np.eye(4)
        c2w[:3, 3] = [0.2 * i, 0.0, 4.0]
        frames.append(
            {"file_path": f"images/im_{i}.jpg", "mask_path": f"masks/im_{i}.png", "transform_matrix": c2w.tolist()}
        )
    meta = {"frames": frames, "fl_x": 40.0, "fl_y": 40.0, "cx": 24.0, "cy": 18.0, "w": 48, "h": 36}
    (src / "transforms.json").write_text(json.dumps({**meta, **top_level}))


def test_a_nerfstudio_copy_keeps_its_masks_and_points(tmp_path):
    """The degraded copy of a nerfstudio scene reads back with each frame's mask and the point cloud."""
    from metegs.files import staged_output
    from metegs.meteo import theta_from_values
    from metegs.synth.writers import DatasetWriter, write_ply_points
    from metegs.weather.conditions import camera_spec
    from metegs.weather.degrade import degrade_scene

    src = tmp_path / "scene"
    write_masked_nerfstudio(src, ply_file_path="points.ply")
    rng = np.random.default_rng(1)
    write_ply_points(src / "points.ply", rng.normal(size=(20, 3)), rng.uniform(size=(20, 3)))
    scene = parse_scene(src, None, DatasetConfig())
    assert scene.mask_paths is not None
    theta = theta_from_values(
        30.0, visibility_m=50.0, fog_kind="fog", camera=camera_spec(scene.cameras, capture_width_px=0, far_m=5.0)
    )
    rainy, _ = degrade_scene(scene, theta, depths=[np.full((36, 48), 4.0, np.float32)] * 3, metres_per_unit=1.0)
    with staged_output(tmp_path / "out") as tmp:
        w = DatasetWriter(scene, tmp)
        for i in range(3):
            w.write_view(i, rainy.images[i], rainy.clean_images[i])
        w.finish()
    back = parse_scene(tmp_path / "out", None, DatasetConfig())
    assert back.mask_paths is not None and [p.name for p in back.mask_paths] == [p.name for p in scene.mask_paths]
    assert all(b.read_bytes() == s.read_bytes() for b, s in zip(back.mask_paths, scene.mask_paths))
    np.testing.assert_allclose(back.points, scene.points)
    from metegs.data.point_colours import colours_seen  # coloured from the degraded photos, not the clean ones

    photos = [cv2.imread(str(p))[..., ::-1].astype(np.float32) / 255 for p in back.image_paths]
    np.testing.assert_allclose(back.point_colors, colours_seen(scene.points, scene.cameras, photos), atol=1 / 255)
    assert np.abs(back.point_colors - scene.point_colors).max() > 0.1


def test_a_synthetic_copys_points_take_the_colours_of_its_degraded_views(storm):
    from metegs.data.point_colours import colours_seen

    back, original = parse_scene(storm, None, DatasetConfig()), parse_scene(None, None, TINY)
    np.testing.assert_allclose(back.points, original.points, atol=1e-6)
    photos = [cv2.imread(str(p))[..., ::-1].astype(np.float32) / 255 for p in back.image_paths]
    expected = colours_seen(back.points, back.cameras, photos, back.depths)
    np.testing.assert_allclose(back.point_colors, expected, atol=1 / 255)
    assert np.abs(back.point_colors - original.point_colors).mean() > 0.02  # the storm's, not the clean scene's


def test_synthetic_copy_reads_back_with_its_scale_exposure_up_and_rendering(storm):
    import torch

    scene = parse_scene(storm, None, DatasetConfig())
    original = parse_scene(None, None, TINY)
    assert scene.metric_scale == original.metric_scale
    assert np.allclose(scene.up, original.up)
    assert torch.allclose(scene.cameras.exposure_time_s, original.cameras.exposure_time_s)
    assert original.rendered and scene.rendered  # one exposure: `view_exposure` auto stays off on the copy


def test_a_photographed_scene_copy_is_not_marked_rendered(tmp_path):
    """A nerfstudio capture of photos is not rendered; its metegs block may say so, but only as true or false."""
    src = tmp_path / "scene"
    write_masked_nerfstudio(src)
    assert not parse_scene(src, None, DatasetConfig()).rendered
    meta = json.loads((src / "transforms.json").read_text())
    (src / "transforms.json").write_text(json.dumps({**meta, "metegs": {"rendered": "yes"}}))
    with pytest.raises(DataError, match="metegs.rendered"):
        parse_scene(src, None, DatasetConfig())


def test_a_distorted_capture_is_degraded_as_the_pinhole_views_it_trains_on(tmp_path):
    """Frames with lens distortion are read through undistorted copies; their degraded copy is a PINHOLE nerfstudio
    dataset of those views (weather drawn on a distorted original would need distorting too), and reads back with
    the same cameras."""
    from metegs.files import staged_output
    from metegs.meteo import theta_from_values
    from metegs.synth.writers import DatasetWriter, reads_cached_copies
    from metegs.weather.conditions import camera_spec
    from metegs.weather.degrade import degrade_scene

    src = tmp_path / "scene"
    write_masked_nerfstudio(src, k1=-0.2)
    scene = parse_scene(src, None, DatasetConfig())
    assert reads_cached_copies(scene)
    theta = theta_from_values(
        30.0, visibility_m=50.0, fog_kind="fog", camera=camera_spec(scene.cameras, capture_width_px=0, far_m=5.0)
    )
    rainy, _ = degrade_scene(scene, theta, depths=[np.full((36, 48), 4.0, np.float32)] * 3, metres_per_unit=1.0)
    with staged_output(tmp_path / "out") as tmp:
        w = DatasetWriter(scene, tmp)
        assert w.format == "nerfstudio" and w.image_rel == [f"images/im_{i}.png" for i in range(3)]
        for i in range(3):
            w.write_view(i, rainy.images[i], rainy.clean_images[i])
        w.finish()
    out = tmp_path / "out"
    written = json.loads((out / "transforms.json").read_text())
    assert written["camera_model"] == "PINHOLE" and "k1" not in written and "k1" not in written["frames"][0]
    assert "undistorted" in written["metegs"]["source"]
    back = parse_scene(out, None, DatasetConfig())
    assert back.parser == "nerfstudio" and not reads_cached_copies(back)
    assert back.mask_paths is not None  # the undistorted masks travel with their views
    assert all(b.read_bytes() == s.read_bytes() for b, s in zip(back.mask_paths, scene.mask_paths))
    for field in ("fx", "fy", "cx", "cy"):
        torch.testing.assert_close(getattr(back.cameras, field), getattr(scene.cameras, field))
    torch.testing.assert_close(back.cameras.camera_to_worlds, scene.cameras.camera_to_worlds)
    assert all(c.read_bytes() == s.read_bytes() for c, s in zip(back.clean_image_paths, scene.image_paths))
    assert not (src / "images_clean").exists()  # the source is read, never written (its cache aside)
