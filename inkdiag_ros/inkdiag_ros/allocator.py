"""Keep freed memory in the process: no page faults for every received frame.

Each trace message (400 kB for 200 nozzles x 512 samples) is taken into fresh
buffers: by default glibc serves allocations above 128 kB with ``mmap`` and
returns them with ``munmap``, so every message costs a page fault per 4 kB page
(``scripts/bench take``: about 200-270 minor faults and 0.4-0.9 ms of system time
per message on the subscribing executor thread, none and under 0.05 ms with this
setting). Raising glibc's mmap and trim thresholds makes those buffers come
from, and go back to, the heap, which keeps the pages. Every
inkdiag node process calls :func:`keep_freed_memory` once at start;
``INKDIAG_MALLOC_TUNING=0`` turns it off.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os

__all__ = ["keep_freed_memory"]

# mallopt(3) parameter numbers (glibc malloc.h)
_M_TRIM_THRESHOLD = -1
_M_TOP_PAD = -2
_M_MMAP_THRESHOLD = -3

MMAP_THRESHOLD_BYTES = 64 << 20
"""Allocations below this come from the heap (glibc's default: 128 kB, adaptive)."""
TRIM_THRESHOLD_BYTES = 256 << 20
"""Free heap kept before any is returned to the system (default 128 kB)."""


def keep_freed_memory() -> bool:
    """Set glibc's malloc thresholds (see the module docstring); idempotent.

    Returns
    -------
    bool
        True if they were set; False where turned off by ``INKDIAG_MALLOC_TUNING=0``
        or not on glibc (the defaults then stay, nothing else changes).
    """
    if os.environ.get("INKDIAG_MALLOC_TUNING", "1") == "0":
        return False
    name = ctypes.util.find_library("c")
    try:
        mallopt = ctypes.CDLL(name).mallopt
    except (OSError, AttributeError, TypeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    ok = mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES) == 1
    ok &= mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES) == 1
    ok &= mallopt(_M_TOP_PAD, MMAP_THRESHOLD_BYTES) == 1
    return bool(ok)
