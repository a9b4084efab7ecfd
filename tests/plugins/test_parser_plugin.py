"""A second registry kind opened by a plugin: the example `metegs-parser-idr` (plugins/metegs-parser-idr) adds
a data parser that metegs detects and trains on, with no change to metegs.

Runs from the source tree through ``METEGS_PLUGINS`` (so CI needs no install).
"""

from pathlib import Path

import cv2
import numpy as np

from metegs.data.config import DatasetConfig, SyntheticSceneConfig
from metegs.data.parsers.base import detect_parser, parse_scene


def idr_scene(folder: Path):
    """The synthetic scene written as IDR/NeuS (image/ + cameras_sphere.npz, no scale_mat: world frame kept)."""
    from metegs_parser_idr.parser import write_cameras_npz

    scene = parse_scene(None, None, DatasetConfig(synthetic=SyntheticSceneConfig(width=48, height=36, num_views=8)))
    (folder / "image").mkdir(parents=True)
    for i, img in enumerate(scene.images):
        cv2.imwrite(str(folder / "image" / f"{i:06d}.png"), (img[..., ::-1] * 255).round().astype(np.uint8))
    write_cameras_npz(folder / "cameras_sphere.npz", scene.cameras)
    return scene


def test_plugin_parser_is_detected_and_trained_on(idr_plugin, tmp_path):
    from metegs.cli.train import components_help, parse_args

    truth = idr_scene(tmp_path / "scan")
    assert "idr [metegs" in components_help()
    assert detect_parser(tmp_path / "scan") == "idr"
    scene = parse_scene(tmp_path / "scan", None, DatasetConfig())
    assert np.allclose(scene.cameras.camera_to_worlds.numpy(), truth.cameras.camera_to_worlds.numpy(), atol=1e-4)
    cfg = parse_args(
        ["3dgs", "--data", str(tmp_path / "scan"), "--max-steps", "3", "--output-dir", str(tmp_path / "out")]
    )
    trainer = cfg.setup()
    assert trainer.scene.parser == "idr"
    assert trainer.train()["psnr"] > 0
