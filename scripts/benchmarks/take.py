"""Cost of receiving one trace message in a node process, with and without the allocator setting.

    scripts/bench take [--rate 200] [--seconds 6] [--nozzles 200]

A publisher process sends the same encoded trace message (``--nozzles`` x 512 float32
samples, 400 kB by default) at ``--rate`` messages/s; a subscriber process spins an rclpy
``SingleThreadedExecutor`` whose callback decodes each frame (``msg_defs.decode_traces``,
what the fdi node's executor thread does before handing a frame to its labeller). The
subscriber is run twice, with glibc's defaults (``INKDIAG_MALLOC_TUNING=0``) and with
``inkdiag_ros.allocator.keep_freed_memory`` (what every inkdiag node process calls), and
reports, per message, the executor thread's user and system CPU time and its minor page
faults (``getrusage(RUSAGE_THREAD)``), and the ratio of the two runs' CPU per message.

``--raw``: instead, both runs with the allocator setting, one taking the message as rclpy
converts it (``decode_traces``) and one taking it serialized (``raw=True``,
``msg_defs.decode_traces_serialized``: what the fe node does). ``--events``: the
subscriber spins rclpy's ``EventsExecutor`` (as the fe node does) instead of the
``SingleThreadedExecutor``.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time

TOPIC = "bench_take_traces"


def publisher(rate: float, seconds: float, nozzles: int) -> int:
    import numpy as np
    import rclpy
    from rclpy.node import Node

    from msg_defs import TRACE_MSG_TYPE, TRACES_QOS, encode_traces

    rclpy.init()
    node = Node("bench_take_pub")
    pub = node.create_publisher(TRACE_MSG_TYPE, TOPIC, TRACES_QOS)
    x = np.random.default_rng(0).standard_normal((nozzles, 512)).astype(np.float32)
    msg = encode_traces(x, first_nozzle=0, frame_id=0, stamp=0.0)
    deadline = time.monotonic() + 10.0
    while pub.get_subscription_count() == 0 and time.monotonic() < deadline:
        time.sleep(0.05)
    end = time.monotonic() + seconds
    nxt = time.monotonic()
    while time.monotonic() < end and rclpy.ok():
        try:
            pub.publish(msg)
        except Exception:
            if rclpy.ok():
                raise
            break  # stopped (SIGTERM) while publishing
        nxt += 1.0 / rate
        time.sleep(max(0.0, nxt - time.monotonic()))
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


def subscriber(seconds: float, raw: bool = False, events: bool = False) -> int:
    from inkdiag_ros.allocator import keep_freed_memory

    tuned = keep_freed_memory()
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node

    from msg_defs import TRACE_MSG_TYPE, TRACES_QOS, decode_traces, decode_traces_serialized

    rclpy.init()
    node = Node("bench_take_sub")
    count = [0]
    decode = decode_traces_serialized if raw else decode_traces

    def on_msg(msg):
        decode(msg)
        count[0] += 1

    node.create_subscription(TRACE_MSG_TYPE, TOPIC, on_msg, TRACES_QOS, raw=raw)
    if events:
        from rclpy.experimental import EventsExecutor

        ex = EventsExecutor()
    else:
        ex = SingleThreadedExecutor()
    ex.add_node(node)
    deadline = time.monotonic() + 15.0
    while count[0] < 20 and time.monotonic() < deadline:  # warm-up
        ex.spin_once(timeout_sec=0.1)
    r0, n0, t0 = resource.getrusage(resource.RUSAGE_THREAD), count[0], time.monotonic()
    while time.monotonic() - t0 < seconds:
        ex.spin_once(timeout_sec=0.1)
    r1, n = resource.getrusage(resource.RUSAGE_THREAD), count[0] - n0
    elapsed = time.monotonic() - t0
    n = max(n, 1)
    print(json.dumps({"tuned": tuned, "msgs_per_s": n / elapsed,
                      "user_us": 1e6 * (r1.ru_utime - r0.ru_utime) / n,
                      "sys_us": 1e6 * (r1.ru_stime - r0.ru_stime) / n,
                      "minflt": (r1.ru_minflt - r0.ru_minflt) / n}))
    ex.shutdown()
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


def measure(tuning: str, ns, raw: bool = False) -> dict:
    env = dict(os.environ, INKDIAG_MALLOC_TUNING=tuning)
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    me = [sys.executable, __file__]
    sub = subprocess.Popen(me + ["--role", "sub", "--seconds", str(ns.seconds)] + (["--raw"] if raw else [])
                           + (["--events"] if ns.events else []), env=env,
                           stdout=subprocess.PIPE, text=True)
    pub = subprocess.Popen(me + ["--role", "pub", "--rate", str(ns.rate), "--nozzles", str(ns.nozzles),
                                "--seconds", str(ns.seconds + 8.0)], env=env)
    out, _ = sub.communicate(timeout=ns.seconds + 60)
    pub.terminate()
    pub.wait(timeout=30)
    return json.loads(out.strip().splitlines()[-1])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--role", default="bench", choices=["bench", "pub", "sub"])
    ap.add_argument("--rate", type=float, default=200.0, help="messages per second")
    ap.add_argument("--seconds", type=float, default=6.0, help="measured time per run")
    ap.add_argument("--nozzles", type=int, default=200, help="traces per message (512 samples each)")
    ap.add_argument("--raw", action="store_true", help="compare the message with the serialized take (fe's)")
    ap.add_argument("--events", action="store_true", help="the subscriber spins rclpy's EventsExecutor (fe's)")
    ns = ap.parse_args()
    if ns.role == "pub":
        return publisher(ns.rate, ns.seconds, ns.nozzles)
    if ns.role == "sub":
        return subscriber(ns.seconds, ns.raw, ns.events)
    print(f"take benchmark: {ns.nozzles} x 512 float32 samples per message "
          f"({ns.nozzles * 512 * 4 / 1e3:.0f} kB), {ns.rate:g} msgs/s for {ns.seconds:g} s per run; "
          "executor thread of the subscribing process, per message")
    res = {}
    runs = ((("message", "1", False), ("serialized (raw)", "1", True)) if ns.raw
            else (("glibc defaults", "0", False), ("keep_freed_memory", "1", False)))
    for name, tuning, raw in runs:
        r = res[name] = measure(tuning, ns, raw)
        print(f"{name:<18} {r['msgs_per_s']:6.0f} msgs/s  user {r['user_us']:7.0f} us  "
              f"sys {r['sys_us']:6.0f} us  minor faults {r['minflt']:6.0f}"
              + ("" if r["tuned"] or tuning == "0" else "  (not applied: no glibc)"))
    a, b = (res[k]["user_us"] + res[k]["sys_us"] for k in res)
    print(f"CPU per message, {runs[1][0]} / {runs[0][0]} = {b / a:.2f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
