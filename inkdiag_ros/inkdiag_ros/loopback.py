"""Loopback check: trace frames through real rclpy + Fast DDS and back.

The smallest end-to-end path of inkdiag: a publisher node encodes frames of
model-generated traces with :mod:`msg_defs.codec`, a subscriber node in the
same process (one executor) decodes them, and the run prints how many arrived,
whether they are bit-exact, and the throughput in traces/s.

    python -m inkdiag_ros.loopback [--nozzles 256] [--samples 512] [--frames 50]
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np
import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.utilities import remove_ros_args

from inkdiag_core import InkChannelModel
from msg_defs import RELIABLE_QOS, TRACE_MSG_TYPE, decode_traces, encode_traces, topics

from ._spin import exit_now, tear_down


def model_frame(n_nozzles: int, n_samples: int, sample_rate_hz: float, seed: int) -> np.ndarray:
    """Healthy-channel free responses with per-nozzle gain and noise, float32 (n, s)."""
    rng = np.random.default_rng(seed)
    y = InkChannelModel().free_response([0.0, 1e-6, 1e-6], n_samples, sample_rate_hz)
    y = y / np.max(np.abs(y))
    gains = rng.uniform(0.8, 1.2, size=(n_nozzles, 1))
    return (gains * y + 0.01 * rng.standard_normal((n_nozzles, n_samples))).astype(np.float32)


class TraceSender(Node):
    """Publishes a fixed list of trace frames, one per spin callback."""

    def __init__(self, frames, sample_rate_hz: float, **kwargs):
        super().__init__("loopback_sender", **kwargs)
        self._pub = self.create_publisher(TRACE_MSG_TYPE, topics.TRACES, RELIABLE_QOS)
        self._frames = frames
        self._fs = sample_rate_hz
        self.sent = 0

    def send_next(self) -> bool:
        if self.sent >= len(self._frames):
            return False
        msg = encode_traces(self._frames[self.sent], frame_id=self.sent, sample_rate_hz=self._fs,
                            stamp=time.time())
        self._pub.publish(msg)
        self.sent += 1
        return True

    def subscribers(self) -> int:
        return self._pub.get_subscription_count()


class TraceReceiver(Node):
    """Decodes every trace frame it receives and keeps the arrays."""

    def __init__(self, **kwargs):
        super().__init__("loopback_receiver", **kwargs)
        self.frames = {}
        self._sub = self.create_subscription(TRACE_MSG_TYPE, topics.TRACES, self._on_traces,
                                             RELIABLE_QOS)

    def _on_traces(self, msg) -> None:
        frame = decode_traces(msg)
        self.frames[frame.frame_id] = np.array(frame.traces)


def run(n_nozzles: int, n_samples: int, n_frames: int, sample_rate_hz: float = 10e6,
        timeout_s: float = 30.0) -> dict:
    """Send ``n_frames`` frames through DDS in one process; return what arrived."""
    frames = [model_frame(n_nozzles, n_samples, sample_rate_hz, seed=i) for i in range(n_frames)]
    rclpy.init()
    sender = TraceSender(frames, sample_rate_hz)
    receiver = TraceReceiver()
    executor = SingleThreadedExecutor()
    executor.add_node(sender)
    executor.add_node(receiver)
    try:
        deadline = time.monotonic() + timeout_s
        while sender.subscribers() == 0 and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
        t0 = time.perf_counter()
        while len(receiver.frames) < n_frames and time.monotonic() < deadline:
            sender.send_next()
            executor.spin_once(timeout_sec=0.01)
        elapsed = time.perf_counter() - t0
    except (KeyboardInterrupt, ExternalShutdownException):
        elapsed = float("nan")
    finally:
        tear_down(executor, [sender, receiver])
    exact = all(np.array_equal(receiver.frames[i], frames[i]) for i in receiver.frames)
    return {
        "sent": sender.sent,
        "received": len(receiver.frames),
        "bit_exact": exact,
        "seconds": elapsed,
        "traces_per_s": len(receiver.frames) * n_nozzles / elapsed if elapsed > 0 else float("nan"),
    }


def main(args=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--nozzles", type=int, default=256)
    parser.add_argument("--samples", type=int, default=512)
    parser.add_argument("--frames", type=int, default=50)
    ns = parser.parse_args(remove_ros_args(args if args is not None else sys.argv)[1:])
    r = run(ns.nozzles, ns.samples, ns.frames)
    print(
        f"loopback over rclpy/Fast DDS: {r['received']}/{r['sent']} frames of "
        f"{ns.nozzles} x {ns.samples} received, bit-exact: {r['bit_exact']}, "
        f"{r['traces_per_s']:,.0f} traces/s (one process, reliable QoS)"
    )
    return 0 if r["received"] == ns.frames and r["bit_exact"] else 1


if __name__ == "__main__":
    exit_now(main())  # the nodes down: not the interpreter's teardown too
