"""inkdiag_ros.exit_deadline: a process exit that needs no GIL (a node's bound on its teardown)."""

import subprocess
import sys
import time

import pytest

from inkdiag_ros.exit_deadline import exit_deadline

_HOLD_THE_GIL = """
import sys, time
from inkdiag_ros.exit_deadline import exit_deadline
with exit_deadline(1.0, int(sys.argv[1])) as armed:
    print("armed", armed, flush=True)
    sum(range(10**11))  # one C call that never lets the GIL go, as rclpy's participant deletion does
print("the deadline did not fire", flush=True)
"""

_LEAVE_IN_TIME = """
import time
from inkdiag_ros.exit_deadline import exit_deadline
with exit_deadline(0.8, 3):
    time.sleep(0.1)
time.sleep(1.2)
print("still running after the deadline's time", flush=True)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="POSIX timers with SIGEV_THREAD: Linux only")
@pytest.mark.parametrize("status", [0, 4])
def test_the_deadline_ends_a_process_whose_main_thread_holds_the_gil(status):
    t0 = time.monotonic()
    out = subprocess.run([sys.executable, "-c", _HOLD_THE_GIL, str(status)], capture_output=True, text=True,
                         timeout=60)
    took = time.monotonic() - t0
    assert "armed True" in out.stdout and "did not fire" not in out.stdout, out.stdout + out.stderr
    assert out.returncode == status, out.stdout + out.stderr
    assert "Timeout (" in out.stderr and "line 6" in out.stderr, out.stderr  # the stacks, before the exit
    assert took < 30


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="POSIX timers with SIGEV_THREAD: Linux only")
def test_leaving_the_block_disarms_the_deadline():
    out = subprocess.run([sys.executable, "-c", _LEAVE_IN_TIME], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and "still running" in out.stdout, out.stdout + out.stderr
    assert "Timeout" not in out.stderr, out.stderr


@pytest.mark.parametrize("seconds", [0.0, 0.5, -1.0, float("nan")])
def test_a_deadline_too_short_to_print_the_stacks_is_refused(seconds):
    with pytest.raises(ValueError, match="exit deadline"):
        with exit_deadline(seconds):
            pass


def test_tear_down_closes_every_nodes_outputs_and_destroys_them_even_when_one_close_fails():
    from inkdiag_ros._spin import tear_down

    calls = []

    class Node:
        def __init__(self, name, fail=False):
            self.name, self.fail = name, fail

        def close_outputs(self):
            calls.append(("close", self.name))
            if self.fail:
                raise OSError(f"{self.name}: disk full")

        def destroy_node(self):
            calls.append(("destroy", self.name))

    class Plain:  # no close_outputs: destroyed only
        def destroy_node(self):
            calls.append(("destroy", "plain"))

    with pytest.raises(OSError, match="a: disk full"):
        tear_down(None, [Node("a", fail=True), None, Node("b"), Plain()], context_is_ours=False)
    assert calls == [("close", "a"), ("close", "b"), ("destroy", "a"), ("destroy", "b"), ("destroy", "plain")]
