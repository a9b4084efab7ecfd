"""The compiled extension's build lock: one build per folder at a time, and none left held by a killed build.

torch's `cpp_extension.load` guards a build folder with a plain ``lock`` file that a killed build (Ctrl-C at the
wrong moment, ``kill -9``, the OOM killer) leaves behind, after which every later load waits for it forever. metegs
takes its own lock first, an ``flock`` that the kernel releases when its holder dies however it dies; whoever holds
it is the only metegs process in the folder, so a torch ``lock`` file found then is a dead build's and is removed.
"""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Iterator
from pathlib import Path

try:
    import fcntl
except ImportError:  # not POSIX: torch's own lock only
    fcntl = None

LOCK_NAME = "metegs-build.lock"
"""metegs' lock file in the build folder; it holds the PID of the process that has it."""

TORCH_LOCK_NAME = "lock"
"""The lock file `torch.utils.cpp_extension` creates in the build folder for the length of a build."""


def _say(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


@contextlib.contextmanager
def build_lock(build_dir: Path, what: str = "the metegs CPU rasteriser") -> Iterator[None]:
    """Hold the build lock of ``build_dir`` for the block: wait (saying for which process) while another process
    builds, and remove a torch ``lock`` file left by a build that was killed (saying so)."""
    if fcntl is None:
        yield
        return
    build_dir = Path(build_dir)
    build_dir.mkdir(parents=True, exist_ok=True)
    with open(build_dir / LOCK_NAME, "a+", encoding="utf-8") as f:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            f.seek(0)
            owner = f.read().strip() or "?"
            _say(f"waiting for process {owner}, which is building {what} in {build_dir} ...")
            fcntl.flock(f, fcntl.LOCK_EX)
        f.seek(0)
        f.truncate()
        f.write(str(os.getpid()))
        f.flush()
        stale = build_dir / TORCH_LOCK_NAME
        if stale.exists():
            stale.unlink(missing_ok=True)
            _say(f"removed {stale}, the lock of an earlier build of {what} that was killed before it finished")
        try:
            yield
        finally:
            f.seek(0)
            f.truncate()
            fcntl.flock(f, fcntl.LOCK_UN)
