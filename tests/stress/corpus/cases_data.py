"""Corrupt data files: COLMAP models (binary and text), PLY Gaussians, images, LLFF, nerfstudio and Blender scenes.

Each builder writes a tiny valid scene (32x24 images) or run folder, corrupts one thing, and returns the
command's arguments. Scenes are read by ``metegs-train --data``; PLY files (a tiny trained run's Gaussians,
rewritten) by ``metegs-render`` / ``metegs-eval --ply`` on that run.
"""

from __future__ import annotations

import io
import json
import struct
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import numpy.lib.format as npy_format

from corpus.harness import QUIET_RUN, Case, Result, trained_run

W, H = 32, 24
"""Size of the images of every scene built here."""


# --- valid inputs ------------------------------------------------------------------------------------


def _c2w(i: int, n: int) -> np.ndarray:
    """[4, 4] OpenCV camera-to-world of view ``i`` of ``n`` on a circle of radius 3 looking at the origin."""
    angle = 2 * np.pi * i / n
    center = np.array([3 * np.cos(angle), 3 * np.sin(angle), 0.5])
    z = -center / np.linalg.norm(center)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, np.cross(z, x), z, center
    return m


def _photo(i: int) -> np.ndarray:
    """[H, W, 3] uint8 test picture of view ``i``."""
    yy, xx = np.mgrid[0:H, 0:W]
    return np.stack([xx * 8 % 256, yy * 10 % 256, np.full_like(xx, 40 * i)], axis=2).astype(np.uint8)


def _train(folder: Path, scene: Path, *extra) -> list:
    return ["3dgs", "--data", scene, *QUIET_RUN, "--output-dir", folder / "out", "--experiment-name", "run", *extra]


def colmap_scene(folder: Path, text: bool = False, n_points: int = 4) -> Path:
    """``folder/scene``: 3 PINHOLE views with 4 2D points each, ``n_points`` 3D points (the first 4 seen by all)."""
    import pycolmap

    scene, rng = folder / "scene", np.random.default_rng(0)
    (scene / "images").mkdir(parents=True)
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(pycolmap.Camera.create_from_model_name(1, "PINHOLE", 30.0, W, H))
    for i in range(3):
        w2c = np.linalg.inv(_c2w(i, 3))
        pts = pycolmap.Point2DList([pycolmap.Point2D(np.array([5.0 + k, 6.0])) for k in range(4)])
        image = pycolmap.Image(name=f"img_{i}.png", points2D=pts, camera_id=1, image_id=i + 1)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pycolmap.Rotation3d(w2c[:3, :3]), w2c[:3, 3]))
        cv2.imwrite(str(scene / "images" / f"img_{i}.png"), _photo(i))
    for k in range(n_points):
        track = pycolmap.Track()
        for i in range(3 if k < 4 else 0):
            track.add_element(i + 1, k)
        rec.add_point3D(rng.normal(size=3) * 0.3, track, np.array([200, 120, 40], np.uint8))
    (scene / "sparse" / "0").mkdir(parents=True)
    (rec.write_text if text else rec.write)(str(scene / "sparse" / "0"))
    return scene


def nerfstudio_scene(folder: Path, suffix: str = ".png", **extra) -> Path:
    """``folder/scene``: transforms.json with 4 frames (shared intrinsics) and their images."""
    scene = folder / "scene"
    (scene / "images").mkdir(parents=True)
    frames = []
    for i in range(4):
        name = f"images/frame_{i}{suffix}"
        cv2.imwrite(str(scene / name), _photo(i))
        frames.append({"file_path": name, "transform_matrix": (_c2w(i, 4) @ np.diag([1, -1, -1, 1])).tolist()})
    meta = {"fl_x": 30.0, "fl_y": 30.0, "cx": W / 2, "cy": H / 2, "w": W, "h": H, "frames": frames, **extra}
    (scene / "transforms.json").write_text(json.dumps(meta))
    return scene


