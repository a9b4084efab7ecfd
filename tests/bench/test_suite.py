"""`metegs-bench SUITE.yaml`: the suite file, the runner (resumable, results.json), the report and the CLI."""

import json
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from metegs.bench.plot import Series, line_chart_png, nice_ticks
from metegs.bench.report import evaluate_checks, markdown_report
from metegs.bench.suite_config import CheckSpec, load_suite, suite_from_dict
from metegs.errors import ConfigError

REPO = Path(__file__).resolve().parents[2]


def test_the_shipped_suites_parse():
    default = load_suite(REPO / "configs/bench/default.yaml")
    assert [s.name for s in default.scenes] == ["synthetic", "ethiopianhead"]
    assert len(default.conditions) == 12 and {c.kind for c in default.conditions} == {"rain", "fog", "rain+fog"}
    assert sum(c.family == "independent" for c in default.conditions) == 4
    names = {m.name for m in default.methods}
    assert {"3dgs", "3dgs-clean", "restore+3dgs", "metegs-full", "metegs-blind", "abl-a", "abl-d"} <= names
    assert default.scenes[1].data.name == "ethiopianhead-llff" and default.scenes[1].conditions
    full = load_suite(REPO / "configs/bench/full.yaml")
    assert full.train["max_steps"] > default.train["max_steps"] and all(s.conditions is None for s in full.scenes)
    quick = load_suite(REPO / "configs/bench/quick.yaml")
    assert quick.train["max_steps"] <= 300 and len(quick.conditions) == 1
    assert quick.checks[0].chain() == [("3dgs-clean", ">=", "metegs-blind"), ("metegs-blind", ">", "3dgs")]
    assert quick.checks[1].chain() == [("metegs-full", ">", "3dgs")]
    real = load_suite(REPO / "configs/bench/real.yaml")  # issue 27's grid: real captures at >= 400 px
    assert all(s.data is not None for s in real.scenes)
    sizes = {s.name: s.train["dataset"] for s in real.scenes}
    assert all(d["auto_max_side"] >= 400 for name, d in sizes.items() if name != "kitchen")
    assert 1558 / sizes["kitchen"]["downscale"] >= 400  # the kitchen's photos are 1558 px wide
    kinds = {(c.kind, c.family) for c in real.conditions}
    assert kinds == {(k, f) for k in ("rain", "fog", "rain+fog") for f in ("physical", "independent")}
    other = load_suite(REPO / "configs/bench/real-other.yaml")  # the same captures under a third generator's rain
    assert [(s.name, s.data, s.train) for s in other.scenes] == [(s.name, s.data, s.train) for s in real.scenes]
    assert all(c.family == "independent" for c in other.conditions)  # benchmarks/other_generator.py draws them all
    other_fog = load_suite(REPO / "configs/bench/real-other-fog.yaml")  # the fox and Lund under its fog and smog
    assert [(s.name, s.data, s.train) for s in other_fog.scenes] == [(s.name, s.data, s.train) for s in real.scenes[1:]]
    assert [(c.kind, c.family) for c in other_fog.conditions] == [("fog", "independent"), ("rain+fog", "independent")]


def _minimal(**extra):
    data = {
        "name": "t",
        "scenes": [{"name": "synthetic"}],
        "conditions": [{"name": "f", "kind": "fog", "fog": {"visibility_m": 300, "explicit": True}}],
        "methods": [{"name": "3dgs"}],
    }
    data.update(extra)
    return data


