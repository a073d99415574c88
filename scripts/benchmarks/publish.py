"""CPU of publishing the fdi node's answers: a message object, its serialized bytes, bytes written directly; same run.

    scripts/bench publish [--rounds 6] [--count 4000] [--faults 5]

For each trace message the fdi node publishes a ``labels`` and a ``drying_nozzles`` message
(``std_msgs/String`` JSON). ``Publisher.publish`` takes either the message object (rclpy
converts it to its C form, then the middleware serializes it) or its serialized bytes
(``msg_defs.serialized``: published as they are); ``msg_defs.serialize_labels`` and
``serialize_drying`` write the same bytes without the ``json`` encoder and the message object (what
the node publishes). This publishes the same realistic pair (a
200-nozzle frame with ``--faults`` faulty nozzles) ``--count`` times per round each way (14
pairs, one head scan's, back to back, then 10 ms of rest), ``--rounds`` rounds each way in
turn (which way goes first rotates), to a subscriber in another process (a raw
subscription on rclpy's ``EventsExecutor``, as the bench's ceiling takes messages), and
prints the publishing thread's CPU per message pair (``getrusage(RUSAGE_THREAD)``, user +
system, building the message included: ``encode_*`` and ``serialized``, or ``serialize_*``),
best of the rounds, and the ratios. It checks that the bytes of both byte ways are
``rclpy.serialization.serialize_message``'s and that the subscriber got every message (exit
status 1 otherwise).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time

LABELS_TOPIC, DRYING_TOPIC = "bench_publish_labels", "bench_publish_drying"
SCAN, PAUSE_S = 14, 0.01  # pairs published back to back (one head scan's messages), then a pause


def sink(expected: int) -> int:
    """Count the messages of both topics until ``expected`` arrived (or none for 10 s); print the count."""
    import rclpy
    from rclpy.experimental.events_executor import EventsExecutor
    from rclpy.node import Node
    from std_msgs.msg import String

    from msg_defs import RELIABLE_QOS

    rclpy.init()
    node = Node("bench_publish_sink")
    got = [0]
    for topic in (LABELS_TOPIC, DRYING_TOPIC):
        node.create_subscription(String, topic, lambda m: got.__setitem__(0, got[0] + 1), RELIABLE_QOS, raw=True)
    ex = EventsExecutor(context=node.context)
    ex.add_node(node)
    last, seen = time.monotonic(), 0
    while got[0] < expected and time.monotonic() - last < 10.0:
        ex.spin_once(timeout_sec=0.1)
        if got[0] != seen:
            last, seen = time.monotonic(), got[0]
    print(json.dumps({"received": got[0]}), flush=True)
    ex.shutdown()
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


def thread_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_THREAD)
    return r.ru_utime + r.ru_stime


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--role", default="bench", choices=["bench", "sink"])
    ap.add_argument("--rounds", type=int, default=6, help="rounds of each way, in turn (a multiple of 3: each way first as often)")
    ap.add_argument("--count", type=int, default=4000, help="message pairs per round")
    ap.add_argument("--faults", type=int, default=5, help="faulty nozzles in the 200-nozzle frame")
    ap.add_argument("--expected", type=int, default=0, help=argparse.SUPPRESS)  # the sink's
    ns = ap.parse_args()
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")  # before rclpy starts, in both roles
    if ns.role == "sink":
        return sink(ns.expected)

    import numpy as np
    import rclpy
    from rclpy.node import Node
    from rclpy.serialization import serialize_message
    from std_msgs.msg import String

    from msg_defs import (DryingNozzles, LabelsReport, RELIABLE_QOS, encode_drying, encode_labels, serialize_drying,
                          serialize_labels, serialized)

    n = 200
    classes = np.array(["healthy_nozzle"] * n, dtype=object)
    faulty = np.linspace(3, n - 4, ns.faults).astype(int)
    classes[faulty] = ["deeply_dried", "slightly_dried", "partially_blocked", "intermediately_dried",
                       "mature_air_bubble"] * (ns.faults // 5) + ["deeply_dried"] * (ns.faults % 5)
    report = LabelsReport.from_arrays(frame_id=123456, stamp=1764201600.125, first_nozzle=2400, classes=classes,
                                      confidence=np.linspace(0.5, 0.99, n), valid=np.ones(n, bool),
                                      reasons=np.full(n, "", dtype=object), model_id="fdi-rf-kpi_y-3f2a9c1b+baseline",
                                      gate_cleared=classes == "healthy_nozzle")
    drying = DryingNozzles.from_labels(report)
    same = all(serialized(m) == serialize_message(m)
               for m in (encode_labels(report), encode_drying(drying), String(data=""), String(data="é ü ∆ " * 7)))
    same &= (serialize_labels(report) == serialize_message(encode_labels(report))
             and serialize_drying(drying) == serialize_message(encode_drying(drying)))
    print(f"publish benchmark: a labels message ({len(encode_labels(report).data)} characters, {ns.faults} faults) "
          f"and its drying message, {ns.count} pairs per round, {ns.rounds} rounds each way, in turn; "
          f"both ways' bytes identical to serialize_message's: {same}")
    if not same:
        return 1

    rclpy.init()
    node = Node("bench_publish")
    pubs = [node.create_publisher(String, topic, RELIABLE_QOS) for topic in (LABELS_TOPIC, DRYING_TOPIC)]
    env = dict(os.environ)
    total = 2 * ns.count * 3 * ns.rounds
    sub = subprocess.Popen([sys.executable, __file__, "--role", "sink", "--expected", str(total)], env=env,
                           stdout=subprocess.PIPE, text=True)
    t0 = time.monotonic()
    while any(p.get_subscription_count() == 0 for p in pubs):
        if time.monotonic() - t0 > 30:
            print("the subscriber never matched", file=sys.stderr)
            sub.kill()
            return 1
        time.sleep(0.05)
    time.sleep(0.5)

    def as_object():
        pubs[0].publish(encode_labels(report))
        pubs[1].publish(encode_drying(DryingNozzles.from_labels(report)))

    def as_bytes():
        pubs[0].publish(serialized(encode_labels(report)))
        pubs[1].publish(serialized(encode_drying(DryingNozzles.from_labels(report))))

    def as_direct_bytes():
        pubs[0].publish(serialize_labels(report))
        pubs[1].publish(serialize_drying(DryingNozzles.from_labels(report)))

    ways = {"message object": as_object, "serialized bytes": as_bytes, "direct bytes": as_direct_bytes}
    cpu = {k: [] for k in ways}
    order = list(ways.items())
    for r in range(ns.rounds):
        for name, publish in order[r % 3:] + order[:r % 3]:
            c0 = thread_cpu()
            for k in range(ns.count):
                publish()
                if k % SCAN == SCAN - 1:
                    time.sleep(PAUSE_S)  # a head scan's answers, then a pause: the subscriber keeps up
            cpu[name].append((thread_cpu() - c0) / ns.count)
            time.sleep(0.2)  # the subscriber drains
    out, _ = sub.communicate(timeout=120)
    received = json.loads(out.strip().splitlines()[-1])["received"] if out.strip() else 0
    for name, v in cpu.items():
        print(f"  {name:<17}: {1e6 * min(v):6.1f} us CPU per pair (best of {ns.rounds}; "
              f"rounds {1e6 * min(v):.1f}-{1e6 * max(v):.1f})")
    a, b, c = (min(v) for v in cpu.values())
    print(f"ratios of the CPU: message object / serialized bytes {a / b:.2f}x, serialized / direct bytes {b / c:.2f}x, "
          f"message object / direct bytes {a / c:.2f}x; the subscriber got {received} of {total} messages")
    node.destroy_node()
    rclpy.try_shutdown()
    return 0 if received == total else 1


if __name__ == "__main__":
    sys.exit(main())
