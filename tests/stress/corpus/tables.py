"""Every case of the corpus: the ``CASES`` lists of the ``cases_*.py`` modules in this folder."""

from __future__ import annotations

import importlib
from collections import Counter
from pathlib import Path

from corpus.harness import Case


def all_cases() -> list[Case]:
    """The cases of every ``cases_*.py`` module, in file order; ids are unique."""
    cases: list[Case] = []
    for path in sorted(Path(__file__).parent.glob("cases_*.py")):
        cases += importlib.import_module(f"corpus.{path.stem}").CASES
    ids = Counter(c.id for c in cases)
    repeated = [i for i, n in ids.items() if n > 1]
    if repeated:
        raise ValueError(f"corpus case ids used twice: {repeated}")
    return cases