@pytest.mark.parametrize(
    "change,message",
    [
        ({"bogus": 1}, "unknown key"),
        ({"methods": [{"name": "a"}, {"name": "a"}]}, "duplicate method"),
        ({"methods": [{"name": "a/b"}]}, "folder-safe"),
        ({"methods": [{"name": "a", "photos": "noisy"}]}, "photos must be"),
        ({"checks": [{"expect": "3dgs >> x"}]}, "names unknown method"),
        ({"checks": [{"expect": "3dgs"}]}, "expected 'A > B'"),
        ({"checks": [{"expect": "3dgs > 3dgs", "metrics": ["mse"]}]}, "unknown metric"),
        ({"eval_every": 2}, "eval_every"),
        ({"conditions": [], "methods": [{"name": "3dgs"}]}, "at least one condition"),
        ({"scenes": [{"name": "synthetic", "conditions": ["nope"]}]}, "names unknown condition"),
        (
            {"conditions": [{"name": "f", "kind": "fog", "fog": {"visibility_m": 9, "explicit": True}, "family": "x"}]},
            "family must be one of physical, independent",
        ),
        ({"resources": {"cpus": 2, "tpus": 1}}, "unknown resource"),
        ({"resources": {"gpus": -1}}, "resources.gpus must be a non-negative number"),
        ({"methods": [{"name": "a", "resources": {"cpus": "many"}}]}, "method 'a': resources.cpus"),
        ({"conditions": [{"name": "h", "kind": "hail", "rain": {"precip_mm_h": 5}}]}, "unknown: hail"),
        ({"conditions": [{"name": "d", "kind": "drops"}]}, "with '\\+drops' for the lens"),
        (
            {"conditions": [{"name": "r", "kind": "rain+fog", "fog": {"visibility_m": 300, "explicit": True}}]},
            "'rain:'",
        ),
    ],
)
def test_suite_file_errors_are_clear(change, message):
    with pytest.raises(ConfigError, match=message):
        suite_from_dict(_minimal(**change))


def test_resources_default_to_one_cpu_and_the_executor_names_are_checked():
    from metegs.bench.executors import LocalExecutor, RayExecutor, make_executor

    suite = suite_from_dict(_minimal(resources={"gpus": 1}, methods=[{"name": "a", "resources": {"cpus": 4}}]))
    assert suite.resources == {"cpus": 1, "gpus": 1} and suite.methods[0].resources == {"cpus": 4}
    assert isinstance(make_executor("local"), LocalExecutor)
    assert isinstance(make_executor("ray", "auto"), RayExecutor)  # Ray itself is imported only when it runs
    with pytest.raises(ConfigError, match="--address goes with --executor ray"):
        make_executor("local", "auto")
    with pytest.raises(ConfigError, match="expected one of local, ray"):
        make_executor("dask")


def test_the_ray_executor_says_how_to_install_ray(monkeypatch):
    from metegs.bench.executors import RayExecutor

    monkeypatch.setitem(sys.modules, "ray", None)  # as where the extra is not installed
    with pytest.raises(ConfigError, match=r'--executor ray needs Ray: pip install -e "\.\[ray\]"'):
        RayExecutor().run(None, [])


def _run(scene, cond, method, psnr, ssim, status="done", oracle=False, history=None):
    return {
        "scene": scene,
        "condition": cond,
        "method": method,
        "label": method,
        "group": "main",
        "oracle": oracle,
        "photos": "clean" if oracle else "degraded",
        "status": status,
        "psnr": psnr,
        "ssim": ssim,
        "lpips": None,
        "num_gaussians": 100,
        "time_seconds": 10.0,
        "train_seconds": 10.0,
        "render_fps": 50.0,
        "history": history or [{"time_seconds": 0.0, "psnr": 10.0}, {"time_seconds": 10.0, "psnr": psnr}],
    }


def _results():
    suite = suite_from_dict(
        _minimal(
            methods=[{"name": "clean", "photos": "clean", "oracle": True}, {"name": "a"}, {"name": "b"}, {"name": "c"}],
            checks=[{"expect": "clean >= a > b", "metrics": ["psnr", "ssim", "lpips"]}],
        )
    )
    runs = [
        _run("synthetic", None, "clean", 30.0, 0.95, oracle=True),
        _run("synthetic", "f", "a", 25.0, 0.80),
        _run("synthetic", "f", "b", 20.0, 0.85),
        _run("synthetic", "f", "c", 22.0, 0.70),
    ]

    class C:
        kind = "fog"

    checks = evaluate_checks(suite, runs, {"f": C()})
    methods = [{"name": m.name, "label": m.name, "group": m.group, "oracle": m.oracle} for m in suite.methods]
    return {
        "suite": "t",
        "created": "now",
        "total_seconds": 1.0,
        "host": {},
        "scenes": ["synthetic"],
        "methods": methods,
        "conditions": {"f": {"kind": "fog", "fog": {"visibility_m": 300.0}, "theta": {}}},
        "runs": runs,
        "support_runs": [],
        "checks": checks,
        "all_checks_passed": all(c["passed"] is not False for c in checks),
    }


