"""Subprocess side of the two-process test: publish seeded trace frames.

    python publish_frames.py N_NOZZLES N_SAMPLES SEED TIMEOUT_S

Publishes the same frame (frame_id 7) every 50 ms until a subscriber has
been matched for a while or the timeout passes. Runs on the ROS_DOMAIN_ID
of its environment.
"""

import sys
import time

import numpy as np
import rclpy
from rclpy.node import Node

from msg_defs import TRACE_MSG_TYPE, TRACES_QOS, encode_traces, topics


def main():
    n, s, seed, timeout = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]), float(sys.argv[4])
    traces = np.random.default_rng(seed).standard_normal((n, s)).astype(np.float32)
    rclpy.init()
    node = Node("frame_publisher")
    pub = node.create_publisher(TRACE_MSG_TYPE, topics.TRACES, TRACES_QOS)
    msg = encode_traces(traces, first_nozzle=100, frame_id=7, stamp=1.5)
    deadline = time.monotonic() + timeout
    try:
        while time.monotonic() < deadline:
            pub.publish(msg)
            rclpy.spin_once(node, timeout_sec=0.05)
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    main()
