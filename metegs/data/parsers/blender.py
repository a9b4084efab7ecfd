"""Blender / NeRF-synthetic scenes: ``transforms_{train,val,test}.json``.

Each file holds ``camera_angle_x`` (horizontal field of view, radians) and ``frames`` with ``file_path``
(without extension: ``.png`` is appended) and an OpenGL camera-to-world ``transform_matrix``. The focal
length is ``0.5 * W / tan(0.5 * camera_angle_x)`` for square pixels, with W, H from the optional ``w``/``h``
keys or else the first image; the principal point is the image centre. Views come from the train file
(training) and the test file (testing; the val file is used for testing when there is no test file).
The images are RGBA: `metegs.data.images.load_image` composites them on a white background. Clean references
(as `metegs-synth` writes them) come from the sibling folders ``train_clean/``, ``test_clean/``...
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import ClassVar

import numpy as np

from metegs.cameras import Cameras
from metegs.data.config import DatasetConfig
from metegs.data.images import image_size
from metegs.data.parsers.clean import find_clean_paths
from metegs.data.parsers.nerfstudio import gl_matrix, gl_to_cv, number, read_json, warn_missing
from metegs.data.scene import SceneData
from metegs.errors import DataError


def frame_path(root: Path, file_path: str) -> Path:
    """Image file of a frame: ``file_path`` relative to ``root``, ``.png`` appended when it has no suffix."""
    p = root / str(file_path)
    return p if p.suffix else p.with_name(p.name + ".png")


class BlenderParser:
    """NeRF-synthetic ``transforms_{train,val,test}.json`` -> SceneData (see the module docstring)."""

    priority: ClassVar[int] = 15

    @staticmethod
    def can_parse(path: Path) -> bool:
        return (Path(path) / "transforms_train.json").is_file()

    def parse(self, path: Path | None, options: DatasetConfig) -> SceneData:
        if path is None:
            raise DataError(None, "the blender parser needs a scene folder")
        path = Path(path)
        splits = {"train": path / "transforms_train.json"}
        test_file = path / "transforms_test.json"
        splits["test"] = test_file if test_file.is_file() else path / "transforms_val.json"
        views, missing = [], []
        for split, source in splits.items():
            if split == "train" or source.is_file():
                found, lost = self._read_split(source, path)
                views += [(split, *v) for v in found]
                missing += lost
        if missing:
            warn_missing(path, missing)
        if not views:
            raise DataError(path, "no images found: none of the frame image files exist")
        width, height, focal = self._intrinsics(views, path)
        c2w = gl_to_cv(np.stack([v[3] for v in views]))
        cams = Cameras.create(c2w, focal, focal, width / 2.0, height / 2.0, width, height)
        return SceneData(
            cameras=cams,
            names=[v[1] for v in views],
            image_paths=[v[2] for v in views],
            clean_image_paths=find_clean_paths(path, [v[2] for v in views]),
            train_indices=[i for i, v in enumerate(views) if v[0] == "train"],
            test_indices=[i for i, v in enumerate(views) if v[0] == "test"],
            source=path,
            rendered=True,
        )

    @staticmethod
    def _read_split(source: Path, root: Path) -> tuple[list, list[str]]:
        """([(name, image path, GL c2w [4, 4], angle_x, meta)], missing names) of one transforms file."""
        meta = read_json(source)
        if "camera_angle_x" not in meta:
            raise DataError(source, "missing 'camera_angle_x'")
        angle_x = number(meta["camera_angle_x"], source, "'camera_angle_x'")
        frames = meta.get("frames")
        if not isinstance(frames, list):
            raise DataError(source, "missing 'frames' list")
        found, missing = [], []
        for i, frame in enumerate(frames):
            if not isinstance(frame, dict) or "file_path" not in frame:
                raise DataError(source, f"frame {i} has no 'file_path'")
            if "transform_matrix" not in frame:
                raise DataError(source, f"frame {i} has no 'transform_matrix'")
            image = frame_path(root, frame["file_path"])
            name = image.relative_to(root).as_posix() if image.is_relative_to(root) else str(image)
            if not image.is_file():
                missing.append(name)
                continue
            c2w = gl_matrix(frame["transform_matrix"], source, f"frame {i}")
            found.append((name, image, c2w, (angle_x, meta, source)))
        return found, missing

    @staticmethod
    def _intrinsics(views: list, root: Path) -> tuple[int, int, list[float]]:
        """(width, height, per-view focal) from the first image (or ``w``/``h``) and each ``camera_angle_x``."""
        _, meta, source = views[0][4]
        if "w" in meta and "h" in meta:
            width, height = int(number(meta["w"], source, "'w'")), int(number(meta["h"], source, "'h'"))
        else:
            width, height = image_size(views[0][2])
        focals = []
        for *_, (angle_x, _, source) in views:
            if not 0.0 < angle_x < math.pi:
                raise DataError(source, f"camera_angle_x must be in (0, pi) radians, got {angle_x}")
            focals.append(0.5 * width / math.tan(0.5 * angle_x))
        return width, height, focals