def test_checks_and_table_marks():
    results = _results()
    verdict = {(c["pair"], c["metric"]): c["passed"] for c in results["checks"]}
    assert verdict[("clean >= a", "psnr")] and verdict[("a > b", "psnr")]
    assert verdict[("a > b", "ssim")] is False and verdict[("a > b", "lpips")] is None
    md = markdown_report(results)
    assert "| a | **25.00** | <u>0.8000</u> | – |" in md
    assert "| c | <u>22.00</u> | 0.7000 | – |" in md and "| b | 20.00 | **0.8500** |" in md
    assert "| a | **25.00** | <u>0.8000</u> | – | 10.0 | 100 | 50.0 |" in md  # equal times: nothing marked
    assert "*clean (oracle)* | 30.00" in md  # the oracle is shown, not ranked
    assert "**FAIL**" in md and "some fail" in md


def test_a_suite_of_clean_photo_runs_only_gets_its_table():
    results = {**_results(), "conditions": {}, "checks": []}
    results["runs"] = [r for r in results["runs"] if r["condition"] is None]
    results["runs"].append({**results["runs"][0], "method": "a", "psnr": 28.0, "oracle": False})
    md = markdown_report(results)
    assert "### synthetic / clean photos" in md and "| a | 28.00 | 0.9500 |" in md and "*clean (oracle)* | 30.00" in md


def test_curves_plot_is_a_png():
    png = line_chart_png([Series("a", [0, 1, 2], [10, 12, 13]), Series("b", [0, 3], [9, 14], dashed=True)], "t")
    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    assert img.shape == (560, 1000, 3) and (img < 250).any()
    empty = cv2.imdecode(np.frombuffer(line_chart_png([], "t"), np.uint8), cv2.IMREAD_COLOR)
    assert empty is not None
    ticks = nice_ticks(0, 97.5)
    assert ticks[0] <= 0 and ticks[-1] >= 97.5


def test_cli_takes_a_suite_file_positionally(monkeypatch, capsys, tmp_path):
    from metegs.cli import bench

    path = tmp_path / "s.yaml"
    path.write_text(yaml.safe_dump(_minimal(output=str(tmp_path / "out"))))
    monkeypatch.setattr(sys, "argv", ["metegs-bench", str(path), "--dry-run"])
    bench.entrypoint()
    out = capsys.readouterr().out
    assert "synthetic / f / 3dgs" in out and "to run" in out
    two = _minimal(output=str(tmp_path / "out2"), scenes=[{"name": "synthetic", "conditions": ["g"]}])
    two["conditions"].append({"name": "g", "kind": "fog", "fog": {"visibility_m": 500, "explicit": True}})
    path.write_text(yaml.safe_dump(two))
    bench.entrypoint()
    out = capsys.readouterr().out
    assert "synthetic / g / 3dgs" in out and "synthetic / f / 3dgs" not in out  # the scene's own conditions
    monkeypatch.setattr(sys, "argv", ["metegs-bench", "suite", "--quick", "--dry-run", "--output", str(tmp_path / "q")])
    bench.entrypoint()
    assert "synthetic / fog-200 / metegs-full" in capsys.readouterr().out


def test_check_spec_parses_chains():
    assert CheckSpec("a >= b > c").chain() == [("a", ">=", "b"), ("b", ">", "c")]
    with pytest.raises(ConfigError, match="amounts"):
        CheckSpec("a > b", margin=-1.0)


