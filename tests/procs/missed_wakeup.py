"""Subprocess side of the missed wake-up test: spin_node(FeNode) with nothing to receive.

A thread does what rclpy's signal thread does on SIGINT/SIGTERM, in its order, with
time between the two steps: it triggers every executor's signal guard condition, then
shuts the context down (rcl only, no Python shutdown callbacks). A spin that went back
to an unbounded wait after the first step never exits.

    python missed_wakeup.py
"""

import sys
import threading
import time

import rclpy
import rclpy.executors
from rclpy.signals import SignalHandlerGuardCondition

_gcs = []


class _Recorded(SignalHandlerGuardCondition):
    def __init__(self, context=None):
        super().__init__(context)
        _gcs.append(self)


rclpy.executors.SignalHandlerGuardCondition = _Recorded  # every executor built from now on


def _signal_thread_order():
    time.sleep(3.0)  # the node is spinning
    for gc in list(_gcs):
        gc.trigger()  # the wake-up
    time.sleep(0.5)  # the executor finds no work and the context still ok
    rclpy.utilities.get_default_context()._Context__context.shutdown()  # rcl_shutdown, no callbacks
    print("context shut down", flush=True)


def main():
    from inkdiag_ros.fe_node import FeNode
    from inkdiag_ros._spin import spin_node

    threading.Thread(target=_signal_thread_order, daemon=True).start()
    return spin_node(FeNode, ["fe", "--ros-args", "-r", "__ns:=/missed_wakeup"])


if __name__ == "__main__":
    sys.exit(main())
