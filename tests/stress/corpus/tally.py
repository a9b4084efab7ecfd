"""The corpus tally: ``python tests/stress/corpus/tally.py`` counts the cases by command and expected class;
with ``--run`` it runs them (pytest) and counts what each gave: its class, or "anything else" when it failed."""

from __future__ import annotations

import argparse
import sys
from collections import Counter
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from corpus.tables import all_cases  # noqa: E402


class Outcomes:
    """pytest plugin: the outcome class of every corpus case that ran."""

    def __init__(self, expected: dict[str, str]):
        self.expected = expected
        self.counts: Counter[str] = Counter()

    def pytest_runtest_logreport(self, report) -> None:
        case_id = report.nodeid.partition("test_case[")[2][:-1]
        if case_id not in self.expected:
            return
        if report.when == "call" or (report.when == "setup" and not report.passed):
            self.counts[self.expected[case_id] if report.passed else "anything else"] += 1


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--run", action="store_true", help="run the cases and count their outcomes")
    args, pytest_args = parser.parse_known_args()
    cases = all_cases()
    by_class = Counter(c.expect for c in cases)
    print(f"{len(cases)} cases: " + ", ".join(f"{n} {k}" for k, n in sorted(by_class.items())))
    for command, n in sorted(Counter(c.command for c in cases).items()):
        print(f"  {command}: {n}")
    if args.run:
        import pytest

        outcomes = Outcomes({c.id: c.expect for c in cases})
        pytest.main([str(HERE.parent / "test_corpus.py"), "-q", "-p", "no:cacheprovider", *pytest_args],
                    plugins=[outcomes])  # fmt: skip
        ran = sum(outcomes.counts.values())
        print(f"ran {ran}: " + ", ".join(f"{outcomes.counts[k]} {k}" for k in ("clear", "correct", "anything else")))
        raise SystemExit(0 if ran == len(cases) and not outcomes.counts["anything else"] else 1)


if __name__ == "__main__":
    main()