def test_check_margin_asks_the_left_to_pass_by_it():
    """'a > b' by a margin of 2 dB: a 5 dB lead passes, a 1 dB lead fails (as both do at 6 dB); the pair names it."""
    runs = [
        _run("synthetic", "f", "a", 25.0, 0.80),
        _run("synthetic", "f", "b", 20.0, 0.85),
        _run("synthetic", "f", "c", 21.0, 0.7),
    ]

    class C:
        kind = "fog"

    verdicts = {}
    for margin in (2.0, 6.0):
        checks = [
            {"expect": "a > b", "metrics": ["psnr"], "margin": margin},
            {"expect": "c > b", "metrics": ["psnr"], "margin": margin},
        ]
        suite = suite_from_dict(_minimal(methods=[{"name": "a"}, {"name": "b"}, {"name": "c"}], checks=checks))
        for c in evaluate_checks(suite, runs, {"f": C()}):
            verdicts[(c["pair"], margin)] = c["passed"]
    assert verdicts == {
        ("a > b + 2", 2.0): True,
        ("c > b + 2", 2.0): False,
        ("a > b + 6", 6.0): False,
        ("c > b + 6", 6.0): False,
    }


def _tiny_scene_on_disk(folder: Path) -> Path:
    """The synthetic scene written as a nerfstudio dataset without depth or scale (like a real capture)."""
    import dataclasses

    from metegs.data.config import DatasetConfig, SyntheticSceneConfig
    from metegs.data.parsers.base import parse_scene
    from metegs.synth.writers import DatasetWriter, encode_image

    scene = parse_scene(
        None,
        None,
        DatasetConfig(test_every=4, synthetic=SyntheticSceneConfig(width=32, height=24, num_views=8, num_points=300)),
    )
    scene = dataclasses.replace(scene, depths=None, metric_scale=None)
    folder.mkdir(parents=True)
    writer = DatasetWriter(scene, folder)
    for i, image in enumerate(scene.images):
        path = folder / writer.image_rel[i]
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(encode_image(image, ".png"))
    writer.finish(None)
    return folder


@pytest.mark.slow
def _restoring_again_reads_the_cache(cell: Path, suite, target: Path) -> None:
    """The suite's restored photos, restored once more into ``target``: every photo is read from the restored cache,
    reported with the seconds its first restoring took, and written the same."""
    from metegs.bench.data import restored_dataset
    from metegs.bench.suite import SuiteRunner
    from metegs.data.images import load_image
    from metegs.restore import restorer_for_kinds

    first = json.loads((cell / "restored-kang2012+dcp" / "restore.json").read_text())
    assert first["views_from_cache"] == 0
    runner = SuiteRunner(suite, output=cell.parent.parent)
    (scene,) = [s for s in suite.scenes if s.name == "files"]
    (method,) = [m for m in suite.methods if m.name == "restore+3dgs"]
    restorer = restorer_for_kinds("rain+fog", runner.restorer_names(method), method.restorer_options)
    _, again = restored_dataset(target, cell / "data", runner.dataset_config(scene), restorer)
    assert again["views_from_cache"] == first["views"]
    assert again["restore_seconds"] == pytest.approx(first["restore_seconds"], abs=2e-3)
    for png in sorted((cell / "restored-kang2012+dcp" / "images").iterdir()):
        np.testing.assert_array_equal(load_image(target / "images" / png.name), load_image(png))


