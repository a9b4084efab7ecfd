"""The other commands' inputs: metegs-bench, metegs-synth, metegs-process-images, metegs-view options."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from corpus.harness import Case, Result, trained_run

SYNTH_TINY = [
    "--dataset.synthetic.width",
    "32",
    "--dataset.synthetic.height",
    "24",
    "--dataset.synthetic.num-views",
    "3",
    "--dataset.synthetic.num-points",
    "100",
    "--preview-views",
    "0",
]


def _file(folder, name, text):
    path = Path(folder) / name
    path.write_text(text)
    return path


def _suite(folder, text):
    return ["suite", _file(folder, "suite.yaml", text), "--output", Path(folder) / "bench"]


def _synth(folder, *extra, output="rainy"):
    return ["--output", Path(folder) / output, *SYNTH_TINY, *extra]


def _dead_pid() -> int:
    done = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    return int(done.stdout)


def _synth_after_killed_one(folder):
    """A synth output whose previous writer was killed mid-way (kill -9): its staging folder is still there."""
    stale = Path(folder) / f".rainy.partial-{_dead_pid()}"
    (stale / "images").mkdir(parents=True)
    return _synth(folder, "--precip-mm-h", "10")


def _synthesised(result: Result) -> None:
    out = result.folder / "rainy"
    assert len(list((out / "images").glob("*"))) == 3 and (out / "weather.json").is_file()
    assert not [p for p in result.folder.iterdir() if ".partial-" in p.name], "a staging folder was left behind"


PRSA_ROWS = ['"No","year","month","day","hour","RAIN","wd","WSPM","station"'] + [
    f'{i + 1},2024,7,1,{i},{rain},"NE",2.5,"Test"' for i, rain in enumerate([0, 4.0, 12.5, 3.0])
]


def _prsa_utf16(folder):
    """A PRSA-layout record saved by a spreadsheet as "Unicode text" (UTF-16 with a byte-order mark)."""
    path = Path(folder) / "prsa.csv"
    path.write_bytes("\r\n".join(PRSA_ROWS).encode("utf-16"))
    return _synth(folder, "--record", path, "--time", "2024-06-30T18:00Z", "--visibility-m", "2000")


def _existing_output(folder):
    (Path(folder) / "rainy").mkdir()
    (Path(folder) / "rainy" / "keep.txt").write_text("earlier work")
    return _synth(folder)


def _kept(result: Result) -> None:
    assert (result.folder / "rainy/keep.txt").read_text() == "earlier work"


def _photos(folder, n=0):
    path = Path(folder) / "photos"
    path.mkdir()
    return path


def _blocker(folder):
    return _file(folder, "blocker", "a file where a folder is expected")


SUITE_SCENE = "name: t\nscenes:\n  - name: s\n    data: synthetic\n"

# The cases are a table to read down: one case on one or two lines.
# fmt: off
CASES = [
    # metegs-bench
    Case(
        "bench-suite-missing-file",
        "metegs-bench",
        lambda f: ["suite", "missing.yaml"],
        "clear",
        match=r"missing\.yaml: suite file not found",
    ),
    Case("bench-suite-broken-yaml", "metegs-bench", lambda f: _suite(f, "scenes: [\n"), "clear", match=r"suite\.yaml"),
    Case(
        "bench-suite-unknown-key",
        "metegs-bench",
        lambda f: _suite(f, "nonsense: 1\n"),
        "clear",
        match=r"suite\.yaml: unknown key\(s\) nonsense",
    ),
    Case(
        "bench-suite-empty",
        "metegs-bench",
        lambda f: _suite(f, "name: t\n"),
        "clear",
        match=r"suite\.yaml: a suite needs at least one scene",
    ),
    Case(
        "bench-suite-method-not-a-mapping",
        "metegs-bench",
        lambda f: _suite(f, SUITE_SCENE + "methods: [nope]\n"),
        "clear",
        match=r"suite\.yaml: methods\[0\]",
    ),
    Case(
        "bench-suite-output-under-a-file",
        "metegs-bench",
        lambda f: ["suite", "--quick", "--output", _blocker(f) / "x"],
        "clear",
        match=r"blocker",
    ),
    Case(
        "bench-raster-negative-size",
        "metegs-bench",
        lambda f: ["raster", "--sizes", "-5"],
        "clear",
        match=r"--sizes -5",
    ),
    Case(
        "bench-raster-zero-image",
        "metegs-bench",
        lambda f: ["raster", "--images", "0x0"],
        "clear",
        match=r"--images.*0x0",
    ),
    Case(
        "bench-raster-bad-image",
        "metegs-bench",
        lambda f: ["raster", "--images", "wide"],
        "clear",
        match=r"--images.*wide",
    ),
    Case(
        "bench-raster-zero-repeats",
        "metegs-bench",
        lambda f: ["raster", "--repeats", "0"],
        "clear",
        match=r"--repeats 0",
    ),
    Case(
        "bench-raster-zero-threads",
        "metegs-bench",
        lambda f: ["raster", "--threads", "0"],
        "clear",
        match=r"--threads 0",
    ),
    Case(
        "bench-raster-unknown-backend",
        "metegs-bench",
        lambda f: ["raster", "--backends", "vulkan", "--sizes", "10", "--images", "8x8"],
        "clear",
        match=r"vulkan",
    ),
    Case("bench-step-zero-size", "metegs-bench", lambda f: ["step", "--sizes", "0"], "clear", match=r"--sizes 0"),
    Case("bench-step-tiny-width", "metegs-bench", lambda f: ["step", "--width", "2"], "clear", match=r"--width 2"),
    Case(
        "bench-step-negative-torch-threads",
        "metegs-bench",
        lambda f: ["step", "--torch-threads", "-1"],
        "clear",
        match=r"--torch-threads -1",
    ),
    # metegs-synth
    Case("synth-tiny", "metegs-synth", lambda f: _synth(f, "--precip-mm-h", "10"), "correct", check=_synthesised),
    Case("synth-after-a-killed-synth", "metegs-synth", _synth_after_killed_one, "correct", check=_synthesised),
    Case("synth-prsa-record-in-utf16", "metegs-synth", _prsa_utf16, "correct", check=_synthesised),
    Case("synth-precipitation-above-world-record", "metegs-synth", lambda f: _synth(f, "--precip-mm-h", "1e9"),
         "clear", match=r"--precip-mm-h 1000000000.0: expected a number >= 0 and <= 2400"),
    Case("synth-visibility-below-a-metre", "metegs-synth", lambda f: _synth(f, "--visibility-m", "0.5"), "clear",
         match=r"--visibility-m 0.5"),
    Case("synth-infinite-wind-direction", "metegs-synth",
         lambda f: _synth(f, "--precip-mm-h", "5", "--wind-speed-m-per-s", "3", "--wind-dir-deg", "inf"), "clear",
         match=r"--wind-dir-deg inf"),
    Case("synth-hurricane-beyond-record", "metegs-synth",
         lambda f: _synth(f, "--precip-mm-h", "5", "--wind-speed-m-per-s", "500"), "clear",
         match=r"--wind-speed-m-per-s 500"),
    Case("synth-output-exists", "metegs-synth", _existing_output, "clear", match=r"rainy exists", check=_kept),
    Case(
        "synth-unknown-kind", "metegs-synth", lambda f: _synth(f, "--kinds", "snow"), "clear", match=r"kinds='snow'"
    ),
    Case(
        "synth-zero-exposure",
        "metegs-synth",
        lambda f: _synth(f, "--exposure-s", "0"),
        "clear",
        match=r"--exposure-s 0",
    ),
    Case(
        "synth-negative-capture-width",
        "metegs-synth",
        lambda f: _synth(f, "--capture-width-px", "-1"),
        "clear",
        match=r"--capture-width-px -1",
    ),
    Case(
        "synth-nan-precipitation",
        "metegs-synth",
        lambda f: _synth(f, "--precip-mm-h", "nan"),
        "clear",
        match=r"--precip-mm-h nan",
    ),
    Case(
        "synth-negative-metres-per-unit",
        "metegs-synth",
        lambda f: _synth(f, "--metres-per-unit", "-3"),
        "clear",
        match=r"--metres-per-unit -3",
    ),
    Case(
        "synth-tiny-scene-width",
        "metegs-synth",
        lambda f: _synth(f, "--dataset.synthetic.width", "0"),
        "clear",
        match=r"--dataset\.synthetic\.width 0",
    ),
    Case(
        "synth-missing-data",
        "metegs-synth",
        lambda f: _synth(f, "--data", "no-such-scene"),
        "clear",
        match=r"no-such-scene",
    ),
    Case(
        "synth-depth-from-not-a-run",
        "metegs-synth",
        lambda f: _synth(f, "--depth-from", f),
        "clear",
        match=r"config\.yml",
    ),
    Case(
        "synth-output-under-a-file",
        "metegs-synth",
        lambda f: ["--output", _blocker(f) / "rainy", *SYNTH_TINY],
        "clear",
        match=r"blocker",
    ),
    # metegs-process-images
    Case(
        "process-images-missing-folder",
        "metegs-process-images",
        lambda f: ["no-photos", Path(f) / "out"],
        "clear",
        match=r"no-photos: photo folder does not exist",
    ),
    Case(
        "process-images-empty-folder",
        "metegs-process-images",
        lambda f: [_photos(f), Path(f) / "out"],
        "clear",
        match=r"photos: no photos found",
    ),
    Case(
        "process-images-output-exists",
        "metegs-process-images",
        lambda f: [_photos(f), os.makedirs(Path(f) / "out") or Path(f) / "out"],
        "clear",
        match=r"out exists",
    ),
    Case(
        "process-images-folder-is-a-file",
        "metegs-process-images",
        lambda f: [_blocker(f), Path(f) / "out"],
        "clear",
        match=r"blocker",
    ),
    # metegs-view options (refused before a server starts)
    Case("view-port-out-of-range", "metegs-view", lambda f: [f, "--port", "99999"], "clear", match=r"--port 99999"),
    Case("view-max-side-zero", "metegs-view", lambda f: [f, "--max-side", "0"], "clear", match=r"--max-side 0"),
    Case("view-not-a-run", "metegs-view", lambda f: [f], "clear", match=r"config\.yml.*not a metegs run folder"),
    Case(
        "view-missing-ply", "metegs-view", lambda f: [trained_run(f), "--ply", "none.ply"], "clear", match=r"none\.ply"
    ),
]
# fmt: on
