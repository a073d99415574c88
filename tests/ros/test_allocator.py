"""inkdiag_ros.allocator: glibc's malloc thresholds, set once per node process."""

import ctypes.util
import os
import subprocess
import sys

import pytest

from inkdiag_ros.allocator import keep_freed_memory

GLIBC = sys.platform.startswith("linux") and ctypes.util.find_library("c") is not None

_PROBE = """
import resource, sys
from inkdiag_ros.allocator import keep_freed_memory
ok = keep_freed_memory()


def message():
    # a received message's buffers (DDS sample, serialized copy, Python object), freed together
    bufs = [bytearray(400_000) for _ in range(3)]
    for b in bufs:
        b[::4096] = b"x" * len(b[::4096])


message()  # the first sets glibc's adaptive thresholds (and what the imports left on the heap)
r0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(200):
    message()
print(ok, resource.getrusage(resource.RUSAGE_SELF).ru_minflt - r0)
"""


def _probe(tuning):
    env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_") and k != "LD_PRELOAD"}
    env["INKDIAG_MALLOC_TUNING"] = tuning  # glibc's own defaults otherwise
    out = subprocess.run([sys.executable, "-c", _PROBE], env=env, capture_output=True, text=True,
                         check=True, timeout=60).stdout.split()
    return out[0] == "True", int(out[1])


def test_turned_off_by_environment(monkeypatch):
    monkeypatch.setenv("INKDIAG_MALLOC_TUNING", "0")
    assert keep_freed_memory() is False


@pytest.mark.skipif(not GLIBC, reason="glibc's mallopt only")
def test_freed_buffers_are_reused_without_page_faults():
    # Default glibc: the freed buffers go back to the system (mmap'ed, or trimmed off the
    # heap's top), so the next message faults in ~100 fresh pages per buffer again.
    tuned, faults_tuned = _probe("1")
    untuned, faults_default = _probe("0")
    assert tuned and not untuned
    assert faults_default > 200 * 50
    assert faults_tuned < faults_default / 10


_BACKLOG_PROBE = """
import sys
from inkdiag_ros.allocator import keep_freed_memory, release_freed_memory, resident_bytes
keep_freed_memory()
r0 = resident_bytes()
backlog, pinned = [], []
for _ in range(40):  # 40 held 2 MB messages, each with a small long-lived array after it
    b = bytearray(2_000_000)
    b[::4096] = b"x" * len(b[::4096])
    backlog.append(b)
    pinned.append(bytearray(1000))
del backlog, b  # the backlog drained; the small ones stay (above it in the heap)
r1 = resident_bytes()
released = release_freed_memory()
print(r0, r1, resident_bytes(), released)
"""


@pytest.mark.skipif(not GLIBC, reason="glibc's malloc_trim only")
def test_a_drained_backlog_is_released():
    env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_") and k != "LD_PRELOAD"}
    env["INKDIAG_MALLOC_TUNING"] = "1"
    r0, kept, after, released = subprocess.run(
        [sys.executable, "-c", _BACKLOG_PROBE], env=env, capture_output=True, text=True, check=True,
        timeout=60).stdout.split()
    mb = 1 << 20
    assert int(kept) - int(r0) > 60 * mb  # freed, but kept resident by the heap
    assert released == "True"
    assert int(after) - int(r0) < 10 * mb


def test_periodic_release_only_after_growth(monkeypatch):
    from inkdiag_ros import allocator

    now, rss, calls = [0.0], [0], []
    monkeypatch.setattr(allocator, "release_freed_memory", lambda: calls.append(now[0]) or True)
    p = allocator.PeriodicRelease(5.0, 8 << 20, clock=lambda: now[0], resident=lambda: rss[0])
    steps = ((1.0, 300), (5.0, 200), (10.0, 207), (15.0, 230), (16.0, 230), (20.0, 190), (25.0, 201),
             (30.0, 230), (35.0, 236))
    for t, size in steps:
        now[0], rss[0] = t, size << 20
        p()
    # 1 s: before the first period; 5 s: the reference (200 MB); 10 s: grown 7 MB, not more
    # than 8; 15 s: grown 30 MB -> released; 16 s: within the period; 20 s: the new reference
    # once the buffers faulted in again (190 MB); 25 s: 11 MB over it -> released; 30 s: the
    # reference; 35 s: 6 MB over it
    assert calls == [15.0, 25.0] and p.releases == 2
