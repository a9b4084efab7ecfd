"""`metegs-bench suite --executor ray`: the quick suite on a local Ray instance (2 CPUs, loopback only) gives the
local executor's rows, a suite whose Ray driver is killed half-way is finished by the local executor (nothing
half-counted), and a failing run is reported with its error and log while the others finish."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

ray = pytest.importorskip("ray", reason="the Ray executor's tests need Ray (pip install -e '.[ray]')")

from metegs.bench.executors import LocalExecutor, RayExecutor  # noqa: E402
from metegs.bench.suite import SuiteRunner  # noqa: E402
from metegs.bench.suite_config import load_suite  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
QUICK = REPO / "configs" / "bench" / "quick.yaml"
ISD = REPO / ".." / "shared" / "data" / "meteo" / "isd-janmayen-1988" / "DS3505.txt"

pytestmark = [pytest.mark.slow, pytest.mark.data]


@pytest.fixture
def quick_suite(tmp_path):
    """The quick suite with one torch thread per run (the runs of both executors then round alike), written where
    the tests may change it."""
    if not ISD.is_file():
        pytest.skip(f"{ISD} absent (shared data only in development checkouts)")

    def write(name: str = "quick.yaml", **changes) -> Path:
        data = yaml.safe_load(QUICK.read_text())
        data["conditions"][0]["fog"]["record"] = str(ISD.resolve())
        data.update({"threads": 1, **changes})
        path = tmp_path / name
        path.write_text(yaml.safe_dump(data))
        return path

    return write


@pytest.fixture
def local_ray():
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield
    ray.shutdown()


def summary_rows(out: Path) -> list[str]:
    """The rows of results.md's per-scene summary table (method, PSNR, SSIM, LPIPS per condition)."""
    lines = (out / "results.md").read_text().splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("| Method | fog-200 PSNR"))
    return [line for line in lines[start:] if line.startswith("|")][: 2 + 5]


def test_ray_gives_the_local_executors_rows(quick_suite, tmp_path, local_ray):
    suite = load_suite(quick_suite())
    local = SuiteRunner(suite, tmp_path / "local").run(LocalExecutor())
    remote = SuiteRunner(suite, tmp_path / "ray").run(RayExecutor())
    assert [r["method"] for r in remote["runs"]] == [r["method"] for r in local["runs"]]  # the plan's order
    for a, b in zip(local["runs"], remote["runs"]):
        assert b["status"] == "done" and abs(a["psnr"] - b["psnr"]) < 0.01, (a["method"], a["psnr"], b["psnr"])
    assert summary_rows(tmp_path / "ray") == summary_rows(tmp_path / "local")
    logs = sorted(p.name for p in (tmp_path / "ray" / "logs").iterdir())
    assert "synthetic__fog-200__data.log" in logs and "synthetic__fog-200__metegs-blind.log" in logs
    assert remote["all_checks_passed"]


def test_a_suite_whose_ray_driver_is_killed_is_finished_by_the_local_executor(quick_suite, tmp_path):
    suite_file, out = quick_suite(), tmp_path / "suite"
    cmd = [
        sys.executable,
        "-c",
        "import sys; from metegs.cli.bench import entrypoint; sys.argv[0] = 'metegs-bench'; entrypoint()",
        *("suite", str(suite_file), "--output", str(out), "--executor", "ray"),
    ]
    driver = subprocess.Popen(cmd, start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.time() + 240
        while time.time() < deadline and not list(out.glob("synthetic/*/*/bench.json")):
            assert driver.poll() is None, "the driver ended before any run finished"
            time.sleep(0.1)
    finally:
        os.killpg(driver.pid, signal.SIGKILL)  # the driver, its Ray and its workers, half-way
        driver.wait()
    finished = {p.parent.name for p in out.glob("synthetic/*/*/bench.json")}
    assert finished and not (out / "results.json").exists()
    results = SuiteRunner(load_suite(suite_file), out).run(LocalExecutor())
    status = {r["method"]: r["status"] for r in results["runs"]}
    assert len(status) == 5 and set(status.values()) <= {"cached", "done"}
    assert {m for m, s in status.items() if s == "cached"} >= finished  # what ended before the kill is reused
    assert results["all_checks_passed"]


def test_a_failing_run_is_reported_with_its_log_and_the_others_finish(quick_suite, tmp_path, local_ray):
    data = yaml.safe_load(quick_suite().read_text())
    broken = {"name": "broken", "method": "3dgs", "overrides": {"load_checkpoint": str(tmp_path / "none.ckpt")}}
    data["methods"] = [m for m in data["methods"] if m["name"] == "3dgs"] + [broken]
    data["checks"] = []
    (tmp_path / "broken.yaml").write_text(yaml.safe_dump(data))
    out = tmp_path / "suite"
    results = SuiteRunner(load_suite(tmp_path / "broken.yaml"), out).run(RayExecutor())
    runs = {r["method"]: r for r in results["runs"]}
    assert runs["3dgs"]["status"] == "done" and runs["broken"]["status"] == "failed"
    assert "none.ckpt" in runs["broken"]["error"]
    log = out / runs["broken"]["log"]
    assert log.is_file() and "training" not in log.read_text()  # it failed while setting up, and said so there
    assert "broken" in (out / "results.md").read_text()