def llff_scene(folder: Path) -> Path:
    """``folder/scene``: poses_bounds.npy with 3 rows and images/ with 3 pictures."""
    scene = folder / "scene"
    (scene / "images").mkdir(parents=True)
    rows = []
    for i in range(3):
        c2w = _c2w(i, 3)
        pose = np.stack([c2w[:3, 1], c2w[:3, 0], -c2w[:3, 2], c2w[:3, 3], [H, W, 30.0]], axis=1)  # LLFF axes
        rows.append(np.concatenate([pose.reshape(-1), [0.5, 10.0]]))
        cv2.imwrite(str(scene / "images" / f"im_{i}.png"), _photo(i))
    np.save(scene / "poses_bounds.npy", np.array(rows))
    return scene


def blender_scene(folder: Path) -> Path:
    """``folder/scene``: transforms_train.json with 3 frames and train/r_i.png."""
    scene = folder / "scene"
    (scene / "train").mkdir(parents=True)
    frames = []
    for i in range(3):
        frames.append(
            {"file_path": f"./train/r_{i}", "transform_matrix": (_c2w(i, 3) @ np.diag([1, -1, -1, 1])).tolist()}
        )
        cv2.imwrite(str(scene / "train" / f"r_{i}.png"), _photo(i))
    (scene / "transforms_train.json").write_text(json.dumps({"camera_angle_x": 0.8, "frames": frames}))
    return scene


def write_ply(path: Path, rows: np.ndarray, fmt: str = "binary_little_endian", count: int | None = None) -> Path:
    """Write ``rows`` (float properties) as a PLY in ``fmt``; ``count`` overrides the header's vertex count."""
    names = rows.dtype.names
    header = ["ply", f"format {fmt} 1.0", f"element vertex {len(rows) if count is None else count}"]
    header += [f"property float {n}" for n in names] + ["end_header"]
    if fmt == "ascii":
        body = "".join(" ".join(f"{float(v):.9g}" for v in r) + "\n" for r in rows.tolist()).encode()
    else:
        order = ">" if fmt == "binary_big_endian" else "<"
        body = rows.astype([(n, order + "f4") for n in names]).tobytes()
    path.write_bytes(("\n".join(header) + "\n").encode() + body)
    return path


def _valid_rows(run: Path) -> np.ndarray:
    """[N] writable rows of the run's scene.ply (INRIA property names, float32)."""
    from metegs.gaussians.ply import read_ply_vertices

    return np.array(read_ply_vertices(run / "scene.ply"))


def ply_case(mutate: Callable[[np.ndarray], np.ndarray | None] | None = None, **write) -> Callable[[Path], list]:
    """Builder: a trained run and ``scene.ply`` of its Gaussians after ``mutate`` (in place, or returning new rows)."""

    def build(folder: Path) -> list:
        run = trained_run(folder)
        rows = _valid_rows(run)
        changed = mutate(rows) if mutate else None
        return [run, "--ply", write_ply(folder / "scene.ply", rows if changed is None else changed, **write)]

    return build


def ply_bytes(make: Callable[[bytes], bytes]) -> Callable[[Path], list]:
    """Builder: a trained run and ``scene.ply`` whose bytes are ``make(bytes of the run's valid little-endian PLY)``."""

    def build(folder: Path) -> list:
        run = trained_run(folder)
        path = write_ply(folder / "scene.ply", _valid_rows(run))
        path.write_bytes(make(path.read_bytes()))
        return [run, "--ply", path]

    return build


def _set(prop: str, value: float, rows_idx=slice(0, 3)):
    def mutate(rows):
        rows[prop][rows_idx] = value

    return mutate


def _drop(prop: str):
    return lambda rows: rows[[n for n in rows.dtype.names if n != prop]]


def _zero_quaternion(rows: np.ndarray) -> None:
    for i in range(4):
        rows[f"rot_{i}"][4] = 0.0


def _swap_body(raw: bytes) -> bytes:
    """Big-endian float data under the little-endian header."""
    end = raw.index(b"end_header\n") + len(b"end_header\n")
    return raw[:end] + np.frombuffer(raw[end:], "<f4").astype(">f4").tobytes()


def _rendered(result: Result) -> None:
    """Every test view was rendered and is not black."""
    files = sorted((result.folder / "run" / "renders" / "test-render").glob("*.png"))
    assert len(files) == 2, files
    for f in files:
        assert cv2.imread(str(f)).mean() > 20, f"{f.name} is (nearly) black"


