"""metegs-process-images: pycolmap SfM on real photos, checked against the shipped LLFF poses."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from metegs.cli.process_images import ProcessImagesArgs, main
from metegs.data.config import DatasetConfig
from metegs.data.parsers.base import parse_scene
from metegs.data.sfm import SfmOptions, list_photos, run_sfm
from metegs.errors import ConfigError, DataError

SCENE = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "scenes" / "ethiopianhead-llff"
SUBSET = 12
"""Photos of the real scene used here (every other one of the first 24: a full run takes minutes)."""


def similarity_align(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Umeyama least-squares similarity mapping src [N, 3] onto dst [N, 3]; returns the mapped src."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    s, d = src - mu_s, dst - mu_d
    u, sig, vt = np.linalg.svd(d.T @ s / len(src))
    fix = np.eye(3)
    fix[2, 2] = np.sign(np.linalg.det(u @ vt))
    rot = u @ fix @ vt
    scale = np.trace(np.diag(sig) @ fix) / s.var(0).sum()
    return scale * s @ rot.T + mu_d


def test_similarity_align_recovers_a_known_transform():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(20, 3))
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.linalg.det(q))
    dst = 2.5 * src @ q.T + np.array([1.0, -2.0, 0.5])
    assert np.allclose(similarity_align(src, dst), dst, atol=1e-9)


@pytest.fixture(scope="module")
def processed(tmp_path_factory):
    if not SCENE.is_dir():
        pytest.skip(f"real LLFF scene not found at {SCENE} (needs ../shared beside the repository)")
    photos = tmp_path_factory.mktemp("photos")
    for name in sorted((SCENE / "images_8").iterdir())[: 2 * SUBSET : 2]:
        shutil.copy2(name, photos / name.name)
    out = tmp_path_factory.mktemp("sfm") / "head"
    # the bust turns on a turntable in front of a static room: SfM must see the object only (its masks)
    opts = SfmOptions(num_threads=1, accurate_features=True, min_inliers=15)
    result = main(ProcessImagesArgs(photos, out, masks=SCENE / "masks_8", sfm=opts))
    return photos, out, result


def test_registers_the_photos_and_writes_a_colmap_dataset(processed):
    photos, out, result = processed
    assert len(result.registered) >= SUBSET - 1
    assert result.mean_reprojection_error_px < 1.5
    assert sorted(p.name for p in (out / "images").iterdir()) == list_photos(photos)
    assert (out / "sparse" / "0").is_dir() and not (out / "database.db").exists()
    import pycolmap

    rec = pycolmap.Reconstruction(out / "sparse" / "0")  # undistorted: any tool takes the photos as they are
    assert {cam.model.name for cam in rec.cameras.values()} == {"PINHOLE"}
    assert "undistort" in result.timings_s
    record = json.loads((out / "process_images.json").read_text())
    assert record["registered"] == result.registered and record["options"]["matcher"] == "exhaustive"
    assert record["options"]["masks"] == str(SCENE / "masks_8")
    assert not list(out.parent.glob(".head.partial-*"))


def test_poses_agree_with_the_shipped_llff_poses(processed):
    """Camera centres, after the best similarity transform, lie near LLFF's (median 3 %, max 10 % of the
    rig's extent: LLFF's poses come from the 4000 px originals, ours from 500 px copies)."""
    _, out, result = processed
    sfm = parse_scene(out, "colmap", DatasetConfig(test_every=0))
    llff = parse_scene(SCENE, "llff", DatasetConfig(test_every=0))
    llff_centres = dict(zip(llff.names, llff.cameras.centers.double().numpy()))
    src = sfm.cameras.centers.double().numpy()
    dst = np.stack([llff_centres[name] for name in sfm.names])
    err = np.linalg.norm(similarity_align(src, dst) - dst, axis=1)
    extent = np.linalg.norm(dst - dst.mean(0), axis=1).max()
    assert np.median(err) < 0.03 * extent and err.max() < 0.10 * extent, (err, extent)


def test_missing_folder_and_empty_folder_are_clear_errors(tmp_path):
    with pytest.raises(DataError, match="does not exist"):
        run_sfm(tmp_path / "nope", tmp_path / "out")
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataError, match="no photos found"):
        run_sfm(tmp_path / "empty", tmp_path / "out")


def test_masks_must_cover_every_photo(tmp_path):
    import cv2

    photos, masks = tmp_path / "photos", tmp_path / "masks"
    photos.mkdir()
    masks.mkdir()
    for name in ("a", "b"):
        cv2.imwrite(str(photos / f"{name}.jpg"), np.zeros((8, 8, 3), np.uint8))
    cv2.imwrite(str(masks / "a.png"), np.full((8, 8), 255, np.uint8))
    with pytest.raises(DataError, match="no mask for 1 photo"):
        run_sfm(photos, tmp_path / "out", masks=masks)
    assert not (tmp_path / "out").exists()


def test_unreadable_photo_is_named(tmp_path):
    photos = tmp_path / "photos"
    photos.mkdir()
    (photos / "a.jpg").write_bytes(b"not an image")
    with pytest.raises(DataError, match="a.jpg"):
        run_sfm(photos, tmp_path / "out")


def test_unmatchable_photos_fail_clearly_and_leave_nothing(tmp_path):
    import cv2

    photos = tmp_path / "photos"
    photos.mkdir()
    rng = np.random.default_rng(1)
    for i in range(4):  # independent noise: features but no geometry
        cv2.imwrite(str(photos / f"{i}.png"), rng.integers(0, 255, size=(120, 160, 3), dtype=np.uint8))
    with pytest.raises(DataError, match="could be registered"):
        run_sfm(photos, tmp_path / "out", SfmOptions(num_threads=1))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["photos"]


def test_existing_output_is_kept_without_overwrite(tmp_path):
    photos = tmp_path / "photos"
    photos.mkdir()
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    with pytest.raises(ConfigError, match="--overwrite"):
        run_sfm(photos, out)
    assert (out / "keep.txt").read_text() == "mine"


def test_focal_priors_are_dropped_from_the_database(tmp_path):
    import pycolmap

    from metegs.data.sfm import _drop_focal_priors

    db = tmp_path / "database.db"
    database = pycolmap.Database.open(db)
    camera = pycolmap.Camera.create(1, pycolmap.CameraModelId.SIMPLE_RADIAL, 900.0, 640, 480)
    camera.has_prior_focal_length = True
    database.write_camera(camera)
    database.close()
    assert _drop_focal_priors(pycolmap, db)
    database = pycolmap.Database.open(db)
    assert not any(cam.has_prior_focal_length for cam in database.read_all_cameras())
    database.close()
    assert not _drop_focal_priors(pycolmap, db)  # nothing left to drop: no second mapping


@pytest.fixture
def four_photos(tmp_path):
    """Four photos of the real scene (every other one of the first eight), for the mapping-retry tests."""
    if not SCENE.is_dir():
        pytest.skip(f"real LLFF scene not found at {SCENE} (needs ../shared beside the repository)")
    photos = tmp_path / "photos"
    photos.mkdir()
    for name in sorted((SCENE / "images_8").iterdir())[:8:2]:
        shutil.copy2(name, photos / name.name)
    return photos


def _count_mappings(monkeypatch, fails):
    """Patch `run_sfm`'s mapping so that the calls for which ``fails(dropped)`` holds build nothing; returns the
    lists of calls made (seed, forward) and of focal-length drops."""
    import metegs.data.sfm as sfm

    real_map, calls, dropped = sfm._map, [], []

    def mapping(*args, forward=False):
        calls.append((args[-2].seed, forward))
        return [] if fails(len(calls), dropped) else real_map(*args, forward=forward)

    def drop(pycolmap, db):
        dropped.append(db)
        return True  # these photos carry no EXIF focal: count the call and go on

    monkeypatch.setattr(sfm, "_map", mapping)
    monkeypatch.setattr(sfm, "_drop_focal_priors", drop)
    return calls, dropped


def test_a_stalled_mapping_retries_with_a_forward_initial_pair(four_photos, tmp_path, monkeypatch):
    """A first mapping that registers nothing (as COLMAP's initial pair can leave a street walk) is retried with a
    forward-moving initial pair allowed, the EXIF focal kept; the retry's model is kept and said so."""
    calls, dropped = _count_mappings(monkeypatch, lambda n, dropped: n == 1)
    opts = SfmOptions(num_threads=1, accurate_features=True, min_inliers=15)
    result = run_sfm(four_photos, tmp_path / "out", opts, masks=SCENE / "masks_8")
    assert calls[:2] == [(0, False), (0, True)] and not dropped
    assert (result.initial_pair, result.focal_prior) == ("forward", "exif") and len(result.registered) >= 3
    record = json.loads((tmp_path / "out" / "process_images.json").read_text())
    assert (record["initial_pair"], record["focal_prior"]) == ("forward", "exif")
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["images", "process_images.json", "sparse"]


def test_mapping_that_stalls_from_exif_retries_without_the_focal(four_photos, tmp_path, monkeypatch):
    """Where the forward retries stall too (from every seed), the EXIF focal is dropped and mapping retried."""
    import metegs.data.sfm as sfm

    calls, dropped = _count_mappings(monkeypatch, lambda n, dropped: not dropped)
    opts = SfmOptions(num_threads=1, accurate_features=True, min_inliers=15)
    result = run_sfm(four_photos, tmp_path / "out", opts, masks=SCENE / "masks_8")
    retries = [(seed, True) for seed in range(sfm.RETRY_SEEDS)]
    assert len(dropped) == 1 and calls[: 2 + sfm.RETRY_SEEDS] == [(0, False), *retries, (0, True)]
    assert (result.initial_pair, result.focal_prior) == ("forward", "dropped") and len(result.registered) >= 3


def test_a_forward_mapping_relaxes_colmaps_initial_pair_checks(tmp_path):
    """forward=True lets the initial pair move along its view with a small angle; the default keeps COLMAP's."""
    import pycolmap

    import metegs.data.sfm as sfm

    seen = []

    class Recorder:
        IncrementalPipelineOptions = pycolmap.IncrementalPipelineOptions

        @staticmethod
        def incremental_mapping(db, images, sparse, options, **callbacks):
            seen.append((options.mapper.init_max_forward_motion, options.mapper.init_min_tri_angle))
            return {}

    for forward in (False, True):
        sfm._map(Recorder, tmp_path / "db", tmp_path, tmp_path / "sparse", 4, SfmOptions(), print, forward=forward)
    default = pycolmap.IncrementalPipelineOptions().mapper
    assert seen == [
        (default.init_max_forward_motion, default.init_min_tri_angle),
        (1.0, sfm.FORWARD_INIT_TRI_ANGLE_DEG),
    ]
    assert default.init_max_forward_motion < 1.0 and default.init_min_tri_angle > sfm.FORWARD_INIT_TRI_ANGLE_DEG


def test_mapping_that_registers_enough_photos_is_not_repeated(four_photos, tmp_path, monkeypatch):
    """Only a stalled mapping (under `RETRY_BELOW` of the photos) maps again: 4 of 4 keep the EXIF start (from seed 3;
    from seeds 0 and 1 COLMAP's initial pair leaves two models of two photos each, and the forward retry maps all
    four)."""
    import metegs.data.sfm as sfm

    dropped = []
    monkeypatch.setattr(sfm, "_drop_focal_priors", lambda pycolmap, db: dropped.append(db) or True)
    opts = SfmOptions(num_threads=1, accurate_features=True, min_inliers=15, seed=3)
    result = run_sfm(four_photos, tmp_path / "out", opts, masks=SCENE / "masks_8")
    assert len(result.registered) >= sfm.RETRY_BELOW * 4 and not dropped
    assert (result.initial_pair, result.focal_prior) == ("default", "exif")


@pytest.mark.parametrize("single_camera", [True, False])
def test_extraction_numbers_the_photos_in_file_order(four_photos, tmp_path, single_camera):
    """The photos are numbered in file order, whatever order COLMAP's threads finish them in: with one camera each
    photo is a frame of that camera's rig, as COLMAP enters it; with a camera per photo each has its own."""
    import pycolmap

    import metegs.data.sfm as sfm

    names = list_photos(four_photos)
    opts = SfmOptions(num_threads=2, single_camera=single_camera)
    sfm._extract(pycolmap, tmp_path / "db", four_photos, names, None, opts, lambda *a: None)
    database = pycolmap.Database.open(tmp_path / "db")
    try:
        images = sorted(database.read_all_images(), key=lambda im: im.image_id)
        frames = database.read_all_frames()
        assert [im.name for im in images] == names
        assert all(database.num_keypoints_for_image(im.image_id) > 100 for im in images)
        assert sorted(data.id for f in frames for data in f.image_ids) == [im.image_id for im in images]
        assert database.num_cameras() == (1 if single_camera else len(names))
        assert len({im.camera_id for im in images}) == database.num_cameras()
    finally:
        database.close()


def test_the_same_photos_and_seed_give_the_same_poses_on_several_threads(four_photos, tmp_path):
    """COLMAP numbers the photos of one extraction call as its threads finish them, verifies each pair with RANSAC
    from a random seed, and maps differently on several threads: the Lund street's 29 photos registered 27, 28 or 29
    from run to run. The same photos and seed now pose alike, point for point, on two threads (these four small photos
    matched alike in 21 of 21 runs; the street's raw matches differed in 3 of 5, so it takes one thread for that)."""
    import pycolmap

    opts = SfmOptions(num_threads=2, min_inliers=15, seed=3)
    runs = [run_sfm(four_photos, tmp_path / f"run{i}", opts, masks=SCENE / "masks_8") for i in range(2)]
    assert runs[0].registered == runs[1].registered and runs[0].num_points == runs[1].num_points
    poses = []
    for i in range(2):
        model = pycolmap.Reconstruction(str(tmp_path / f"run{i}" / "sparse" / "0"))
        poses.append({im.name: im.cam_from_world().matrix() for im in model.images.values()})
    assert poses[0].keys() == poses[1].keys() and len(poses[0]) >= 3
    assert all(np.array_equal(poses[0][name], poses[1][name]) for name in poses[0])


@pytest.mark.parametrize("hazed", [False, True])
def test_hazed_photos_are_matched_at_a_lower_contrast_threshold(tmp_path, monkeypatch, hazed):
    """Fog leaves a third of a photo's contrast, and SIFT's threshold is absolute: SfM lowers it for hazed photos
    and keeps COLMAP's for clear ones (the triangulation tests show what it finds)."""
    import metegs.data.sfm as sfm
    from metegs.data.images import save_image

    photos = tmp_path / "photos"
    rng = np.random.default_rng(0)
    for i in range(3):
        image = rng.random((48, 64, 3)).astype(np.float32)
        save_image(photos / f"{i}.png", 0.3 * image + 0.6 if hazed else image)
    seen = []

    def stop(pycolmap, db, images, names, masks, opts, progress):
        seen.append(opts.peak_threshold)
        raise RuntimeError("stopped after the options were set")

    monkeypatch.setattr(sfm, "_extract", stop)
    with pytest.raises(RuntimeError, match="stopped after"):
        run_sfm(photos, tmp_path / "out")
    assert (0 < seen[0] < 0.5 * sfm.SIFT_PEAK_THRESHOLD) if hazed else seen[0] == 0
    assert not (tmp_path / "out").exists()
    with pytest.raises(RuntimeError, match="stopped after"):
        run_sfm(photos, tmp_path / "out", SfmOptions(peak_threshold=0.004))
    assert seen[-1] == 0.004  # an explicit threshold is the user's


def test_a_negative_contrast_threshold_is_a_clear_error(tmp_path):
    with pytest.raises(ConfigError, match="peak-threshold"):
        run_sfm(tmp_path / "photos", tmp_path / "out", SfmOptions(peak_threshold=-0.001))
    assert not (tmp_path / "out").exists()