def test_a_tiny_suite_runs_resumes_and_reports(tmp_path):
    from metegs.bench.suite import SuiteRunner

    scene_dir = _tiny_scene_on_disk(tmp_path / "scene")
    suite = suite_from_dict(
        {
            "name": "tiny",
            "eval_every": 0.5,
            "fps_repeats": 1,
            "train": {
                "max_steps": 6,
                "checkpoint_every": 3,
                "save_renders": False,
                "densify": {"max_gaussians": 600},
                "dataset": {
                    "test_every": 4,
                    "synthetic": {"width": 32, "height": 24, "num_views": 8, "num_points": 300},
                },
            },
            "scenes": [
                {"name": "synthetic"},
                {"name": "files", "data": str(scene_dir), "synth": {"assumed_depth_m": 30.0}},
            ],
            "conditions": [
                {
                    "name": "rf",
                    "kind": "rain+fog",
                    "rain": {"record": "storm", "class": "violent"},
                    "fog": {"visibility_m": 300, "explicit": True},
                },
            ],
            "methods": [
                {"name": "3dgs"},
                {"name": "3dgs-clean", "photos": "clean", "oracle": True},
                {
                    "name": "restore+3dgs",
                    "photos": "restored",
                    "restorer_options": {"kang2012": {"iterations": 1, "train_patches": 200}},
                },
                {"name": "restormer+3dgs", "photos": "restored", "restorer": {"rain": "restormer"}, "optional": True},
                {
                    "name": "metegs-full",
                    "method": "metegs-full",
                    "overrides": {"weights": {"perceptual": 0.0}},
                    "scenes": ["files"],
                },
            ],
            "checks": [{"expect": "3dgs-clean >= 3dgs", "metrics": ["psnr"]}],
        }
    )
    out = tmp_path / "out"
    results = SuiteRunner(suite, output=out).run()
    by = {(r["scene"], r["condition"], r["method"]): r for r in results["runs"]}
    assert by[("synthetic", None, "3dgs-clean")]["status"] == "done"
    assert by[("files", "rf", "metegs-full")]["status"] == "done"
    assert by[("files", "rf", "restormer+3dgs")]["status"] == "skipped"
    assert ("synthetic", "rf", "metegs-full") not in by  # scenes filter
    restored = by[("files", "rf", "restore+3dgs")]
    assert restored["restorer"] == "kang2012+dcp" and restored["preprocess_seconds"] > 0
    _restoring_again_reads_the_cache(out / "files" / "rf", suite, tmp_path / "again")
    for r in results["runs"]:
        if r["status"] == "done":
            assert r["render_fps"] > 0 and r["history"][0]["step"] == 0 and r["history"][0]["time_seconds"] >= 0
            assert r["history"][-1]["step"] == 6 and len(r["history"]) >= 3
    cond = json.loads((out / "files" / "rf" / "condition.json").read_text())
    assert cond["rain"]["precip_mm_h"] == pytest.approx(72.5) and cond["theta"]["rain"]["active"]
    assert cond["metres_per_unit_source"].startswith("guess")
    assert (out / "files" / "clean" / "3dgs-clean" / "metrics.json").is_file()  # the depth source
    assert json.loads((out / "conditions.json").read_text())["conditions"]["rf"]["theta"]["files"]["rain_active"]
    assert (out / "results.md").is_file() and (out / "plots" / "files__rf.png").is_file()
    assert results["checks"] and results["total_seconds"] > 0
    done = [r for r in results["runs"] if r["status"] == "done"]
    assert all(r["wall_seconds"] > 0 for r in done) and results["runs_wall_unknown"] == 0
    assert results["runs_wall_seconds"] == pytest.approx(sum(r["wall_seconds"] for r in done), abs=0.1)
    assert f"its runs took {results['runs_wall_seconds']:.0f} s" in (out / "results.md").read_text()

    # resumable: finished runs are reused; a run cut short resumes from its checkpoint
    stamp = (out / "synthetic" / "rf" / "3dgs" / "metrics.json").stat().st_mtime_ns
    cut = out / "files" / "rf" / "3dgs"
    (cut / "metrics.json").unlink()
    (cut / "bench.json").unlink()
    for ckpt in (cut / "checkpoints").glob("step-000006.ckpt"):
        ckpt.unlink()
    again = SuiteRunner(suite, output=out).run()
    by2 = {(r["scene"], r["condition"], r["method"]): r for r in again["runs"]}
    assert by2[("synthetic", "rf", "3dgs")]["status"] == "cached"
    assert (out / "synthetic" / "rf" / "3dgs" / "metrics.json").stat().st_mtime_ns == stamp
    resumed = by2[("files", "rf", "3dgs")]
    assert resumed["status"] == "done" and resumed["history"][-1]["step"] == 6
    assert by2[("files", "rf", "3dgs")]["psnr"] is not None
    # reused runs keep the wall time of the invocation that trained them
    assert by2[("synthetic", "rf", "3dgs")]["wall_seconds"] == by[("synthetic", "rf", "3dgs")]["wall_seconds"]
    assert again["runs_wall_seconds"] > again["total_seconds"] * 0.5

    # a changed suite does not silently pass old runs off as new ones
    suite.train["max_steps"] = 7
    suite.train["lpips_download"] = False  # trains nothing differently: never reported as a change
    third = SuiteRunner(suite, output=out).run()
    assert all(r.get("config_changed") == ["max_steps"] for r in third["runs"] if r["status"] == "cached")


