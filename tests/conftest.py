"""Test session settings."""

import os

import torch

if os.environ.get("PYTEST_XDIST_WORKER"):
    # Each xdist worker gets one thread: torch's OpenMP threads busy-wait, and two workers with two
    # threads each on a 2-core machine slow each other down many times over.
    torch.set_num_threads(1)


import pytest  # noqa: E402


@pytest.fixture(autouse=True)
def _restore_flush_denormal():
    """The trainer turns on flush-to-zero for the process (a speed-up); tests that use it must not leak it
    into later tests (hypothesis refuses to run when subnormal floats cannot be represented)."""
    yield
    torch.set_flush_denormal(False)
