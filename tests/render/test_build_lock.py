"""The extension's build lock: a killed build never blocks later runs, and a waiting run says for whom it waits."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest

from metegs.render.build_lock import LOCK_NAME, TORCH_LOCK_NAME, build_lock

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="flock is POSIX")

HOLD = textwrap.dedent("""
    import fcntl, os, sys, time
    f = open(sys.argv[1], "a+")
    fcntl.flock(f, fcntl.LOCK_EX)
    f.seek(0); f.truncate(); f.write(str(os.getpid())); f.flush()
    print("held", flush=True)
    time.sleep(float(sys.argv[2]))
""")


def _holder(path, seconds):
    proc = subprocess.Popen([sys.executable, "-c", HOLD, str(path), str(seconds)], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "held"
    return proc


def test_a_killed_builds_torch_lock_is_removed_with_a_message(tmp_path, capsys):
    (tmp_path / TORCH_LOCK_NAME).touch()  # what torch's FileBaton leaves when its build is killed
    with build_lock(tmp_path):
        assert not (tmp_path / TORCH_LOCK_NAME).exists()
        assert (tmp_path / LOCK_NAME).read_text() == str(os.getpid())
    assert "killed before it finished" in capsys.readouterr().err


def test_waits_for_a_live_builder_and_names_it(tmp_path, capsys):
    proc = _holder(tmp_path / LOCK_NAME, 1.5)
    (tmp_path / TORCH_LOCK_NAME).touch()  # the live build's own lock: must survive until it is done
    t0 = time.monotonic()
    with build_lock(tmp_path):
        waited = time.monotonic() - t0
    proc.wait()
    assert waited > 0.5
    assert f"waiting for process {proc.pid}" in capsys.readouterr().err


def test_a_builder_killed_with_sigkill_releases_the_lock(tmp_path):
    proc = _holder(tmp_path / LOCK_NAME, 60)
    proc.kill()
    proc.wait()
    t0 = time.monotonic()
    with build_lock(tmp_path):
        assert time.monotonic() - t0 < 5


LOAD = "from metegs.bench.peak import PROBE; PROBE.load(); print('loaded')"


@pytest.mark.slow
def test_a_build_killed_half_way_does_not_hang_the_next(tmp_path):
    """kill -9 of a first build (compiler processes included) while it holds torch's lock: the next load builds
    and loads the extension instead of waiting forever. The extension is the peak probe (`metegs.bench.peak`),
    built by the same `build_extension` as the kernels from one small source, in about half their build time."""
    env = dict(os.environ, METEGS_EXTENSIONS_DIR=str(tmp_path))
    build_dir = tmp_path / "peak-probe"
    first = subprocess.Popen([sys.executable, "-c", LOAD], env=env, start_new_session=True,
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
    deadline = time.monotonic() + 120
    while not (build_dir / TORCH_LOCK_NAME).exists():
        assert first.poll() is None, "the first build ended before it took its lock"
        assert time.monotonic() < deadline, "the first build never took its lock"
        time.sleep(0.05)
    time.sleep(1.0)  # the compiler is running
    os.killpg(first.pid, signal.SIGKILL)
    first.wait()
    assert (build_dir / TORCH_LOCK_NAME).exists()
    assert not list(build_dir.glob("*.so")), "the first build finished before it was killed"
    second = subprocess.run([sys.executable, "-c", LOAD], env=env, capture_output=True, text=True, timeout=540)
    assert second.returncode == 0, second.stderr[-2000:]
    assert "loaded" in second.stdout
    assert "killed before it finished" in second.stderr


def _checkout_copy(monkeypatch, cb, folder):
    """Point the backend at a copy of its kernel sources in ``folder`` (another checkout of the same code)."""
    import shutil

    shutil.copytree(cb.CSRC, folder)
    monkeypatch.setattr(cb, "SOURCES", [folder / f.name for f in cb.SOURCES])
    monkeypatch.setattr(cb, "HEADERS", [folder / f.name for f in cb.HEADERS])


def test_checkouts_with_the_same_kernels_share_one_build_folder(tmp_path, monkeypatch):
    from metegs.render import cpu_backend as cb

    monkeypatch.delenv("METEGS_EXTENSIONS_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    here = cb.build_directory(["-O3"])
    _checkout_copy(monkeypatch, cb, tmp_path / "other-checkout")
    assert cb.build_directory(["-O3"]) == here
    assert cb.build_directory(["-O2"]) != here  # other flags, another build
    edited = cb.SOURCES[0]
    edited.write_bytes(edited.read_bytes() + b"\n// edited\n")
    assert cb.build_directory(["-O3"]) != here  # other kernels, another build: neither rebuilds the other's


def test_the_build_reads_copies_that_name_no_checkout(tmp_path, monkeypatch):
    from metegs.render import cpu_backend as cb

    src, changed = cb.stage_sources(tmp_path)
    assert changed and src == tmp_path / "src"
    assert all((src / f.name).read_bytes() == f.read_bytes() for f in cb.SOURCES + cb.HEADERS)
    assert cb.stage_sources(tmp_path) == (src, False)  # nothing rewritten: ninja sees nothing new
    _checkout_copy(monkeypatch, cb, tmp_path / "other-checkout")
    assert cb.stage_sources(tmp_path) == (src, False)