def _evaluated(result: Result) -> None:
    """The rewritten PLY scores what the run's own Gaussians scored."""
    got = json.loads((result.folder / "run" / "eval.json").read_text())
    run = json.loads((result.folder / "run" / "metrics.json").read_text())
    assert abs(got["psnr"] - run["psnr"]) < 1e-4 and got["num_gaussians"] == run["num_gaussians"], (got, run)


def _trained(result: Result) -> None:
    metrics = json.loads(next((result.folder / "out").rglob("metrics.json")).read_text())
    assert metrics["steps"] == 4


# --- corruptions -------------------------------------------------------------------------------------


def edit(path_in_scene: str, change: Callable[[bytes], bytes], scene=colmap_scene, **scene_args):
    """Builder: a valid scene, then the bytes of one of its files replaced by ``change(bytes)``."""

    def build(folder: Path) -> list:
        scene_dir = scene(folder, **scene_args)
        path = scene_dir / path_in_scene
        path.write_bytes(change(path.read_bytes()))
        return _train(folder, scene_dir)

    return build


def edit_text(path_in_scene: str, old: str, new: str, scene=colmap_scene, **scene_args):
    """Builder: a valid scene, then the first ``old`` in one of its text files replaced by ``new``."""

    def change(raw: bytes) -> bytes:
        text = raw.decode()
        assert old in text, f"{old!r} not in {path_in_scene}"
        return text.replace(old, new, 1).encode()

    return edit(path_in_scene, change, scene, **scene_args)


def edit_json(change: Callable[[dict], None], scene=nerfstudio_scene, name: str = "transforms.json"):
    """Builder: a valid scene whose JSON file is loaded, changed in place by ``change`` and written back."""

    def rewrite(raw: bytes) -> bytes:
        meta = json.loads(raw)
        change(meta)
        return json.dumps(meta).encode()

    return edit(name, rewrite, scene)


def _data_token(line: int, token: int, value: str) -> Callable[[bytes], bytes]:
    """Set token ``token`` of the ``line``-th non-comment line of a text file to ``value``."""

    def change(raw: bytes) -> bytes:
        lines = raw.decode().split("\n")
        index = [i for i, ln in enumerate(lines) if ln and not ln.startswith("#")][line]
        words = lines[index].split(" ")
        words[token] = value
        lines[index] = " ".join(words)
        return "\n".join(lines).encode()

    return change


def cut(n: int) -> Callable[[bytes], bytes]:
    """Keep the first ``n`` bytes (negative: drop the last ``-n``)."""
    return lambda raw: raw[:n]


def patch(offset: int, fmt: str, value) -> Callable[[bytes], bytes]:
    """Overwrite the little-endian ``fmt`` field at ``offset``."""

    def change(raw: bytes) -> bytes:
        out = bytearray(raw)
        struct.pack_into("<" + fmt, out, offset, value)
        return bytes(out)

    return change


def _huge_npy(raw: bytes) -> bytes:
    """A .npy header claiming [10^9, 17] float64 rows, followed by 3 rows."""
    out = io.BytesIO()
    npy_format.write_array_header_1_0(out, {"descr": "<f8", "fortran_order": False, "shape": (10**9, 17)})
    return out.getvalue() + bytes(3 * 17 * 8)


def _npy_rows(change: Callable[[np.ndarray], np.ndarray]) -> Callable[[bytes], bytes]:
    """Rewrite poses_bounds.npy with ``change(rows)``."""

    def rewrite(raw: bytes) -> bytes:
        out = io.BytesIO()
        np.save(out, change(np.load(io.BytesIO(raw))), allow_pickle=True)
        return out.getvalue()

    return rewrite


def _nan_at(index) -> Callable[[np.ndarray], np.ndarray]:
    def change(rows):
        rows[index] = np.nan
        return rows

    return change


def _other_size(raw: bytes) -> bytes:
    return cv2.imencode(".png", np.zeros((H, W + 4, 3), np.uint8))[1].tobytes()


def _with_depths(folder: Path) -> Path:
    scene = nerfstudio_scene(folder)
    meta = json.loads((scene / "transforms.json").read_text())
    for i, frame in enumerate(meta["frames"]):
        frame["depth_file_path"] = f"depth_{i}.npy"
        np.save(scene / f"depth_{i}.npy", np.ones((H, W), np.float32))
    (scene / "transforms.json").write_text(json.dumps(meta))
    return scene


