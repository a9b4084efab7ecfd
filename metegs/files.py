"""Files metegs writes, written whole or not at all: atomic files (a temporary beside the target, renamed over it)
with the user's umask, results that fall back to standard output, and staged folders (built hidden beside the
output and renamed into place)."""

from __future__ import annotations

import contextlib
import filecmp
import os
import shutil
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path

from metegs.errors import ConfigError, DataError


def _umask() -> int:
    """The process's file-creation mask (read once; Linux reports it in /proc without changing it)."""
    try:
        with open("/proc/self/status", encoding="ascii") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except OSError:
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


NEW_FILE_MODE = 0o666 & ~_umask()
"""Permissions of the files metegs writes: those of any new file under the user's umask (0644 under 022), not
the 0600 of the temporary files they are written through."""


@contextlib.contextmanager
def atomic_output(path: Path, suffix: str = ".tmp") -> Iterator[Path]:
    """A temporary path beside ``path`` to write to; when the block ends without error it is renamed to ``path``
    with `NEW_FILE_MODE`, so a crash never leaves half a file; on error it is removed. ``suffix``: the temporary
    file's extension, for writers that choose a format from it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=suffix)
    os.close(fd)
    tmp = Path(name)
    try:
        yield tmp
        os.chmod(tmp, NEW_FILE_MODE)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` through `atomic_output`."""
    with atomic_output(path) as tmp:
        tmp.write_bytes(data)


def atomic_write_text(path: Path, text: str) -> None:
    """`atomic_write_bytes` of UTF-8 ``text``."""
    atomic_write_bytes(path, text.encode("utf-8"))


def write_result(path: Path, text: str) -> None:
    """`atomic_write_text` of a result that must not be lost: when the write fails, the text goes to standard output
    and a DataError names the path."""
    try:
        atomic_write_text(path, text)
    except OSError as exc:
        print(text, flush=True)
        raise DataError(path, f"cannot write ({exc.strerror or exc}); the result is printed above instead") from None


@contextlib.contextmanager
def staged_output(output: Path, overwrite: bool = False) -> Iterator[Path]:
    """Yield a temp folder next to ``output``; on success it replaces ``output`` by renames, on error it is removed."""
    output = Path(output)
    if output.exists() and not overwrite:
        raise ConfigError(f"{output} exists; choose another --output or pass --overwrite")
    output.parent.mkdir(parents=True, exist_ok=True)
    remove_dead_stages(output)
    tmp = output.parent / f".{output.name}.partial-{os.getpid()}"
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir()
    try:
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    old = None
    if output.exists():
        old = output.parent / f".{output.name}.old-{os.getpid()}"
        os.replace(output, old)
    os.replace(tmp, output)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True) if old.is_dir() else old.unlink(missing_ok=True)


def remove_dead_stages(output: Path) -> list[Path]:
    """Remove the ``.partial-PID`` / ``.old-PID`` folders beside ``output`` whose process no longer runs (a killed
    `staged_output`), saying so on stderr; those of live processes are left alone. Returns the removed paths."""
    removed = []
    for stage in output.parent.glob(f".{output.name}.*-*"):
        kind, _, pid = stage.name[len(output.name) + 2 :].rpartition("-")
        if kind not in ("partial", "old") or not pid.isdigit() or process_alive(int(pid)):
            continue
        shutil.rmtree(stage, ignore_errors=True) if stage.is_dir() else stage.unlink(missing_ok=True)
        print(f"removed {stage}, left by a run (process {pid}) that was killed before it finished", file=sys.stderr)
        removed.append(stage)
    return removed


def process_alive(pid: int) -> bool:
    """Whether a process ``pid`` exists (it may belong to another user)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def same_files(a: Path, b: Path) -> bool:
    """Whether ``a`` and ``b`` hold the same bytes: two files, or two folders with the same files under the same
    names. Hidden names (the caches metegs writes beside a dataset, such as ``.metegs_points``) are left out."""
    a, b = Path(a), Path(b)
    if a.is_file() and b.is_file():
        return filecmp.cmp(a, b, shallow=False)
    if not (a.is_dir() and b.is_dir()):
        return False

    def visible(root: Path) -> list[Path]:
        files = (p.relative_to(root) for p in root.rglob("*") if p.is_file())
        return sorted(p for p in files if not any(part.startswith(".") for part in p.parts))

    names = visible(a)
    return names == visible(b) and all(filecmp.cmp(a / n, b / n, shallow=False) for n in names)
