"""Runs, checkpoints, run folders, options and outputs: metegs-train, -eval, -render, -view."""

from __future__ import annotations

import json
import pickle
import shutil
from pathlib import Path

import pytest
import torch

from corpus.harness import QUIET_RUN, TINY_SCENE, Case, Result, trained_run

# --- inputs ------------------------------------------------------------------------------------------------------


def _train(folder, *extra, method="3dgs", name="run"):
    args = [method, *TINY_SCENE, *QUIET_RUN, "--output-dir", Path(folder) / "out", "--experiment-name", name, *extra]
    return [str(a) for a in args]


def _latest(run: Path) -> Path:
    return sorted((run / "checkpoints").glob("*.ckpt"))[-1]


class CodePayload:
    """Unpickling this writes the marker file: what a crafted checkpoint would do with real code."""

    def __init__(self, marker: Path):
        self.marker = str(marker)

    def __reduce__(self):
        return exec, (f"open({self.marker!r}, 'w').write('code ran')",)


def _marker(folder: Path) -> Path:
    return Path(folder) / "code-ran.txt"


def _crafted(folder: Path, kind: str = "zip") -> Path:
    """A checkpoint that runs code when unpickled: torch's zip format, its legacy format, or a raw pickle."""
    payload = {"step": 0, "params": {}, "sh_degree": 0, "x": CodePayload(_marker(folder))}
    path = Path(folder) / f"crafted-{kind}.ckpt"
    if kind == "raw":
        path.write_bytes(pickle.dumps(payload))
    else:
        torch.save(payload, path, _use_new_zipfile_serialization=kind == "zip")
    return path


def _crafted_latest(folder: Path, kind: str = "zip") -> Path:
    """A finished run whose latest checkpoint is a crafted one."""
    run = trained_run(folder)
    shutil.copy(_crafted(folder, kind), run / "checkpoints" / "step-999999.ckpt")
    return run


def _edited(folder: Path, edit) -> tuple[Path, Path]:
    """A finished run and a copy of its latest checkpoint changed by ``edit(payload)``."""
    run = trained_run(folder)
    payload = torch.load(_latest(run), weights_only=True)
    edited = edit(payload)
    payload = edited if isinstance(edited, dict) else payload
    path = Path(folder) / "edited.ckpt"
    torch.save(payload, path)
    return run, path


def _set_param(name, value):
    def edit(p):
        p["params"][name][0].fill_(value)

    return edit


def _no_code_ran(result: Result) -> None:
    assert not _marker(result.folder).exists(), "the crafted checkpoint ran its code"


def _metrics(run: Path) -> dict:
    return json.loads((run / "metrics.json").read_text())


# --- checks of correct results -----------------------------------------------------------------------------------


def _finished(result: Result, run="out/synthetic/3dgs/run", steps=4) -> None:
    metrics = _metrics(result.folder / run)
    assert metrics["steps"] == steps and metrics["psnr"] > 5


def _evaluated(result: Result) -> None:
    m = json.loads((result.folder / "run/eval.json").read_text())
    assert m["psnr"] > 5 and m["num_gaussians"] > 0


def _rendered(result: Result) -> None:
    assert len(list((result.folder / "run/renders/test-render").glob("*.png"))) == 2


def _second_name_refused(result: Result) -> None:
    first = _metrics(result.folder / "out/synthetic/3dgs/run")
    assert first["steps"] == 4, "the first run's results were replaced"


def _resumed(result: Result) -> None:
    _finished(result, steps=8)
    assert (result.folder / "out/synthetic/3dgs/run/checkpoints/step-000008.ckpt").is_file()


def _printed_metrics(result: Result) -> None:
    assert '"psnr"' in result.stdout, "the metrics were lost with the failed write"


# --- builders of two-step inputs ---------------------------------------------------------------------------------


def _train_twice(folder, *second):
    from metegs.cli.train import main

    main(_train(folder))
    return _train(folder, *second)


def _resume(folder):
    from metegs.cli.train import main

    main(_train(folder))
    return _train(folder, "--max-steps", "8", "--load-checkpoint", folder / "out/synthetic/3dgs/run/checkpoints")


def _config(folder, text):
    path = Path(folder) / "c.yaml"
    path.write_text(text)
    return ["3dgs", "--config", str(path)]


