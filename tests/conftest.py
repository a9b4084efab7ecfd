"""Test session settings."""

import os

import torch

if os.environ.get("PYTEST_XDIST_WORKER"):
    # Each xdist worker gets one thread: torch's OpenMP threads busy-wait, and two workers with two
    # threads each on a 2-core machine slow each other down many times over.
    torch.set_num_threads(1)
