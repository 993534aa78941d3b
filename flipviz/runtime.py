"""Process-wide settings that make CPU training fast, applied once by whoever trains or renders.

glibc serves every allocation above its mmap threshold (at most 32 MiB, however it adapts) with a
fresh mmap and unmaps it on free, so each training step's gradient of a 128^3 grid (~60 MB) is
faulted in page by page and handed back to the kernel: on the 2-core machine a third of a step
was kernel time (150 lamp steps: 19.7 s, 8.7 s of it sys). Raising the mmap and trim thresholds
keeps freed memory in the heap for the next step: the same steps took 9.7 s, 0.0 s sys.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys

M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3  # glibc's mallopt parameters (malloc.h)
_applied = False


def keep_freed_memory() -> None:
    """Large allocations come from the heap and freed memory stays there (glibc only; else nothing)."""
    global _applied
    if _applied or not sys.platform.startswith("linux") or os.environ.get("FLIPVIZ_GLIBC_MALLOC") == "default":
        return  # FLIPVIZ_GLIBC_MALLOC=default keeps glibc's settings (studies/bench_run_time.py compares)
    _applied = True
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        libc.mallopt(M_MMAP_THRESHOLD, 1 << 30)
        libc.mallopt(M_TRIM_THRESHOLD, 1 << 31)
    except (OSError, AttributeError):  # musl and others have no mallopt: keep their defaults
        pass
