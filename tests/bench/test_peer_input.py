"""benchmarks/peer_input.py: another toolkit gets exactly the training views, cameras and points of a run."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from metegs.bench.suite_config import load_suite

REPO = Path(__file__).resolve().parents[2]


def test_the_peer_input_holds_the_runs_training_views_as_it_loaded_them(tmp_path, benchmark_script):
    from metegs.data.config import DatasetConfig, SyntheticSceneConfig
    from metegs.data.dataset import Dataset
    from metegs.data.images import load_image
    from metegs.data.parsers.base import parse_scene
    from metegs.engine.config import TrainConfig

    ds = DatasetConfig(synthetic=SyntheticSceneConfig(width=40, height=30, num_views=9, num_points=200), test_every=3)
    cfg = TrainConfig(max_steps=2, output_dir=tmp_path, experiment_name="r", progress=False, dataset=ds,
                      checkpoint_every=0, save_renders=False, device="cpu")  # fmt: skip
    trainer = cfg.setup()
    trainer.train()
    out = tmp_path / "peer"
    written = benchmark_script("peer_input").write_peer_input(trainer.run_dir / "config.yml", out)
    assert written == len(trainer.dataset.train_indices)

    peer = parse_scene(out, None, DatasetConfig(downscale=1))  # read back as nerfstudio, every view for training
    run = trainer.dataset
    train = run.train_indices
    assert peer.parser == "nerfstudio" and len(peer) == len(train) == 6
    got, want = peer.cameras.camera_to_worlds, run.cameras.camera_to_worlds[train].cpu()
    assert torch.allclose(got, want, atol=1e-5)
    for name in ("fx", "fy", "cx", "cy", "width", "height"):
        assert torch.allclose(getattr(peer.cameras, name).float(), getattr(run.cameras, name)[train].cpu().float())
    for path, i in zip(peer.image_paths, train, strict=True):  # the pixels the run trained on, to 8 bits
        assert np.abs(load_image(path) - run.images[i].cpu().numpy()).max() <= 0.5 / 255 + 1e-6
    assert np.allclose(peer.points, trainer.scene.points, atol=1e-5)
    assert Dataset(peer, DatasetConfig(downscale=1)).sizes == [run.sizes[i] for i in train]


def test_the_peer_suite_scores_each_peer_like_the_run_of_its_length():
    suite = load_suite(REPO / "configs/bench/peer.yaml")
    runs = {m.name: m.overrides["max_steps"] for m in suite.methods if m.peer is None}
    assert sorted(runs.values()) == [2000, 7000, 30000]
    for m in (m for m in suite.methods if m.peer is not None):
        steps = runs[m.peer["like"]]
        assert m.peer["ply"].endswith(f"-{steps}.ply")