def _with_points(folder: Path) -> Path:
    scene = nerfstudio_scene(folder, ply_file_path="points.ply")
    rows = np.rec.fromarrays(np.random.default_rng(0).normal(size=(3, 20)).astype(np.float32), names="x,y,z")
    write_ply(scene / "points.ply", rows.view(np.ndarray))
    return scene


def _without(path_in_scene: str) -> Callable[[Path], list]:
    """Builder: a valid COLMAP scene without one of its files."""

    def build(folder: Path) -> list:
        scene = colmap_scene(folder)
        (scene / path_in_scene).unlink()
        return _train(folder, scene)

    return build


def _missing_image(folder: Path) -> list:
    scene = nerfstudio_scene(folder)
    (scene / "images" / "frame_2.png").unlink()
    return _train(folder, scene)


def _skipped_one(result: Result) -> None:
    """Trained on the 3 frames that have an image (the warning naming the 4th goes to the warnings system)."""
    assert "(2 train / 1 test views" in " ".join(result.stderr.split()), result.stderr
    _trained(result)


BIN, TXT, IMG = "sparse/0/{}.bin", "sparse/0/{}.txt", "images/frame_{}"
# images.bin of colmap_scene: 8-byte count, then 3 records of 178 bytes (id, pose, camera, "img_i.png\0", 4 2D points)
# points3D.bin: 8-byte count, then 4 records of 75 bytes (43 fixed, track length, 3 track elements)

