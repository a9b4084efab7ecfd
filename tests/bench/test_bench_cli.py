"""`metegs-bench raster` and `metegs-bench step` produce complete records (functional checks, not timings)."""

import json

import pytest
import torch

from metegs.bench.raster import benchmark_camera, benchmark_scene, plain_pairs
from metegs.cli.bench import RasterArgs, StepArgs, raster, step

RASTER_KEYS = {"backend", "num_gaussians", "width", "height", "forward_ms", "forward_backward_ms", "peak_mem_mb"}


def test_raster_json_records(tmp_path, capsys):
    out = tmp_path / "raster.json"
    rows = raster(RasterArgs(sizes=[300], images=["48x32"], repeats=1, json=True, output=out))
    printed = json.loads(capsys.readouterr().out)
    assert printed == rows == json.loads(out.read_text())
    assert {r["backend"] for r in rows} >= {"torch"}
    for r in rows:
        assert RASTER_KEYS <= r.keys()
        assert r["forward_ms"] > 0 and r["forward_backward_ms"] > 0 and r["num_intersections"] > 0
        assert (r["width"], r["height"], r["num_gaussians"]) == (48, 32, 300)


def test_benchmark_scene_has_the_research_depth_complexity():
    """At 600x400 the 3-sigma discs of the scene cover about 10x the image (as in the research note)."""
    import math

    g = benchmark_scene(20000)
    sigma_px = 600 * g.scales.prod(dim=1) ** (1 / 3) / g.means[:, 2]
    coverage = float((math.pi * (3 * sigma_px) ** 2).sum()) / (600 * 400)
    assert 7 < coverage < 14
    assert plain_pairs(g, benchmark_camera(300, 200)) > 20000


def test_raster_records_the_floor_at_the_machines_measured_peak():
    """With the cpu extension, every CPU record carries the multiply-add peak measured between its timed steps and
    the arithmetic floor at that peak: the research note's floor scaled by 330 GFLOP/s / the measured peak."""
    from metegs.bench.raster import PEAK_GFLOPS
    from metegs.render.select import usable_backends

    if "cpu" not in usable_backends("cpu"):
        pytest.skip("the cpu rasteriser extension cannot be built here")
    rows = raster(RasterArgs(sizes=[300], images=["48x32"], repeats=2, backends=["torch", "cpu"]))
    for r in rows:
        assert 0 < r["machine_peak_gflops"] < 1e5
        assert r["machine_floor_ms"] == pytest.approx(r["floor_ms"] * PEAK_GFLOPS / r["machine_peak_gflops"])


def test_raster_table_marks_what_this_run_did_not_measure(capsys, monkeypatch):
    """Without torch in the run there is no speed-up, and without a measured peak no floor here: the table says "-"
    there, never nan."""
    import metegs.bench.raster as raster_module
    from metegs.render.select import usable_backends

    if "cpu" not in usable_backends("cpu"):
        pytest.skip("the cpu rasteriser extension cannot be built here")
    monkeypatch.setattr(raster_module.CpuRasterizer, "available", staticmethod(lambda device="cpu": False))
    monkeypatch.setenv("COLUMNS", "250")
    rows = raster(RasterArgs(sizes=[300], images=["48x32"], repeats=1, backends=["cpu"]))
    assert rows[0]["machine_peak_gflops"] is None and rows[0]["machine_floor_ms"] is None
    line = next(x for x in capsys.readouterr().out.splitlines() if "48x32" in x)
    cells = [c.strip() for c in line.strip("│ ").split("│")]
    assert cells[0] == "cpu" and cells[6] == "-" and cells[8:10] == ["-", "-"] and "nan" not in line


def test_step_records(tmp_path):
    rows = step(
        StepArgs(
            sizes=[500],
            width=40,
            height=30,
            repeats=1,
            backends=["torch"],
            methods=["3dgs"],
            output=tmp_path / "s.json",
        )
    )
    assert len(rows) == 1 and rows[0]["iterations_per_s"] > 0 and rows[0]["width"] == 40 and rows[0]["method"] == "3dgs"
    assert json.loads((tmp_path / "s.json").read_text()) == rows


def test_step_times_metegs_full_beside_3dgs(capsys, monkeypatch):
    """The metegs-full rows run the method's own step (weather branch, GTN, and with references the clean branch) on
    the same resampled model as the 3dgs row, and the table gives their ratios to it and to the rasteriser."""
    monkeypatch.setenv("COLUMNS", "250")
    rows = step(StepArgs(sizes=[400], width=40, height=30, repeats=2, backends=["torch"]))
    assert [r["method"] for r in rows] == ["3dgs", "metegs-full", "metegs-full-blind"]
    assert all(r["step_ms"] > 0 and r["raster_ms"] > 0 for r in rows)
    lines = capsys.readouterr().out.splitlines()
    cells = {m: [c.strip() for c in next(x for x in lines if f" {m} " in x).strip("│ ").split("│")] for m in
             ("metegs-full", "metegs-full-blind")}  # fmt: skip
    ratio, over_raster = float(cells["metegs-full"][5]), float(cells["metegs-full"][7])
    # the ratios' values are timings, which a loaded machine can turn over: the table must report them as measured
    assert ratio == pytest.approx(rows[1]["step_ms"] / rows[0]["step_ms"], abs=0.01)
    assert over_raster == pytest.approx(rows[1]["step_ms"] / rows[1]["raster_ms"], abs=0.01)
    blind = float(cells["metegs-full-blind"][5])
    assert blind == pytest.approx(rows[2]["step_ms"] / rows[0]["step_ms"], abs=0.01)


def test_held_at_mid_run_no_refinement_or_extra_points_are_due(tmp_path):
    from dataclasses import replace

    from metegs.bench.step import hold_at_mid_run, method_config
    from metegs.data.config import DatasetConfig, SyntheticSceneConfig
    from metegs.engine.config import TrainConfig

    ds = DatasetConfig(synthetic=SyntheticSceneConfig(width=40, height=30, num_views=10, num_points=300))
    base = TrainConfig(device="cpu", progress=False, dataset=ds, output_dir=tmp_path)
    trainer = replace(method_config(base, "metegs-full"), max_steps=1000).setup()
    hold_at_mid_run(trainer)
    every = trainer.densifier.every
    assert trainer.step >= 500 and trainer.step % every != 0 and trainer.extra_points.done
    n = len(trainer.model)
    for i in trainer.dataset.train_indices[:3]:
        trainer.train_step(i)
    assert len(trainer.model) == n and trainer.step >= 500


def test_raster_torch_threads_apply_to_the_cpu_backend_only(tmp_path):
    """`--torch-threads 1`: the cpu backend is timed with torch's ops on one thread; torch keeps the run's count."""
    from metegs.render.select import usable_backends

    if "cpu" not in usable_backends("cpu"):
        pytest.skip("the cpu rasteriser extension cannot be built here")
    previous = torch.get_num_threads()
    try:
        rows = raster(
            RasterArgs(sizes=[300], images=["48x32"], repeats=1, backends=["torch", "cpu"], threads=2, torch_threads=1)
        )
    finally:
        torch.set_num_threads(previous)
    assert {r["backend"]: r["torch_threads"] for r in rows} == {"torch": 2, "cpu": 1}
