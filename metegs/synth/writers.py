"""Write a degraded copy of a dataset in its own format, with the clean images alongside, atomically.

Layouts (the clean reference of ``<folder>/<file>`` is ``<folder>_clean/<file>``, see
`metegs.data.parsers.clean`, so that every parser exposes it as ``SceneData.clean_image_paths``):

- ``llff``: ``poses_bounds.npy``, the image folder the parser read (e.g. ``images_8/``) with the degraded
  images under their own names, its masks folder, the top-level files (licence, readme) copied;
- ``nerfstudio`` / ``blender``: the transforms file(s), point cloud and frames' masks copied, degraded images at the
  frames' paths;
- ``colmap``: the ``sparse/`` model copied, degraded images in ``images/``;
- the synthetic scene (in memory): a nerfstudio dataset, ``transforms.json`` (its split, the points in
  ``points.ply``), ``images/view_NNN.png``, exact depth maps ``depths/view_NNN.npy`` (float32 z-depth, m);
- a scene whose photos metegs read through undistorted copies (COLMAP or nerfstudio frames with lens
  distortion): the same PINHOLE nerfstudio layout, as the views were trained on (undistorted PNGs, the
  undistorted cameras and masks), since a mirror of the distorted originals would need the weather distorted too.

The points of every layout (the COLMAP model's, a point cloud file, the synthetic scene's) keep their positions
but take their colours from the degraded photos (`metegs.data.point_colours`): a copy carries nothing of the
clean photos but the clean references beside them.

Everything is built in a hidden temp folder next to the output and renamed into place at the end: an
interrupted run leaves no half-written dataset.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path, PurePosixPath

import cv2
import numpy as np

from metegs.cameras import Cameras, opencv_to_opengl
from metegs.config import user_cache
from metegs.data.parsers.clean import clean_relative_path
from metegs.data.scene import SceneData
from metegs.errors import ConfigError, DataError

JPEG_QUALITY = 95
"""Quality of degraded JPEG images (the format of the source is kept)."""


def encode_image(image: np.ndarray, suffix: str) -> bytes:
    """8-bit encoding of a float RGB image [H, W, 3] in [0, 1] (PNG, or JPEG at ``JPEG_QUALITY``)."""
    arr = (np.clip(np.asarray(image, dtype=np.float32), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    suffix = suffix.lower() or ".png"
    params = [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY] if suffix in (".jpg", ".jpeg") else []
    ok, buf = cv2.imencode(suffix, cv2.cvtColor(arr, cv2.COLOR_RGB2BGR), params)
    if not ok:
        raise DataError(None, f"cannot encode an image as {suffix}")
    return buf.tobytes()


def scene_root(scene: SceneData) -> Path | None:
    """The folder ``scene`` was read from (its source, or the folder of its source file), or None in memory."""
    if scene.source is None:
        return None
    src = Path(scene.source)
    return src.parent if src.is_file() else src


def reads_cached_copies(scene: SceneData) -> bool:
    """Whether ``scene``'s views were read from metegs's cached copies of its photos (undistorted views in a hidden
    folder of the scene or in the user's cache) rather than from the photos themselves."""
    if scene.source is None or scene.image_paths is None:
        return False
    root = scene_root(scene).resolve()
    cache = user_cache().resolve()
    for path in scene.image_paths:
        p = Path(path).resolve()
        if p.is_relative_to(cache):
            return True
        if p.is_relative_to(root) and any(part.startswith(".") for part in p.relative_to(root).parts[:-1]):
            return True
    return False


class DatasetWriter:
    """Writes the views and the metadata of a degraded copy of ``scene`` into ``root`` (the staging folder)."""

    def __init__(self, scene: SceneData, root: Path):
        self.scene, self.root = scene, Path(root)
        self.from_memory = scene.source is None or scene.parser in ("synthetic", "") or reads_cached_copies(scene)
        """Written from the views and cameras as metegs holds them (PINHOLE nerfstudio), not as a mirror."""
        self.format = "nerfstudio" if self.from_memory else scene.parser
        if self.format not in ("llff", "nerfstudio", "blender", "colmap"):
            raise ConfigError(
                f"cannot write a degraded copy of a {self.format!r} dataset (llff, nerfstudio, blender, colmap)"
            )
        self.source_root = scene_root(scene)
        self.image_rel = [self._image_rel(i) for i in range(len(scene))]
        """Path of each view's image in the output, relative to it."""
        if len(set(self.image_rel)) < len(self.image_rel):  # photos of one name in several folders
            self.image_rel = [f"images/{i:05d}_{Path(r).name}" for i, r in enumerate(self.image_rel)]
        self.clean_rel = [str(clean_relative_path(r)) for r in self.image_rel]

    # --- where things go ----------------------------------------------------------------------------------
    def _image_rel(self, i: int) -> str:
        if self.from_memory:
            return f"images/{Path(self.scene.names[i]).stem}.png"
        if self.scene.image_paths is None:
            raise DataError(self.scene.source, "the scene has no image files to mirror")
        p = Path(self.scene.image_paths[i])
        try:
            rel = p.relative_to(self.source_root)
        except ValueError:
            raise DataError(p, f"image lies outside the scene folder {self.source_root}; cannot mirror it") from None
        if rel.parts[0].startswith("."):
            raise DataError(
                p,
                "image is a cached copy (e.g. undistorted COLMAP view); undistort the scene first "
                "(COLMAP image_undistorter) and degrade that",
            )
        return PurePosixPath(rel.as_posix()).as_posix()

    # --- writing ------------------------------------------------------------------------------------------
    def write_view(self, i: int, degraded: np.ndarray, clean: np.ndarray) -> None:
        """The degraded image of view ``i`` at its path and its clean reference next to it (the source file
        itself when the view was read from one)."""
        suffix = Path(self.image_rel[i]).suffix
        for rel, image in ((self.image_rel[i], degraded), (self.clean_rel[i], clean)):
            path = self.root / rel
            path.parent.mkdir(parents=True, exist_ok=True)
            if image is clean and self.scene.image_paths is not None and Path(self.scene.image_paths[i]).is_file():
                shutil.copyfile(self.scene.image_paths[i], path)  # the original file, not a re-encoding
            else:
                path.write_bytes(encode_image(image, suffix))

    def finish(self, depths: list[np.ndarray] | None = None) -> None:
        """Format metadata (poses, transforms, model) and companion files."""
        if self.from_memory:
            self._write_nerfstudio_from_memory(depths)
            return
        src = self.source_root
        for item in sorted(src.iterdir()):  # top-level files: poses, transforms, licence, readme, ...
            if item.is_file() and not item.name.startswith("."):
                shutil.copy2(item, self.root / item.name)
        if self.format == "llff":
            image_dir = Path(self.image_rel[0]).parts[0]
            masks = src / image_dir.replace("images", "masks", 1)
            if masks.is_dir():
                shutil.copytree(masks, self.root / masks.name)
        elif self.format == "colmap":
            if (src / "sparse").is_dir():
                shutil.copytree(src / "sparse", self.root / "sparse")
                self._recolour_colmap(self.root / "sparse")
        elif self.format == "nerfstudio":
            meta = json.loads(
                (self.scene.source if Path(self.scene.source).is_file() else src / "transforms.json").read_text()
            )
            masks = [f.get("mask_path") for f in meta.get("frames", []) if isinstance(f, dict)]
            for rel in [meta.get("ply_file_path"), *masks]:  # the points and each frame's mask, where they exist
                if isinstance(rel, str) and rel and (src / rel).is_file() and not (self.root / rel).exists():
                    (self.root / rel).parent.mkdir(parents=True, exist_ok=True)
                    shutil.copy2(src / rel, self.root / rel)
            if isinstance(meta.get("ply_file_path"), str) and (self.root / meta["ply_file_path"]).is_file():
                self._recolour_ply(self.root / meta["ply_file_path"])

    def _degraded_images(self) -> list[np.ndarray]:
        """[H, W, 3] float32 in [0, 1]: every view's degraded image as written."""
        from metegs.data.images import load_image

        return [load_image(self.root / rel) for rel in self.image_rel]

    def _recolour_colmap(self, sparse: Path) -> None:
        """Every COLMAP model under ``sparse`` coloured from the degraded images (`recolour_colmap_model`)."""
        from metegs.data.point_colours import recolour_colmap_model

        written = {PurePosixPath(*PurePosixPath(r).parts[1:]).as_posix(): self.root / r for r in self.image_rel}
        for points in sorted(sparse.rglob("points3D.*")):
            if points.suffix in (".bin", ".txt"):
                recolour_colmap_model(points.parent, written.get)

    def _recolour_ply(self, path: Path) -> None:
        """The copied point cloud ``path`` coloured from the degraded images, where it holds the scene's points (in
        their order; the file's own positions and frame are kept)."""
        from metegs.data.parsers.nerfstudio import read_ply_points
        from metegs.data.point_colours import colours_seen

        points, _ = read_ply_points(path)
        if self.scene.points is None or len(points) != len(self.scene.points):
            return
        colours = colours_seen(self.scene.points, self.scene.cameras, self._degraded_images())
        write_ply_points(path, points, colours)

    def _write_nerfstudio_from_memory(self, depths: list[np.ndarray] | None) -> None:
        scene = self.scene
        cams = scene.cameras
        frames = []
        for i, frame in enumerate(pinhole_frames(cams, self.image_rel)):
            if depths is not None:
                rel = f"depths/{Path(self.image_rel[i]).stem}.npy"
                path = self.root / rel
                path.parent.mkdir(parents=True, exist_ok=True)
                np.save(path, np.asarray(depths[i], dtype=np.float32), allow_pickle=False)
                frame["depth_file_path"] = rel
            if scene.mask_paths is not None:  # the (undistorted) masks beside the views they belong to
                src = Path(scene.mask_paths[i])
                rel = f"masks/{Path(self.image_rel[i]).stem}{src.suffix}"
                (self.root / "masks").mkdir(exist_ok=True)
                shutil.copy2(src, self.root / rel)
                frame["mask_path"] = rel
            frames.append(frame)
        meta = {
            "camera_model": "PINHOLE",
            "frames": frames,
            "train_filenames": [self.image_rel[i] for i in scene.train_indices],
            "test_filenames": [self.image_rel[i] for i in scene.test_indices],
            "metegs": {
                "source": "synthetic scene"
                if scene.parser == "synthetic"
                else f"{scene.parser} scene {scene.source}, undistorted"
                if scene.source is not None
                else scene.parser or "in-memory scene",
                "metric_scale": scene.metric_scale,
                "up": [float(x) for x in np.asarray(scene.up).reshape(-1)],
                "exposure_time_s": None
                if cams.exposure_time_s is None
                else [float(x) for x in cams.exposure_time_s.tolist()],
                "image_space": scene.image_space,
                "rendered": scene.rendered,
            },
        }
        if scene.points is not None and len(scene.points):
            from metegs.data.point_colours import colours_seen

            colours = colours_seen(scene.points, cams, self._degraded_images(), depths)
            write_ply_points(self.root / "points.ply", scene.points, colours)
            meta["ply_file_path"] = "points.ply"
        (self.root / "transforms.json").write_text(json.dumps(meta, indent=1) + "\n")


def pinhole_frames(cameras: Cameras, files: list[str]) -> list[dict]:
    """One nerfstudio frame per view of ``cameras`` (OpenCV convention, as metegs holds them): ``files[i]`` as its
    image, the camera-to-world in OpenGL camera axes and the PINHOLE intrinsics of its size."""
    c2w_gl = opencv_to_opengl(cameras.camera_to_worlds.double()).numpy()
    return [
        {
            "file_path": file,
            "transform_matrix": [[float(x) for x in row] for row in c2w_gl[i]],
            "fl_x": float(cameras.fx[i]),
            "fl_y": float(cameras.fy[i]),
            "cx": float(cameras.cx[i]),
            "cy": float(cameras.cy[i]),
            "w": int(cameras.width[i]),
            "h": int(cameras.height[i]),
        }
        for i, file in enumerate(files)
    ]


def write_ply_points(path: Path, points: np.ndarray, colors: np.ndarray | None) -> None:
    """Binary little-endian PLY of points [P, 3] (and colours [P, 3] in [0, 1] as uchar)."""
    pts = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if colors is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    data = np.empty(len(pts), dtype=np.dtype(fields))
    data["x"], data["y"], data["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    if colors is not None:
        rgb = (np.clip(np.asarray(colors, dtype=np.float32).reshape(-1, 3), 0, 1) * 255 + 0.5).astype(np.uint8)
        data["red"], data["green"], data["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(pts)}"]
    header += [f"property {'float' if t == '<f4' else 'uchar'} {n}" for n, t in fields]
    header.append("end_header")
    path.write_bytes(("\n".join(header) + "\n").encode("ascii") + data.tobytes())