CASES = [
    # COLMAP binary files, truncated at several points, with corrupt counts and fields
    Case("colmap-cameras-bin-empty", "metegs-train", edit(BIN.format("cameras"), cut(0)), "clear", match=r"cameras\.bin: empty file"),
    Case("colmap-cameras-bin-cut-count", "metegs-train", edit(BIN.format("cameras"), cut(5)), "clear", match=r"cameras\.bin: the number of cameras runs past the end"),
    Case("colmap-cameras-bin-cut-params", "metegs-train", edit(BIN.format("cameras"), cut(-8)), "clear", match=r"cameras\.bin: camera 1: the PINHOLE parameters: 4 x 8 bytes run past the end"),
    Case("colmap-cameras-bin-model-id", "metegs-train", edit(BIN.format("cameras"), patch(12, "i", 99)), "clear", match=r"cameras\.bin: camera 1: unknown camera model id 99"),
    Case("colmap-cameras-bin-count-inflated", "metegs-train", edit(BIN.format("cameras"), patch(0, "Q", 1 << 50)), "clear", match=r"cameras\.bin: the number of cameras is 1125899906842624, impossible"),
    Case("colmap-images-bin-cut-header", "metegs-train", edit(BIN.format("images"), cut(38)), "clear", match=r"images\.bin: the number of images is 3, impossible"),
    Case("colmap-images-bin-cut-record", "metegs-train", edit(BIN.format("images"), cut(394)), "clear", match=r"images\.bin: image 3 of 3 runs past the end"),
    Case("colmap-images-bin-cut-name", "metegs-train", edit(BIN.format("images"), cut(432)), "clear", match=r"images\.bin: image 3: the name has no terminating NUL"),
    Case("colmap-images-bin-cut-points2d", "metegs-train", edit(BIN.format("images"), cut(-30)), "clear", match=r"images\.bin: image 3 \(img_2\.png\): the 2D points: 4 x 24 bytes run past"),
    Case("colmap-images-bin-count-inflated", "metegs-train", edit(BIN.format("images"), patch(0, "Q", 1 << 40)), "clear", match=r"images\.bin: the number of images is 1099511627776, impossible"),
    Case("colmap-images-bin-points2d-inflated", "metegs-train", edit(BIN.format("images"), patch(8 + 74, "Q", 1 << 40)), "clear", match=r"images\.bin: image 1 \(img_0\.png\): the 2D points: 1099511627776 x 24 bytes run past"),
    Case("colmap-images-bin-nan-pose", "metegs-train", edit(BIN.format("images"), patch(12, "d", float("nan"))), "clear", match=r"images\.bin: image 1: the pose \(qvec, tvec\) is not finite"),
    Case("colmap-points3d-bin-empty", "metegs-train", edit(BIN.format("points3D"), cut(0)), "clear", match=r"points3D\.bin: empty file"),
    Case("colmap-points3d-bin-60kb", "metegs-train", edit(BIN.format("points3D"), cut(60000), n_points=1500), "clear", match=r"points3D\.bin: the number of points is 1500, impossible.*the file has 60000 bytes"),
    Case("colmap-points3d-bin-cut-record", "metegs-train", edit(BIN.format("points3D"), cut(263)), "clear", match=r"points3D\.bin: point 4 of 4 runs past the end"),
    Case("colmap-points3d-bin-cut-track", "metegs-train", edit(BIN.format("points3D"), cut(-1)), "clear", match=r"points3D\.bin: point 4 of 4: the track of 3 observations runs past"),
    Case("colmap-points3d-bin-count-inflated", "metegs-train", edit(BIN.format("points3D"), patch(0, "Q", 10**12)), "clear", match=r"points3D\.bin: the number of points is 1000000000000, impossible"),
    Case("colmap-points3d-bin-track-inflated", "metegs-train", edit(BIN.format("points3D"), patch(8 + 43, "Q", 1 << 40)), "clear", match=r"points3D\.bin: point 1 of 4: the track of 1099511627776 observations runs past"),
    Case("colmap-points3d-bin-count-deflated", "metegs-train", edit(BIN.format("points3D"), patch(0, "Q", 3)), "clear", match=r"points3D\.bin: 75 bytes follow the last of the 3 points"),
    Case("colmap-points3d-bin-inf-xyz", "metegs-train", edit(BIN.format("points3D"), patch(16, "d", float("inf"))), "clear", match=r"points3D\.bin: 1 of 4 points have a non-finite position"),
    Case("colmap-rigs-bin-cut", "metegs-train", edit(BIN.format("rigs"), cut(-4)), "clear", match=r"rigs\.bin: .*(past the end|impossible)"),
    Case("colmap-frames-bin-cut", "metegs-train", edit(BIN.format("frames"), cut(-10)), "clear", match=r"frames\.bin: frame 3: the data ids: 1 x 16 bytes run past"),
    Case("colmap-points3d-bin-missing", "metegs-train", _without(BIN.format("points3D")), "clear", match=r"sparse/0: incomplete COLMAP model: found cameras\.bin, images\.bin, expected"),
    Case("colmap-bin-valid-trains", "metegs-train", lambda f: _train(f, colmap_scene(f)), "correct", check=_trained),
    # COLMAP text files: the malformed line is named
    Case("colmap-cameras-txt-param-count", "metegs-train", edit_text(TXT.format("cameras"), "30 30 16 12", "30 30 16", text=True), "clear", match=r"cameras\.txt: line 4: model PINHOLE has 4 parameters, the line has 3"),
    Case("colmap-cameras-txt-unknown-model", "metegs-train", edit_text(TXT.format("cameras"), "PINHOLE", "PINHOLX", text=True), "clear", match=r"cameras\.txt: line 4: expected CAMERA_ID MODEL"),
    Case("colmap-images-txt-nan-pose", "metegs-train", edit(TXT.format("images"), _data_token(0, 1, "nan"), text=True), "clear", match=r"images\.txt: line 5: the pose QW QX QY QZ TX TY TZ must be finite"),
    Case("colmap-images-txt-no-name", "metegs-train", edit_text(TXT.format("images"), " 1 img_0.png", " 1", text=True), "clear", match=r"images\.txt: line 5: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME"),
    Case("colmap-images-txt-bad-points2d", "metegs-train", edit_text(TXT.format("images"), "img_0.png\n5 6 1", "img_0.png\n5 6", text=True), "clear", match=r"images\.txt: line 6: expected POINTS2D\[\] as \(X, Y, POINT3D_ID\) triples, got 11 values"),
    Case("colmap-points3d-txt-not-number", "metegs-train", edit(TXT.format("points3D"), _data_token(0, 2, "zero"), text=True), "clear", match=r"points3D\.txt: line 4: X Y Z and ERROR must be numbers, got '.* zero "),
    Case("colmap-points3d-txt-rgb", "metegs-train", edit_text(TXT.format("points3D"), " 200 120 40 ", " 200 999 40 ", text=True), "clear", match=r"points3D\.txt: line 4: R G B must be in 0\.\.255"),
    Case("colmap-points3d-txt-odd-track", "metegs-train", edit_text(TXT.format("points3D"), " 1 0 2 0 3 0", " 1 0 2 0 3", text=True), "clear", match=r"points3D\.txt: line 4: expected POINT3D_ID X Y Z R G B ERROR TRACK"),
    Case("colmap-txt-valid-trains", "metegs-train", lambda f: _train(f, colmap_scene(f, text=True)), "correct", check=_trained),
    # PLY Gaussians for metegs-render / metegs-eval --ply
    Case("ply-huge-count", "metegs-render", ply_case(count=10**9), "clear", match=r"scene\.ply: PLY data truncated: the header declares 1000000000 vertices of \d+ bytes \(\d+ bytes\) but the file holds \d+ bytes"),
    Case("ply-truncated-body", "metegs-render", ply_bytes(cut(-50)), "clear", match=r"scene\.ply: PLY data truncated"),
    Case("ply-empty-file", "metegs-render", ply_bytes(cut(0)), "clear", match=r"scene\.ply: not a PLY file"),
    Case("ply-not-a-ply", "metegs-render", ply_bytes(lambda raw: b"\x89PNG\r\n\x1a\n" + raw), "clear", match=r"scene\.ply: not a PLY file"),
    Case("ply-no-end-header", "metegs-render", ply_bytes(lambda raw: raw[: raw.index(b"end_header\n")]), "clear", match=r"scene\.ply: PLY header has no 'end_header' line"),
    Case("ply-zero-vertices", "metegs-render", ply_case(lambda rows: rows[:0]), "clear", match=r"scene\.ply: the PLY holds no Gaussians"),
    Case("ply-missing-opacity", "metegs-render", ply_case(_drop("opacity")), "clear", match=r"scene\.ply: .*missing required propert.*opacity"),
    Case("ply-unknown-type", "metegs-render", ply_bytes(lambda raw: raw.replace(b"property float opacity", b"property quad opacity")), "clear", match=r"scene\.ply: unsupported PLY property line 'property quad opacity'"),
    Case("ply-nan-x", "metegs-render", ply_case(_set("x", np.nan)), "clear", match=r"scene\.ply: property 'x' is NaN or infinite in 3 of \d+ vertices"),
    Case("ply-nan-opacity", "metegs-render", ply_case(_set("opacity", np.nan)), "clear", match=r"scene\.ply: property 'opacity' is NaN or infinite in 3 of"),
    Case("ply-inf-scale", "metegs-render", ply_case(_set("scale_1", np.inf)), "clear", match=r"scene\.ply: property 'scale_1' is NaN or infinite in 3 of"),
    Case("ply-nan-rot", "metegs-render", ply_case(_set("rot_2", np.nan, 7)), "clear", match=r"scene\.ply: property 'rot_2' is NaN or infinite in 1 of"),
    Case("ply-nan-colour", "metegs-render", ply_case(_set("f_dc_0", np.nan)), "clear", match=r"scene\.ply: property 'f_dc_0' is NaN or infinite"),
    Case("ply-inf-sh-rest", "metegs-render", ply_case(_set("f_rest_5", -np.inf)), "clear", match=r"scene\.ply: property 'f_rest_5' is NaN or infinite"),
    Case("ply-absurd-scale", "metegs-render", ply_case(_set("scale_0", 25.0, 0)), "clear", match=r"scene\.ply: property 'scale_0' \(log standard deviation\) is above 20 in 1 of \d+ vertices \(max 25\)"),
    Case("ply-zero-quaternion", "metegs-render", ply_case(_zero_quaternion), "clear", match=r"scene\.ply: properties 'rot_0'\.\.'rot_3' are a zero quaternion in 1 of"),
    Case("ply-big-endian-data-little-endian-header", "metegs-render", ply_bytes(_swap_body), "clear", match=r"scene\.ply: .*byte order"),
    Case("ply-nan-eval", "metegs-eval", ply_case(_set("y", np.nan)), "clear", match=r"scene\.ply: property 'y' is NaN or infinite"),
    Case("ply-missing-file", "metegs-render", lambda f: [trained_run(f), "--ply", f / "nope.ply"], "clear", match=r"nope\.ply: PLY file not found"),
    Case("ply-big-endian-renders", "metegs-render", ply_case(fmt="binary_big_endian"), "correct", check=_rendered),
    Case("ply-ascii-renders", "metegs-render", ply_case(fmt="ascii"), "correct", check=_rendered),
    Case("ply-big-endian-evaluates", "metegs-eval", ply_case(fmt="binary_big_endian"), "correct", check=_evaluated),
    # images: truncated, empty, not an image, another size, missing
    Case("image-truncated-jpeg", "metegs-train", edit(IMG.format("1.jpg"), cut(-40), nerfstudio_scene, suffix=".jpg"), "clear", match=r"images/frame_1\.jpg: JPEG data is truncated"),
    Case("image-truncated-png", "metegs-train", edit(IMG.format("2.png"), cut(-20), nerfstudio_scene), "clear", match=r"images/frame_2\.png: PNG data is truncated"),
    Case("image-zero-bytes", "metegs-train", edit(IMG.format("0.png"), cut(0), nerfstudio_scene), "clear", match=r"images/frame_0\.png: empty file \(0 bytes\)"),
    Case("image-not-an-image", "metegs-train", edit(IMG.format("3.jpg"), lambda raw: b"hello, not a photo\n", nerfstudio_scene, suffix=".jpg"), "clear", match=r"images/frame_3\.jpg: cannot read image"),
    Case("image-other-size", "metegs-train", edit(IMG.format("1.png"), _other_size, nerfstudio_scene), "clear", match=r"images/frame_1\.png: image is 36x24 but its camera \(view 1, images/frame_1\.png\) is 32x24"),
    Case("image-truncated-colmap", "metegs-train", edit("images/img_1.png", cut(-30)), "clear", match=r"images/img_1\.png: PNG data is truncated"),
    Case("image-truncated-llff", "metegs-train", edit("images/im_0.png", cut(100), llff_scene), "clear", match=r"images/im_0\.png: PNG data is truncated"),
    Case("image-jpeg-zero-padding-trains", "metegs-train", edit(IMG.format("1.jpg"), lambda raw: raw + bytes(256), nerfstudio_scene, suffix=".jpg"), "correct", check=_trained),
    Case("image-missing-one-skipped", "metegs-train", _missing_image, "correct", check=_skipped_one),
    # LLFF poses_bounds.npy
    Case("llff-wrong-shape", "metegs-train", edit("poses_bounds.npy", _npy_rows(lambda r: r[:, :15]), llff_scene), "clear", match=r"poses_bounds\.npy: expected an array of shape \[N, 17\], got \[3, 15\]"),
    Case("llff-nan", "metegs-train", edit("poses_bounds.npy", _npy_rows(_nan_at((1, 7))), llff_scene), "clear", match=r"poses_bounds\.npy: contains non-finite values"),
    Case("llff-not-npy", "metegs-train", edit("poses_bounds.npy", lambda raw: b"0 0 0\n", llff_scene), "clear", match=r"poses_bounds\.npy: the poses and bounds file is not a \.npy array"),
    Case("llff-huge-header", "metegs-train", edit("poses_bounds.npy", _huge_npy, llff_scene), "clear", match=r"poses_bounds\.npy: cannot read the poses and bounds \(truncated"),
    Case("llff-truncated", "metegs-train", edit("poses_bounds.npy", cut(-9), llff_scene), "clear", match=r"poses_bounds\.npy: cannot read the poses and bounds \(truncated"),
    Case("llff-pickled", "metegs-train", edit("poses_bounds.npy", _npy_rows(lambda r: np.array([{"pose": 1}] * 3, dtype=object)), llff_scene), "clear", match=r"poses_bounds\.npy: cannot read the poses and bounds"),
    Case("llff-negative-focal", "metegs-train", edit("poses_bounds.npy", _npy_rows(lambda r: r * np.r_[np.ones(14), -1, 1, 1]), llff_scene), "clear", match=r"poses_bounds\.npy: H, W and focal .* must be positive"),
    Case("llff-count-mismatch", "metegs-train", edit("poses_bounds.npy", _npy_rows(lambda r: r[:2]), llff_scene), "clear", match=r"images: 3 images found but poses_bounds\.npy has 2 poses"),
    # nerfstudio transforms.json
    Case("nerfstudio-not-json", "metegs-train", edit("transforms.json", cut(-5), nerfstudio_scene), "clear", match=r"transforms\.json: cannot parse JSON"),
    Case("nerfstudio-top-level-list", "metegs-train", edit("transforms.json", lambda raw: b"[1, 2]", nerfstudio_scene), "clear", match=r"transforms\.json: expected a JSON object"),
    Case("nerfstudio-nan-matrix", "metegs-train", edit_json(lambda m: m["frames"][1]["transform_matrix"][0].__setitem__(3, float("nan"))), "clear", match=r"transforms\.json: frame 1 has a malformed 'transform_matrix'"),
    Case("nerfstudio-no-frames", "metegs-train", edit_json(lambda m: m.pop("frames")), "clear", match=r"transforms\.json: missing or empty 'frames' list"),
    Case("nerfstudio-no-file-path", "metegs-train", edit_json(lambda m: m["frames"][0].pop("file_path")), "clear", match=r"transforms\.json: frame 0 has no 'file_path'"),
    Case("nerfstudio-nan-intrinsic", "metegs-train", edit_json(lambda m: m.__setitem__("fl_x", float("nan"))), "clear", match=r"transforms\.json: frame 0: intrinsic 'fl_x' must be a finite number"),
    Case("nerfstudio-string-distortion", "metegs-train", edit_json(lambda m: m.__setitem__("k1", "small")), "clear", match=r"transforms\.json: the top level: 'k1' must be a finite number, got 'small'"),
    Case("nerfstudio-string-metric-scale", "metegs-train", edit_json(lambda m: m.__setitem__("metegs", {"metric_scale": "far"})), "clear", match=r"transforms\.json: metegs\.metric_scale must be a finite number"),
    Case("nerfstudio-split-not-a-list", "metegs-train", edit_json(lambda m: m.__setitem__("train_filenames", 7)), "clear", match=r"transforms\.json: 'train_filenames' must be a list of image paths, got 7"),
    Case("nerfstudio-split-matches-nothing", "metegs-train", edit_json(lambda m: m.__setitem__("train_filenames", ["x.png"])), "clear", match=r"transforms\.json: none of the 'train_filenames' is the file_path of a frame"),
    Case("nerfstudio-all-images-missing", "metegs-train", edit_json(lambda m: [f.__setitem__("file_path", "gone.png") for f in m["frames"]]), "clear", match=r"transforms\.json: no images found"),
    Case("nerfstudio-depth-truncated", "metegs-train", edit("depth_1.npy", cut(-100), _with_depths), "clear", match=r"depth_1\.npy: cannot read the depth map \(truncated"),
    Case("nerfstudio-points-huge-count", "metegs-train", edit("points.ply", lambda raw: raw.replace(b"vertex 20\n", b"vertex 2000000000\n"), _with_points), "clear", match=r"points\.ply: PLY data truncated: the header declares 2000000000 vertices"),
    Case("nerfstudio-points-nan", "metegs-train", edit("points.ply", patch(-4, "f", float("nan")), _with_points), "clear", match=r"points\.ply: property 'z' is NaN or infinite in 1 of 20 vertices"),
    # Blender transforms_train.json
    Case("blender-not-json", "metegs-train", edit("transforms_train.json", lambda raw: b"{camera_angle_x: 0.8", blender_scene), "clear", match=r"transforms_train\.json: cannot parse JSON"),
    Case("blender-angle-string", "metegs-train", edit_json(lambda m: m.__setitem__("camera_angle_x", "wide"), blender_scene, "transforms_train.json"), "clear", match=r"transforms_train\.json: 'camera_angle_x' must be a finite number, got 'wide'"),
    Case("blender-width-string", "metegs-train", edit_json(lambda m: m.update(w="big", h=24), blender_scene, "transforms_train.json"), "clear", match=r"transforms_train\.json: 'w' must be a finite number, got 'big'"),
    Case("blender-truncated-png", "metegs-train", edit("train/r_1.png", cut(60), blender_scene), "clear", match=r"train/r_1\.png: PNG data is truncated"),
]  # fmt: skip