def _run_with_config(folder, text):
    run = trained_run(folder)
    (run / "config.yml").write_text(text)
    return [run]


def _moved_run(folder):
    run = trained_run(folder)
    (Path(folder) / "elsewhere").mkdir()
    return [run, "--output", Path(folder) / "run/eval.json"]


def _legacy_checkpoint(folder):
    """A checkpoint from before checkpoints recorded their method and scene."""

    def edit(p):
        del p["method"], p["scene"]

    run, path = _edited(folder, edit)
    return [run, "--checkpoint", path]


def _tensor_file(folder):
    path = Path(folder) / "tensor.ckpt"
    torch.save(torch.zeros(3), path)
    return path


def _bytes(folder, name, data):
    path = Path(folder) / name
    path.write_bytes(data)
    return path


def _truncated_checkpoint(folder):
    run = trained_run(folder)
    data = _latest(run).read_bytes()
    return [run, "--checkpoint", _bytes(folder, "half.ckpt", data[: len(data) // 2])]


def _empty_folder(folder):
    path = Path(folder) / "empty"
    path.mkdir()
    return path


def _file_as_folder(folder, name="blocker"):
    path = Path(folder) / name
    path.write_text("a file where a folder is expected")
    return path


# --- the table ---------------------------------------------------------------------------------------------------

REFUSED = r"crafted-\w+\.ckpt: refused"
LATEST_REFUSED = r"step-999999\.ckpt: refused"

# The cases are a table to read down: one case on one or two lines.
# fmt: off
CASES = [
    # a training run that only has to finish, and re-opening it
    Case("train-tiny", "metegs-train", lambda f: _train(f), "correct", check=_finished),
    Case("eval-finished-run", "metegs-eval", lambda f: [trained_run(f)], "correct", check=_evaluated),
    Case("render-finished-run", "metegs-render", lambda f: [trained_run(f)], "correct", check=_rendered),
    Case("eval-run-from-another-folder", "metegs-eval", _moved_run, "correct", check=_evaluated),
    Case("eval-checkpoint-without-method-record", "metegs-eval", _legacy_checkpoint, "correct", check=_evaluated),
    Case("eval-run-scene-ply", "metegs-eval", lambda f: [trained_run(f), "--ply", Path(f) / "run/scene.ply"],
         "correct", check=_evaluated),
    Case("resume-explicitly-in-same-folder", "metegs-train", _resume, "correct", check=_resumed),
    Case("eval-run-given-as-its-config-yml", "metegs-eval", lambda f: [trained_run(f) / "config.yml"], "correct",
         check=_evaluated),
    Case("render-run-given-as-its-config-yml", "metegs-render", lambda f: [trained_run(f) / "config.yml"],
         "correct", check=_rendered),
    Case("train-load-config-of-a-run", "metegs-train",
         lambda f: ["--load-config", trained_run(f) / "config.yml", *_train(f)[1:]], "correct", check=_finished),
    Case("train-config-file", "metegs-train", lambda f: [*_config(f, "max_steps: 4\n"), *_train(f)[1:]],
         "correct", check=_finished),
    # crafted checkpoints: no code runs through any command
    Case("train-crafted-zip-ckpt", "metegs-train", lambda f: _train(f, "--load-checkpoint", _crafted(f)), "clear",
         match=REFUSED, check=_no_code_ran),
    Case("train-crafted-legacy-ckpt", "metegs-train", lambda f: _train(f, "--load-checkpoint", _crafted(f, "legacy")),
         "clear", match=REFUSED, check=_no_code_ran),
    Case("train-crafted-raw-pickle", "metegs-train", lambda f: _train(f, "--load-checkpoint", _crafted(f, "raw")),
         "clear", match=REFUSED, check=_no_code_ran),
    Case("eval-crafted-latest", "metegs-eval", lambda f: [_crafted_latest(f)], "clear", match=LATEST_REFUSED,
         check=_no_code_ran),
    Case("eval-crafted-raw-latest", "metegs-eval", lambda f: [_crafted_latest(f, "raw")], "clear",
         match=LATEST_REFUSED, check=_no_code_ran),
    Case("eval-crafted-checkpoint-flag", "metegs-eval", lambda f: [trained_run(f), "--checkpoint", _crafted(f)],
         "clear", match=REFUSED, check=_no_code_ran),
    Case("render-crafted-latest", "metegs-render", lambda f: [_crafted_latest(f)], "clear", match=LATEST_REFUSED,
         check=_no_code_ran),
    Case("render-crafted-checkpoint-flag", "metegs-render",
         lambda f: [trained_run(f), "--checkpoint", _crafted(f, "legacy")], "clear", match=REFUSED,
         check=_no_code_ran),
    Case("view-crafted-latest", "metegs-view", lambda f: [_crafted_latest(f)], "clear", match=LATEST_REFUSED,
         check=_no_code_ran),
    Case("view-crafted-checkpoint-flag", "metegs-view", lambda f: [trained_run(f), "--checkpoint", _crafted(f, "raw")],
         "clear", match=REFUSED, check=_no_code_ran),
    # checkpoints that are not, or no longer, sound
    Case("eval-truncated-checkpoint", "metegs-eval", _truncated_checkpoint, "clear", match=r"half\.ckpt"),
    Case("eval-empty-checkpoint", "metegs-eval", lambda f: [trained_run(f), "--checkpoint", _bytes(f, "e.ckpt", b"")],
         "clear", match=r"e\.ckpt"),
    Case("eval-text-as-checkpoint", "metegs-eval",
         lambda f: [trained_run(f), "--checkpoint", _bytes(f, "t.ckpt", b"step: 3\nparams: none\n")], "clear",
         match=r"t\.ckpt"),
    Case("eval-tensor-as-checkpoint", "metegs-eval", lambda f: [trained_run(f), "--checkpoint", _tensor_file(f)],
         "clear", match=r"tensor\.ckpt: not a metegs checkpoint"),
    Case("eval-dict-without-params", "metegs-eval", lambda f: [*_edited(f, lambda p: {"step": 1})[:1], "--checkpoint",
         Path(f) / "edited.ckpt"], "clear", match=r"edited\.ckpt: not a metegs checkpoint \(missing 'params'"),
    Case("eval-nan-means", "metegs-eval", lambda f: ["--checkpoint", *reversed(_edited(f, _set_param("means", float("nan"))))],
         "clear", match=r"edited\.ckpt: params\['means'\] holds 3 non-finite"),
    Case("render-inf-scales", "metegs-render", lambda f: ["--checkpoint", *reversed(_edited(f, _set_param("scales", float("inf"))))],
         "clear", match=r"params\['scales'\] holds 3 non-finite"),
    Case("train-resume-nan-opacities", "metegs-train",
         lambda f: _train(f, "--load-checkpoint", _edited(f, _set_param("opacities", float("nan")))[1]), "clear",
         match=r"params\['opacities'\].*non-finite.*use an earlier one"),
    Case("eval-shape-mismatch", "metegs-eval",
         lambda f: ["--checkpoint", *reversed(_edited(f, lambda p: p["params"].update(quats=p["params"]["quats"][1:])))],
         "clear", match=r"params\['quats'\] has shape"),
    Case("eval-bad-sh-degree", "metegs-eval", lambda f: ["--checkpoint", *reversed(_edited(f, lambda p: p.update(sh_degree=7)))],
         "clear", match=r"field 'sh_degree' is 7"),
    Case("eval-negative-step", "metegs-eval", lambda f: ["--checkpoint", *reversed(_edited(f, lambda p: p.update(step=-4)))],
         "clear", match=r"field 'step' is -4"),
    Case("eval-params-missing-quats", "metegs-eval",
         lambda f: ["--checkpoint", *reversed(_edited(f, lambda p: p["params"].pop("quats")))], "clear",
         match=r"field 'params' has no 'quats'"),
    Case("eval-integer-params", "metegs-eval",
         lambda f: ["--checkpoint", *reversed(_edited(f, lambda p: p["params"].update(sh0=p["params"]["sh0"].long())))],
         "clear", match=r"params\['sh0'\] is torch.int64"),
    Case("train-resume-other-method", "metegs-train",
         lambda f: _train(f, "--load-checkpoint", _edited(f, lambda p: p.update(method="metegs-full"))[1]), "clear",
         match=r"a checkpoint of method 'metegs-full', not of '3dgs'"),
    Case("train-resume-other-scene", "metegs-train",
         lambda f: _train(f, "--load-checkpoint", _edited(f, lambda p: p["scene"].update(num_views=66))[1]), "clear",
         match=r"edited\.ckpt: made for another scene: its num_views is 66"),
    Case("train-resume-other-scene-extent", "metegs-train",
         lambda f: _train(f, "--load-checkpoint", _edited(f, lambda p: p["scene"].update(extent=123.0))[1]), "clear",
         match=r"made for another scene: its extent is 123"),
    Case("train-resume-missing-file", "metegs-train", lambda f: _train(f, "--load-checkpoint", "nope.ckpt"), "clear",
         match=r"nope\.ckpt: checkpoint file not found"),
    Case("train-resume-empty-folder", "metegs-train",
         lambda f: _train(f, "--load-checkpoint", _empty_folder(f)), "clear", match=r"empty: no \.ckpt checkpoint"),
    Case("eval-not-a-run-folder", "metegs-eval", lambda f: [f], "clear", match=r"config\.yml.*not a metegs run folder"),
    Case("eval-run-without-checkpoints", "metegs-eval",
         lambda f: [shutil.rmtree(trained_run(f) / "checkpoints") or Path(f) / "run"], "clear",
         match=r"checkpoints.*(checkpoint file not found|no \.ckpt)"),
    Case("eval-broken-config-yaml", "metegs-eval", lambda f: _run_with_config(f, "method: 3dgs\nmax_steps: [\n"),
         "clear", match=r"config\.yml"),
    Case("eval-config-unknown-method", "metegs-eval", lambda f: _run_with_config(f, "method: nerf-w\n"), "clear",
         match=r"config\.yml.*nerf-w"),
    Case("eval-config-typo", "metegs-eval", lambda f: _run_with_config(f, "method: 3dgs\nmax_stepz: 3\n"), "clear",
         match=r"config\.yml.*max_stepz"),
    Case("eval-config-negative-lr", "metegs-eval",
         lambda f: _run_with_config(f, "method: 3dgs\noptim:\n  means_lr: -1\n"), "clear",
         match=r"config\.yml.*--optim\.means-lr -1"),
    Case("eval-missing-ply", "metegs-eval", lambda f: [trained_run(f), "--ply", "missing.ply"], "clear",
         match=r"missing\.ply"),
    # run folders are never reused
    Case("train-same-experiment-name-twice", "metegs-train", lambda f: _train_twice(f), "clear",
         match=r"out/synthetic/3dgs/run: the run folder exists", check=_second_name_refused),
    Case("train-experiment-name-escapes", "metegs-train", lambda f: _train(f, name="../../escape"), "clear",
         match=r"--experiment-name '\.\./\.\./escape'"),
    Case("train-experiment-name-with-slash", "metegs-train", lambda f: _train(f, name="a/b"), "clear",
         match=r"--experiment-name 'a/b'"),
    Case("train-experiment-name-dotdot", "metegs-train", lambda f: _train(f, name=".."), "clear",
         match=r"--experiment-name '\.\.'"),
    Case("train-output-dir-is-a-file", "metegs-train",
         lambda f: [*_train(f)[:-4], "--output-dir", _file_as_folder(f), "--experiment-name", "run"], "clear",
         match=r"blocker"),
    Case("eval-output-under-a-file", "metegs-eval",
         lambda f: [trained_run(f), "--output", _file_as_folder(f) / "eval.json"], "clear",
         match=r"blocker/eval\.json: cannot write", check=_printed_metrics),
    Case("render-output-under-a-file", "metegs-render",
         lambda f: [trained_run(f), "--output", _file_as_folder(f) / "renders"], "clear", match=r"blocker"),
    # a scene that cannot be trained
    Case("train-one-training-view", "metegs-train",
         lambda f: _train(f, "--dataset.synthetic.num-views", "2", "--dataset.test-every", "2"), "clear",
         match=r"1 training view\(s\).*at least 2"),
    Case("train-no-training-view", "metegs-train",
         lambda f: _train(f, "--dataset.synthetic.num-views", "2", "--dataset.test-every", "1"), "clear",
         match=r"training view"),
    Case("train-data-missing", "metegs-train", lambda f: _train(f, "--data", "no-such-scene"), "clear",
         match=r"no-such-scene"),
    Case("train-data-is-a-file", "metegs-train", lambda f: _train(f, "--data", _file_as_folder(f, "scene.txt")),
         "clear", match=r"scene\.txt"),
    Case("train-unknown-parser", "metegs-train", lambda f: _train(f, "--parser", "nerfw"), "clear", match=r"nerfw"),
    Case("train-cuda-without-gpu", "metegs-train", lambda f: _train(f, "--device", "cuda"), "clear",
         match=r"--device cuda: CUDA is not available",
         marks=[pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a GPU")]),
    Case("train-unknown-backend", "metegs-train", lambda f: _train(f, "--backend", "vulkan"), "clear",
         match=r"vulkan"),
    Case("train-config-file-missing", "metegs-train", lambda f: ["3dgs", "--config", "missing.yaml"], "clear",
         match=r"missing\.yaml: config file not found"),
    Case("train-config-file-broken", "metegs-train", lambda f: _config(f, "max_steps: [\n"), "clear",
         match=r"c\.yaml"),
    Case("train-config-file-negative-lr", "metegs-train", lambda f: _config(f, "optim:\n  scales_lr: -0.1\n"),
         "clear", match=r"c\.yaml.*--optim\.scales-lr -0\.1"),
    Case("train-config-file-not-a-mapping", "metegs-train", lambda f: _config(f, "- 1\n- 2\n"), "clear",
         match=r"c\.yaml"),
    Case("train-config-file-wrong-type", "metegs-train", lambda f: _config(f, "max_steps: many\n"), "clear",
         match=r"c\.yaml.*max_steps"),
]
# fmt: on

# option values refused when the command line is parsed, before anything runs: (flag, value, method)
BAD_OPTIONS = [
    *[(f"--optim.{name}", "-1", "3dgs") for name in ("means-lr", "means-lr-final", "sh0-lr", "shN-lr", "opacities-lr",
                                                       "scales-lr", "quats-lr")],
    ("--optim.eps", "0", "3dgs"), ("--optim.means-lr", "nan", "3dgs"), ("--optim.opacities-lr", "inf", "3dgs"),
    ("--model.sh-degree", "10", "3dgs"), ("--model.sh-degree", "-1", "3dgs"), ("--model.init-opacity", "0", "3dgs"),
    ("--model.init-opacity", "1.5", "3dgs"), ("--model.init-scale-multiplier", "0", "3dgs"),
    ("--model.init-random-points", "0", "3dgs"), ("--model.sh-degree-every", "-0.5", "3dgs"),
    ("--max-steps", "0", "3dgs"), ("--max-steps", "-5", "3dgs"), ("--eval-every", "2", "3dgs"),
    ("--checkpoint-every", "-1", "3dgs"), ("--threads", "-1", "3dgs"), ("--torch-threads", "-2", "3dgs"),
    ("--viewer-port", "70000", "3dgs"), ("--dataset.auto-max-side", "0", "3dgs"), ("--dataset.test-every", "-1", "3dgs"),
    ("--dataset.synthetic.width", "0", "3dgs"), ("--dataset.synthetic.num-views", "1", "3dgs"),
    ("--dataset.synthetic.metres-per-unit", "-10", "3dgs"), ("--densify.refine-every", "0", "3dgs"),
    ("--densify.prune-opacity", "2", "3dgs"), ("--densify.max-gaussians", "0", "3dgs"),
    ("--densify.grow-grad2d", "nan", "3dgs"), ("--densify.refine-start", "1.5", "3dgs"),
    ("--loss.ssim-lambda", "1.5", "3dgs"), ("--weights.photo", "-1", "metegs-full"),
    ("--weights.perceptual", "inf", "metegs-full"), ("--gtn.lr", "nan", "metegs-full"),
    ("--gtn.max-factor", "0.5", "metegs-full"), ("--gtn.width", "0", "metegs-full"),
    ("--weather-lr", "-1", "metegs-full"),
]  # fmt: skip

CASES += [
    Case(
        f"option{flag.replace('--', '-')}={value}-{method}",
        "metegs-train",
        lambda f, flag=flag, value=value, method=method: _train(f, flag, value, method=method),
        "clear",
        match=rf"{flag.replace('.', '[.]')} {value}",
    )
    for flag, value, method in BAD_OPTIONS
]
