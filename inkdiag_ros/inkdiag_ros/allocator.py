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

What the heap keeps is the most the process ever held at once, not what it holds
now: a backlog (frames queued while a node waits for a core, or fe's traces held
while fdi is late) leaves its memory free in the heap, and resident, after it
drains, and glibc cannot trim it from the heap's top once a later, smaller
allocation sits above it. The resident size then rose in steps with each larger
backlog (issue 12's soak: +4.5 % to +13 % from a third of the run to its end,
flat between the steps). So the spin loop of every node checks every few seconds
(:class:`PeriodicRelease`): once its resident size grew by more than
:data:`RELEASE_ABOVE_BYTES` it hands every free page back (``malloc_trim``,
:func:`release_freed_memory`); in the steady state the size stays put and the
buffers keep their pages.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import os
import time

__all__ = ["RELEASE_ABOVE_BYTES", "RELEASE_PERIOD_S", "PeriodicRelease", "keep_freed_memory",
           "release_freed_memory", "resident_bytes"]

# mallopt(3) parameter numbers (glibc malloc.h)
_M_TRIM_THRESHOLD = -1
_M_TOP_PAD = -2
_M_MMAP_THRESHOLD = -3

MMAP_THRESHOLD_BYTES = 64 << 20
"""Allocations below this come from the heap (glibc's default: 128 kB, adaptive)."""
TRIM_THRESHOLD_BYTES = 256 << 20
"""Free heap kept before any is returned to the system (default 128 kB)."""
RELEASE_ABOVE_BYTES = 8 << 20
"""Growth of the resident size (bytes) after which :class:`PeriodicRelease` releases: below
5 % of a node's resident size (about 200 MB for 1,024 nozzles), above the step of a
steady state's buffers (a 2 MB trace message)."""
RELEASE_PERIOD_S = 5.0
"""Seconds between two checks of :class:`PeriodicRelease`."""


@functools.lru_cache(maxsize=1)
def _load_libc():
    try:  # find_library may run ldconfig: once per process
        return ctypes.CDLL(ctypes.util.find_library("c"))
    except (OSError, TypeError):
        return None


def _libc():
    if os.environ.get("INKDIAG_MALLOC_TUNING", "1") == "0":
        return None
    return _load_libc()


def keep_freed_memory() -> bool:
    """Set glibc's malloc thresholds (see the module docstring); idempotent.

    Returns
    -------
    bool
        True if they were set; False where turned off by ``INKDIAG_MALLOC_TUNING=0``
        or not on glibc (the defaults then stay, nothing else changes).
    """
    libc = _libc()
    mallopt = getattr(libc, "mallopt", None)
    if mallopt is None:
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    ok = mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES) == 1
    ok &= mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES) == 1
    ok &= mallopt(_M_TOP_PAD, MMAP_THRESHOLD_BYTES) == 1
    return bool(ok)


def resident_bytes() -> int:
    """This process's resident set size, bytes (``/proc/self/statm``; 0 where there is none)."""
    try:
        with open("/proc/self/statm", "rb") as fh:
            return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return 0


def release_freed_memory() -> bool:
    """Return the free pages of every malloc arena to the system (``malloc_trim(0)``).

    Not only the heap's top: free pages under chunks still in use too. The pages the
    steady state reuses fault in again once afterwards (a few ms).

    Returns
    -------
    bool
        True if memory was returned; False otherwise (none free, not glibc, or
        turned off by ``INKDIAG_MALLOC_TUNING=0``).
    """
    trim = getattr(_libc(), "malloc_trim", None)
    if trim is None:
        return False
    trim.argtypes = (ctypes.c_size_t,)
    trim.restype = ctypes.c_int
    return trim(0) == 1


class PeriodicRelease:
    """A spin loop's helper: :func:`release_freed_memory` after the process grew.

    Called as often as convenient; every ``period_s`` seconds it compares the resident
    size with its reference and releases once it grew by more than ``above`` bytes. The
    reference is the size at the first check, and after a release the size one check
    later (once the steady state's buffers have faulted in again: comparing with the size
    right after the release would release again every period when those buffers are
    more than ``above``). A backlog's memory goes back within about two periods after it
    drained; in the steady state the resident size stays put and nothing is done.

    Parameters
    ----------
    period_s : float
        Seconds between two checks.
    above : int
        Growth of the resident size over the reference, bytes, that triggers a release.
    clock : callable, optional
        Monotonic time, s (default ``time.monotonic``).
    resident : callable, optional
        Resident size, bytes (default :func:`resident_bytes`).

    Attributes
    ----------
    releases : int
        Releases done.
    """

    def __init__(self, period_s: float = RELEASE_PERIOD_S, above: int = RELEASE_ABOVE_BYTES, *,
                 clock=time.monotonic, resident=resident_bytes):
        self.period_s = float(period_s)
        self.above = int(above)
        self._clock, self._resident = clock, resident
        self._next = clock() + self.period_s
        self._ref = None
        self.releases = 0

    def __call__(self) -> bool:
        """Check if the period has passed; True if memory was released now."""
        now = self._clock()
        if now < self._next:
            return False
        self._next = now + self.period_s
        rss = self._resident()
        if self._ref is None:  # the first check, or the first after a release
            self._ref = rss
            return False
        if rss - self._ref <= self.above:
            return False
        released = release_freed_memory()
        self.releases += released
        self._ref = None
        return released
