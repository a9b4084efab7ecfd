"""The import contracts of pyproject.toml ([tool.importlinter]): layers point down, the core imports no layer, the
perceptual loss shares the backbones module with LPIPS (not LPIPS itself), met observations never import their readers."""

from pathlib import Path

import pytest

importlinter_cli = pytest.importorskip("importlinter.cli", reason="import-linter is a dev dependency")

ROOT = Path(__file__).resolve().parents[1]


def test_every_import_contract_is_kept(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(ROOT)
    code = importlinter_cli.lint_imports(
        config_filename=str(ROOT / "pyproject.toml"), cache_dir=str(tmp_path / "cache"), no_logo=True
    )
    out = capsys.readouterr().out
    assert code == 0, out
    assert "Contracts: 3 kept, 0 broken." in out


def test_a_broken_layer_is_caught_in_a_function_level_import(tmp_path, monkeypatch, capsys):
    """With the engine put above synth, the checker names the synthesis pipeline's import of the run loader, which
    sits inside a function."""
    text = (ROOT / "pyproject.toml").read_text()
    broken = text.replace('    "metegs.synth",\n    "metegs.engine",\n', '    "metegs.engine",\n    "metegs.synth",\n')
    assert broken != text
    config = tmp_path / "pyproject.toml"
    config.write_text(broken)
    monkeypatch.chdir(ROOT)
    code = importlinter_cli.lint_imports(config_filename=str(config), cache_dir=str(tmp_path / "cache"), no_logo=True)
    out = capsys.readouterr().out
    assert code != 0 and "metegs.synth.pipeline -> metegs.engine.run" in out
