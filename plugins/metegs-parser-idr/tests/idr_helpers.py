"""Write a small IDR/NeuS scene from metegs' synthetic scene (known cameras) for the tests."""

from pathlib import Path

import cv2
import numpy as np
from metegs.data.config import DatasetConfig, SyntheticSceneConfig
from metegs.data.parsers.base import parse_scene

from metegs_parser_idr.parser import write_cameras_npz

SCALE = 3.0
OFFSET = np.array([0.4, -0.2, 1.5])


def scale_mat() -> np.ndarray:
    """Normalised (unit sphere) -> world: x_world = SCALE·x + OFFSET."""
    s = np.eye(4)
    s[:3, :3] *= SCALE
    s[:3, 3] = OFFSET
    return s


def write_scene(folder: Path, views: int = 6, masks: bool = True, camera_file: str = "cameras_sphere.npz"):
    """The synthetic scene's views as an IDR/NeuS folder; returns the synthetic SceneData (world cameras)."""
    opts = DatasetConfig(synthetic=SyntheticSceneConfig(width=40, height=30, num_views=views, num_points=200))
    scene = parse_scene(None, None, opts)
    (folder / "image").mkdir(parents=True)
    for i, img in enumerate(scene.images):
        cv2.imwrite(str(folder / "image" / f"{i:06d}.png"), (img[..., ::-1] * 255).round().astype(np.uint8))
        if masks:
            (folder / "mask").mkdir(exist_ok=True)
            cv2.imwrite(str(folder / "mask" / f"{i:03d}.png"), np.full((30, 40, 3), 255, np.uint8))
    write_cameras_npz(folder / camera_file, scene.cameras, scale_mat())
    return scene
