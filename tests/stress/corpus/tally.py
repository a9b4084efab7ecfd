"""Print the corpus tally by room and expected class: ``python tests/stress/corpus/tally.py``."""

from __future__ import annotations

import sys
from collections import Counter
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from corpus.tables import all_cases  # noqa: E402


def main() -> None:
    cases = all_cases()
    by_class = Counter(c.expect for c in cases)
    by_command = Counter(c.command for c in cases)
    print(f"{len(cases)} cases: " + ", ".join(f"{n} {k}" for k, n in sorted(by_class.items())))
    for command, n in sorted(by_command.items()):
        print(f"  {command}: {n}")


if __name__ == "__main__":
    main()