def test_both_weather_families_in_one_suite(tmp_path):
    """The same condition made by metegs's weather models and by the independent family: two degraded copies,
    both in the results and the conditions table."""
    from metegs.bench.suite import SuiteRunner

    rain_fog = {"kind": "rain+fog", "rain": {"precip_mm_h": 20.0}, "fog": {"visibility_m": 300, "explicit": True}}
    suite = suite_from_dict(
        {
            "name": "families",
            "fps_repeats": 1,
            "train": {"max_steps": 4, "save_renders": False, "dataset": {"test_every": 3, "synthetic": {
                "width": 48, "height": 36, "num_views": 6, "num_points": 200}}},
            "scenes": [{"name": "synthetic"}],
            "conditions": [{"name": "rf", **rain_fog}, {"name": "rf-ind", "family": "independent", **rain_fog}],
            "methods": [{"name": "3dgs"}],
        }
    )  # fmt: skip
    out = tmp_path / "out"
    results = SuiteRunner(suite, output=out).run()
    assert {r["condition"] for r in results["runs"] if r["status"] == "done"} >= {"rf", "rf-ind"}
    made = {c: json.loads((out / "synthetic" / c / "data" / "weather.json").read_text()) for c in ("rf", "rf-ind")}
    assert made["rf"]["family"] == "physical" and made["rf-ind"]["family"] == "independent"
    assert "theta" not in made["rf-ind"]["views"][0] and made["rf-ind"]["views"][0]["rain"]["layers"]
    assert results["conditions"]["rf-ind"]["family"] == "independent"
    assert "| rf-ind | rain+fog | independent |" in (out / "results.md").read_text()


def test_a_peer_row_scores_another_toolkits_ply_like_a_run(tmp_path, capsys):
    """A peer's PLY (here the 3dgs run's Gaussians written again in the scene's frame without metegs's frame comment,
    as another toolkit writes them) scores what the run scores, on the same views by the same evaluator."""
    from metegs.bench.suite import SuiteRunner
    from metegs.gaussians.ply import load_ply, save_ply

    train = {"max_steps": 6, "checkpoint_every": 0, "save_renders": False, "densify": {"max_gaussians": 600}}
    train["dataset"] = {"test_every": 4, "synthetic": {"width": 32, "height": 24, "num_views": 8, "num_points": 300}}
    peer_ply = str(tmp_path / "peer" / "{scene}-{condition}.ply")
    suite = suite_from_dict(
        _minimal(
            fps_repeats=1,
            train=train,
            methods=[
                {"name": "3dgs"},
                {"name": "3dgs-clean", "photos": "clean"},
                {"name": "peer", "peer": {"ply": peer_ply, "like": "3dgs"}},
                {"name": "peer-clean", "peer": {"ply": str(tmp_path / "missing.ply"), "like": "3dgs-clean"}},
            ],
        )
    )
    out = tmp_path / "out"
    runner = SuiteRunner(suite, output=out)
    first = runner.run()
    by = {r["method"]: r for r in first["runs"]}
    assert by["peer"]["status"] == "failed" and "the peer's PLY file is not there" in by["peer"]["error"]
    assert by["peer-clean"]["status"] == "failed" and "missing.ply" in by["peer-clean"]["error"]
    model = load_ply(out / "synthetic" / "f" / "3dgs" / "scene.ply")
    (tmp_path / "peer").mkdir()
    save_ply(model, tmp_path / "peer" / "synthetic-f.ply")  # no frame comment: another tool's file
    again = {r["method"]: r for r in SuiteRunner(suite, output=out).run()["runs"]}
    assert again["3dgs"]["status"] == "cached" and again["peer"]["status"] == "done"
    assert again["peer"]["psnr"] == pytest.approx(again["3dgs"]["psnr"], abs=1e-4)
    assert again["peer"]["num_gaussians"] == again["3dgs"]["num_gaussians"] and again["peer"]["train_seconds"] is None
    assert (out / "synthetic" / "f" / "peer" / "eval.json").is_file()
    third = {r["method"]: r for r in SuiteRunner(suite, output=out).run()["runs"]}
    assert third["peer"]["status"] == "cached" and third["peer"]["psnr"] == again["peer"]["psnr"]
    assert "| peer |" in (out / "results.md").read_text()
    assert any("peer" in line and "scored" in line for line in SuiteRunner(suite, output=out).plan())


