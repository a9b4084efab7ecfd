"""The comparison a MeteGS run prints and writes is like for like: 3DGS against blind MeteGS on the same photos,
and a run that saw clean references is labelled as such."""

from __future__ import annotations

import json

from metegs.cli.train import main

TINY = ["--dataset.synthetic.width", "32", "--dataset.synthetic.height", "24", "--dataset.synthetic.num-views", "6",
        "--dataset.synthetic.num-points", "200", "--dataset.test-every", "3", "--max-steps", "6", "--no-progress",
        "--no-save-renders", "--eval-every", "0", "--weights.perceptual", "0",
        "--conditions.precip-mm-h", "20", "--conditions.visibility-m", "300"]  # fmt: skip


def test_a_run_with_clean_references_is_compared_through_its_blind_twin(tmp_path):
    metrics = main(["metegs-full", *TINY, "--output-dir", str(tmp_path), "--experiment-name", "run"])
    run = tmp_path / "synthetic" / "metegs-full" / "run"
    record = json.loads((run / "comparison.json").read_text())
    assert list(record["methods"]) == ["3dgs", "metegs-full (blind)", "metegs-full (clean references)"]
    flags = {name: m["clean_references"] for name, m in record["methods"].items()}
    assert flags == {"3dgs": False, "metegs-full (blind)": False, "metegs-full (clean references)": True}
    assert "oracle" in record["methods"]["metegs-full (clean references)"]["inputs"]
    blind = json.loads((run / "blind" / "metrics.json").read_text())
    assert blind["psnr"] == record["methods"]["metegs-full (blind)"]["psnr"] == metrics["blind"]["psnr"]
    decisions = json.loads((run / "blind" / "decisions.json").read_text())["decisions"]
    assert "clean" in decisions["clean branch"] and "off" in decisions["clean branch"]


def test_a_blind_run_is_its_own_row(tmp_path):
    main(["metegs-full", *TINY, "--no-clean-supervision", "--output-dir", str(tmp_path), "--experiment-name", "run"])
    run = tmp_path / "synthetic" / "metegs-full" / "run"
    record = json.loads((run / "comparison.json").read_text())
    assert list(record["methods"]) == ["3dgs", "metegs-full"] and not (run / "blind").exists()
    assert not any(m["clean_references"] for m in record["methods"].values())
