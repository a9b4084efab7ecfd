"""`metegs-bench suite --quick`: the reduced CI suite runs; 3dgs-clean >= metegs-blind > 3dgs (0.5 dB slack on the
bound) and metegs-full > 3dgs hold."""

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
ISD = REPO / ".." / "shared" / "data" / "meteo" / "isd-janmayen-1988" / "DS3505.txt"


@pytest.mark.slow
@pytest.mark.data
def test_quick_suite_orders_the_methods(tmp_path):
    if not ISD.is_file():
        pytest.skip(f"{ISD} absent (shared data only in development checkouts)")
    from metegs.cli.bench import SuiteArgs, suite

    out = tmp_path / "quick"
    results = suite(SuiteArgs(quick=True, output=out))
    assert results["all_checks_passed"], [c for c in results["checks"] if c["passed"] is not True]
    assert all(c["passed"] is True for c in results["checks"])
    psnr = {r["method"]: r["psnr"] for r in results["runs"]}
    assert psnr["3dgs-clean"] + 0.5 >= psnr["metegs-blind"] > psnr["3dgs"] and psnr["metegs-full"] > psnr["3dgs"]
    assert psnr["metegs-full"] > psnr["restore+3dgs"]
    fog = results["conditions"]["fog-200"]["fog"]
    assert fog["record"].endswith("DS3505.txt") and fog["present_weather"] and 130 <= fog["visibility_m"] <= 300
    assert (out / "results.md").read_text().count("|") > 20 and (out / "plots" / "synthetic__fog-200.png").is_file()
