"""Make the helpers next to the tests and the package's src/ importable without installing it (pytest runs the
tests with --import-mode=importlib, also from the repository root)."""

import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
for folder in (HERE, HERE.parent / "src"):
    if str(folder) not in sys.path:
        sys.path.insert(0, str(folder))