def test_a_peer_must_be_scored_like_a_trained_method():
    with pytest.raises(ConfigError, match="peer.like must name a method the suite trains"):
        suite_from_dict(_minimal(methods=[{"name": "3dgs"}, {"name": "p", "peer": {"ply": "x.ply", "like": "nope"}}]))
    with pytest.raises(ConfigError, match=r"peer must be \{ply: FILE, like: METHOD\}"):
        suite_from_dict(_minimal(methods=[{"name": "p", "peer": {"ply": "x.ply"}}]))


def test_a_prepared_folder_gives_its_depth_to_a_filtered_call_and_a_row_its_own_seed(tmp_path):
    """``prepare`` trains the clean row and degrades the photos, no weather run; a later ``--only-methods`` call that
    leaves the clean row out uses them (no helper run), and a row's ``seed`` trains on the suite seed's photos."""
    from metegs.bench.suite import SuiteRunner

    scene_dir = _tiny_scene_on_disk(tmp_path / "scene")
    train = {"max_steps": 4, "checkpoint_every": 4, "save_renders": False, "dataset": {"test_every": 4}}
    suite = suite_from_dict(
        {
            "name": "seeds",
            "fps_repeats": 1,
            "train": train,
            "scenes": [{"name": "files", "data": str(scene_dir), "synth": {"assumed_depth_m": 30.0}}],
            "conditions": [{"name": "fog", "kind": "fog", "fog": {"visibility_m": 300, "explicit": True}}],
            "methods": [
                {"name": "3dgs-clean", "photos": "clean", "oracle": True},
                {"name": "3dgs", "seeds": [1]},
            ],
        }
    )
    copy = suite.method("3dgs-seed1")
    assert (copy.seed, copy.seed_of, copy.group, copy.seeds) == (1, "3dgs", "ablation", [])
    out = tmp_path / "out"
    prepared = SuiteRunner(suite, output=out, only_methods=["3dgs-clean", "3dgs"]).run(prepare=True)
    assert prepared["failed"] == [] and "files/fog/data" in prepared["prepared"]
    assert (out / "files" / "clean" / "3dgs-clean" / "metrics.json").is_file()
    assert (out / "files" / "fog" / "data" / "weather.json").is_file()
    assert not (out / "files" / "fog" / "3dgs").exists() and not (out / "results.json").exists()
    assert json.loads((out / "conditions.json").read_text())["conditions"]["fog"]["theta"]["files"]  # θ kept
    results = SuiteRunner(suite, output=out, only_methods=["3dgs", "3dgs-seed1"]).run()
    assert {r["method"]: r["status"] for r in results["runs"]} == {"3dgs": "done", "3dgs-seed1": "done"}
    assert not (out / "files" / "clean" / "_depth-3dgs").exists()
    assert json.loads((out / "files" / "fog" / "data" / "weather.json").read_text())["seed"] == 0
    seeds = {
        m: yaml.safe_load((out / "files" / "fog" / m / "config.yml").read_text())["seed"]
        for m in ("3dgs", "3dgs-seed1")
    }
    assert seeds == {"3dgs": 0, "3dgs-seed1": 1}
    psnr = [r["psnr"] for r in results["runs"]]
    mean = sum(psnr) / 2
    report = (out / "results.md").read_text()
    assert "### files: across seeds" in report and f"| 3dgs (0, 1) | {mean:.2f} ± " in report

    # a later call limited to another row adds to the report; a run whose folder lost its metrics drops out
    (out / "files" / "fog" / "3dgs-seed1" / "metrics.json").unlink()
    again = SuiteRunner(suite, output=out, only_methods=["3dgs-clean"]).run()
    assert sorted((r["method"], r["status"]) for r in again["runs"]) == [("3dgs", "done"), ("3dgs-clean", "cached")]
    assert again["runs_from_earlier_calls"] == 1 and list(again["conditions"]) == ["fog"]
    assert [m["name"] for m in again["methods"]] == ["3dgs-clean", "3dgs"]
    assert "| 3dgs |" in (out / "results.md").read_text()


