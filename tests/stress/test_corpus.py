"""The bad-input corpus (tests/stress/corpus/): every case gives a clear error naming the file or field, or a
correct result; no traceback, no silent wrong result."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))

from corpus.harness import run_case  # noqa: E402
from corpus.tables import all_cases  # noqa: E402

CASES = all_cases()


@pytest.mark.parametrize("case", [pytest.param(c, id=c.id, marks=c.marks) for c in CASES])
def test_case(case, tmp_path, capsys, monkeypatch):
    run_case(case, tmp_path, capsys, monkeypatch)


def test_corpus_is_large_and_balanced():
    """The corpus covers at least the 145 kinds of the trust campaign, every command, and both classes."""
    assert len(CASES) >= 145
    assert {c.expect for c in CASES} == {"clear", "correct"}
