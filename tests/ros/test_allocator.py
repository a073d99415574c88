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
r0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(200):
    # a received message's buffers (DDS sample, serialized copy, Python object), freed together
    bufs = [bytearray(400_000) for _ in range(3)]
    for b in bufs:
        b[::4096] = b"x" * len(b[::4096])
    del bufs, b
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