def test_seeds_table_gives_mean_and_spread_and_a_repeated_seed_is_refused():
    from metegs.bench.report import ablation_table, seeds_table

    def run(method, psnr, ssim, status="done"):
        return {"scene": "s", "condition": "c", "method": method, "psnr": psnr, "ssim": ssim, "status": status}

    results = {
        "conditions": {"c": {}},
        "methods": [
            {"name": "a", "label": "A", "group": "main", "seed": 0},
            {"name": "a-seed1", "label": "A, seed 1", "group": "ablation", "seed": 1, "seed_of": "a"},
            {"name": "a-seed2", "label": "A, seed 2", "group": "ablation", "seed": 2, "seed_of": "a"},
        ],
        "runs": [run("a", 10.0, 0.5), run("a-seed1", 12.0, 0.7), run("a-seed2", None, None, "failed")],
    }
    table = seeds_table(results, "s")
    assert "| A (0, 1, 2) | 10.00" not in table and "| A (0, 1, 2) | 11.00 ± 1.41 (2) | 0.6000 ± 0.1414 (2) |" in table
    assert ablation_table(results, "s") is None  # the copies are not ablations
    with pytest.raises(ConfigError, match="seeds"):
        suite_from_dict({"scenes": [{"name": "x"}], "methods": [{"name": "m", "photos": "clean", "seeds": [0]}]})


def test_a_copied_suite_folder_reuses_its_runs_without_a_data_warning(tmp_path):
    """A run whose photos now lie in a copy of its folder is the same run; a changed photo makes it another."""
    import shutil

    from metegs.bench.suite import config_changes
    from metegs.config import save_yaml
    from metegs.data.config import DatasetConfig
    from metegs.engine.config import TrainConfig

    def config(data):
        return TrainConfig(data=data, dataset=DatasetConfig(auto_max_side=640))

    made_from = tmp_path / "old" / "data"
    (made_from / "images").mkdir(parents=True)
    (made_from / "images" / "a.png").write_bytes(b"photo a")
    (made_from / "weather.json").write_text("{}")
    run = tmp_path / "old" / "run"
    run.mkdir()
    save_yaml(config(made_from), run / "config.yml")

    copy = tmp_path / "new" / "data"
    shutil.copytree(made_from, copy)
    (copy / ".metegs_points").mkdir()  # a cache written beside the photos, not part of them
    (copy / ".metegs_points" / "points-0.npz").write_bytes(b"cache")
    assert config_changes(run, config(copy)) == []

    (copy / "images" / "a.png").write_bytes(b"photo b")
    assert config_changes(run, config(copy)) == ["data"]
    (copy / "images" / "a.png").write_bytes(b"photo a")
    (copy / "images" / "b.png").write_bytes(b"photo a")
    assert config_changes(run, config(copy)) == ["data"]
    shutil.rmtree(made_from)  # the photos it was made from are gone: it cannot be told the same
    assert config_changes(run, config(copy)) == ["data"]
