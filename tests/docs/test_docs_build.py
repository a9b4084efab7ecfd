"""The documentation site builds with `mkdocs build --strict` without a warning, every page of the nav becomes an
HTML page, and the commands and presets the pages name exist."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10: pytest itself depends on tomli there
    import tomli as tomllib

ROOT = Path(__file__).resolve().parents[2]
DOCS = ROOT / "docs"
MKDOCS_YML = ROOT / "mkdocs.yml"


class _Loader(yaml.SafeLoader):
    """A safe loader that reads mkdocs.yml even if it gains ``!!python/name:`` or ``!ENV`` tags (their values
    are not needed here)."""


_Loader.add_multi_constructor("", lambda loader, suffix, node: None)


def mkdocs_config() -> dict:
    return yaml.load(MKDOCS_YML.read_text(encoding="utf-8"), Loader=_Loader)


def nav_pages(nav) -> list[str]:
    """Every Markdown page named in a mkdocs ``nav`` (nested sections included; external links left out)."""
    pages: list[str] = []
    if isinstance(nav, str):
        if not re.match(r"^[a-z]+://", nav):
            pages.append(nav)
    elif isinstance(nav, list):
        for item in nav:
            pages += nav_pages(item)
    elif isinstance(nav, dict):
        for value in nav.values():
            pages += nav_pages(value)
    return pages


def html_path(page: str, use_directory_urls: bool) -> Path:
    """Where mkdocs writes the HTML of a Markdown page (``a/b.md`` -> ``a/b/index.html`` with directory URLs)."""
    stem = Path(page).with_suffix("")
    if stem.name == "index" or not use_directory_urls:
        return stem.with_suffix(".html")
    return stem / "index.html"


def doc_pages() -> list[Path]:
    return sorted(DOCS.rglob("*.md"))


def test_site_builds_strict_without_warnings(tmp_path):
    pytest.importorskip("mkdocs", reason="mkdocs is not installed (pip install mkdocs); CI installs it")
    site = tmp_path / "site"
    result = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(site)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    output = result.stdout + result.stderr
    assert result.returncode == 0, f"mkdocs build --strict failed:\n{output}"
    assert "WARNING" not in output, f"mkdocs build printed warnings:\n{output}"

    config = mkdocs_config()
    pages = nav_pages(config.get("nav"))
    assert pages, "mkdocs.yml has no nav"
    use_directory_urls = config.get("use_directory_urls", True)
    missing = [p for p in pages if not (site / html_path(p, use_directory_urls)).is_file()]
    assert not missing, f"nav pages without an HTML page in the built site: {missing}"


def test_every_doc_page_is_in_the_nav():
    pages = set(nav_pages(mkdocs_config().get("nav")))
    on_disk = {p.relative_to(DOCS).as_posix() for p in doc_pages()}
    assert on_disk <= pages, f"pages missing from the nav in mkdocs.yml: {sorted(on_disk - pages)}"
    assert pages <= on_disk, f"nav entries without a page in docs/: {sorted(pages - on_disk)}"


FENCE = re.compile(r"^(`{3,}|~{3,})\s*([\w+-]*)[^\n]*\n(.*?)^\1\s*$", re.MULTILINE | re.DOTALL)
SHELL_LANGUAGES = {"bash", "sh", "shell", "console", "zsh"}
COMMAND_AT_START = re.compile(
    r"(?:^|&&|\|\||[;|]|\$\()\s*(?:\$\s+)?(?:[A-Za-z_][A-Za-z0-9_]*=\S*\s+)*(metegs-[a-z][a-z0-9-]*)\b", re.MULTILINE
)
INLINE_COMMAND = re.compile(r"`(metegs-[a-z][a-z0-9-]*)(?:\s[^`\n]*)?`")


def documented_commands() -> dict[str, list[str]]:
    """``metegs-*`` names used as commands in the docs -> the pages using them.

    A name counts as a command where it is run: in command position in a shell code block, or as the first word
    of an inline code span (```metegs-eval RUN```). Method, package and plugin names (``metegs-full``,
    ``metegs-snow``) appear elsewhere and are not commands."""
    found: dict[str, list[str]] = {}
    for page in doc_pages():
        text = page.read_text(encoding="utf-8")
        names: set[str] = set()
        for fence in FENCE.finditer(text):
            if fence.group(2).lower() in SHELL_LANGUAGES:
                names.update(m.group(1) for m in COMMAND_AT_START.finditer(fence.group(3)))
        prose = FENCE.sub("", text)
        for span in INLINE_COMMAND.finditer(prose):
            content = span.group(0).strip("`")
            if " " in content or span.group(1) in ("metegs-train", "metegs-bench", "metegs-meteo"):
                names.add(span.group(1))
        for name in names:
            found.setdefault(name, []).append(page.name)
    return found


def test_documented_console_scripts_exist():
    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]["scripts"]
    commands = documented_commands()
    assert "metegs-train" in commands, "no metegs-train command found in the docs: the command search is broken"
    unknown = {name: pages for name, pages in commands.items() if name not in scripts}
    assert not unknown, f"commands named in the docs but not in pyproject.toml [project.scripts]: {unknown}"


PRESET = re.compile(r"\bconfigs/[A-Za-z0-9_./-]+?\.ya?ml\b")


def test_documented_presets_exist():
    mentioned: dict[str, list[str]] = {}
    for page in doc_pages():
        for match in PRESET.finditer(page.read_text(encoding="utf-8")):
            mentioned.setdefault(match.group(0), []).append(page.name)
    assert mentioned, "no configs/*.yaml preset is mentioned in the docs"
    missing = {path: pages for path, pages in mentioned.items() if not (ROOT / path).is_file()}
    assert not missing, f"presets named in the docs that do not exist: {missing}"
