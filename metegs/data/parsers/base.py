"""The `DataParser` protocol, format detection and the single entry point `parse_scene`."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import ClassVar, Protocol

import torch

from metegs.data.config import DatasetConfig
from metegs.data.exif import exposure_times_s
from metegs.data.scene import SceneData
from metegs.errors import DataError
from metegs.registry import registry


class DataParser(Protocol):
    """A registered data format (registry kind ``parser``)."""

    priority: ClassVar[int]
    """Detection order: lower is tried first."""

    @staticmethod
    def can_parse(path: Path) -> bool:
        """True if ``path`` looks like a scene of this format (cheap: file names only)."""
        ...

    def parse(self, path: Path | None, options: DatasetConfig) -> SceneData:
        """Read the scene; raises DataError naming the file and the problem on bad input."""
        ...


def detect_parser(path: Path) -> str:
    """Registry name of the parser that recognises ``path``; a DataError lists what was looked for."""
    if not path.exists():
        raise DataError(path, "data folder does not exist")
    if not path.is_dir() and path.suffix != ".json":
        raise DataError(path, "expected a scene folder (or a transforms.json file)")
    candidates = []
    for entry in registry("parser").entries():
        cls = entry.load()
        can = getattr(cls, "can_parse", None)
        if can is None or entry.name == "synthetic":
            continue
        candidates.append((getattr(cls, "priority", 100), entry.name, can))
    for _, name, can in sorted(candidates):
        if can(path):
            return name
    raise DataError(
        path,
        "cannot tell the scene format: expected a COLMAP model (sparse/0/cameras.bin or .txt), "
        "transforms.json, transforms_train.json (blender) or poses_bounds.npy (LLFF); "
        f"force one with --parser NAME ({', '.join(registry('parser').names())})",
    )


def parse_scene(path: Path | None, parser: str | None, options: DatasetConfig) -> SceneData:
    """Read a scene: no ``path`` means the synthetic scene; ``parser`` forces a format, else it is detected."""
    if path is None and parser in (None, "synthetic"):
        name = "synthetic"
    elif parser is not None:
        name = parser
        if path is not None and not Path(path).exists():
            raise DataError(path, "data folder does not exist")
    else:
        name = detect_parser(Path(path))
    cls = registry("parser").get(name)
    scene = cls().parse(None if path is None else Path(path), options)
    scene.parser = name
    if scene.cameras.exposure_time_s is None and scene.image_paths:  # any format: the photos' EXIF
        times = exposure_times_s(scene.image_paths)
        if times is not None:
            scene.cameras = replace(scene.cameras, exposure_time_s=torch.tensor(times, dtype=torch.float32))
    scene.cameras.validate(str(path or name))
    return scene
