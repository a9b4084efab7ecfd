"""Process-wide memory-allocator settings for CPU training (glibc only; elsewhere nothing changes)."""

from __future__ import annotations

import ctypes
import functools

M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3
KEEP_FREE_MB = 512
"""Free memory glibc keeps at the top of its heap before it returns any to the system."""
MMAP_FROM_MB = 32
"""Blocks from this size get their own mapping (returned to the system when freed); smaller ones come from the heap."""


@functools.cache
def keep_freed_memory() -> bool:
    """Let glibc reuse freed memory instead of handing it back to the system after every step -> True if set.

    By default glibc gives blocks above its (adaptive) mmap threshold their own mappings and trims the heap top when
    it frees more than twice that; a training step frees and reallocates its images, tile lists and gradients, and
    each new page then costs a page fault (300-500 per step at 20k Gaussians, 300x200: about 1 ms on a virtual
    machine). Freed memory stays with the process up to ``KEEP_FREE_MB``."""
    try:
        libc = ctypes.CDLL(None)  # the process's own symbols: the C library it runs on
        mallopt, _ = libc.mallopt, libc.gnu_get_libc_version  # glibc's; musl and macOS have no mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return bool(mallopt(M_TRIM_THRESHOLD, KEEP_FREE_MB << 20)) and bool(mallopt(M_MMAP_THRESHOLD, MMAP_FROM_MB << 20))
