"""Keep freed memory in the process: the operators' arrays are allocated again at once.

An operator call allocates and frees the same few dozen image-sized numpy arrays (0.3-4 MB:
depth point clouds, renderings, masks) every time. glibc serves an allocation above its mmap
threshold (128 KB at first, raised only as large blocks are freed) with a fresh mmap, whose pages
fault in one by one, zero-filled, and trims freed heap memory back to the system. Measured on an
ICP refinement plus the scoring after it (60 calls, one core): 3,400 minor page faults a call;
with the thresholds below, none, and the call 21.0 -> 16.6 ms (benchmarks/results/ros.md).

`keep_freed_memory()` sets, once, at the start of a process that runs operators (the nodes, the
CLI, training workers): mmap only above MMAP_THRESHOLD and trim only above TRIM_THRESHOLD. The
cost is memory kept after a peak (at most the peak itself). Not glibc (macOS, musl): nothing.
A user's MALLOC_MMAP_THRESHOLD_ / MALLOC_TRIM_THRESHOLD_ in the environment wins.
"""
from __future__ import annotations

import ctypes
import os
import sys

M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD = 32 * 1024 * 1024  # glibc's largest on 64-bit (HEAP_MAX_SIZE / 2)
TRIM_THRESHOLD = 256 * 1024 * 1024

_done = False


def keep_freed_memory() -> bool:
    """Set the thresholds (module docstring); True when they were set here."""
    global _done
    if _done or not sys.platform.startswith("linux"):
        return False
    _done = True
    if "MALLOC_MMAP_THRESHOLD_" in os.environ or "MALLOC_TRIM_THRESHOLD_" in os.environ:
        return False
    try:
        libc = ctypes.CDLL(None)
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # not glibc
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD))
