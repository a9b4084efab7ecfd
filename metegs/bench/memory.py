"""Peak memory of a block of work (RSS sampled in a thread on CPU, the allocator's peak on CUDA) and the device
synchronisation that timings need."""

from __future__ import annotations

import ctypes
import os
import threading
import time

import torch


def sync(device: torch.device) -> None:
    """Wait for ``device``'s queued work (CUDA runs asynchronously: a clock read before this times the launch)."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _trim_heap() -> None:
    """Return freed heap pages to the OS (glibc), so that the RSS increase of the next block is its own."""
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


def rss_mb() -> float:
    """Current resident set size of this process (MB)."""
    return PeakMemory._rss() / 2**20


class PeakMemory:
    """Peak memory above the starting level while the block runs (CPU: RSS sampled every 0.5 ms)."""

    def __init__(self, device: torch.device):
        self.device = device
        self.peak_mb = 0.0

    @staticmethod
    def _rss() -> int:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")

    def __enter__(self):
        if self.device.type == "cuda":
            sync(self.device)
            torch.cuda.reset_peak_memory_stats(self.device)
            self._base = torch.cuda.memory_allocated(self.device)
            return self
        _trim_heap()
        self._base = self._peak = self._rss()
        self._stop = threading.Event()

        def sample():
            while not self._stop.is_set():
                self._peak = max(self._peak, self._rss())
                time.sleep(0.0005)

        self._thread = threading.Thread(target=sample, daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc):
        if self.device.type == "cuda":
            sync(self.device)
            self.peak_mb = (torch.cuda.max_memory_allocated(self.device) - self._base) / 2**20
        else:
            self._stop.set()
            self._thread.join()
            self._peak = max(self._peak, self._rss())
            self.peak_mb = (self._peak - self._base) / 2**20
