"""Aggregate throughput of N heads' fdi nodes in P processes (``inkdiag printer``), against a plain-subscriber ceiling.

    scripts/bench printer [--heads 1,2,4] [--processes 1,2] [--seconds 8] [--nozzles 2656] [--chunk 200]
                          [--faulty 0.02] [--no-baselines] [--executor events|single] [--scan-hz 5]

Per head, pre-generates frames of a realistic head (``graph.realistic_head``: 2,656 nozzles x 512
samples, its own nozzle tolerances, 2 % faulty, the faults the same in every frame) and records every
nozzle's healthy baseline from 8 healthy frames of the same nozzles (``BaselineRecorder``, as
commissioning does; the fdi nodes get them through ``--baselines``). Then, for each N of ``--heads``:

1. ceiling: plain subscribers (decode the frame, touch it, answer a tiny ack), the N heads' in
   ``min(N, 2)`` processes round-robin, spun as ``inkdiag printer``'s workers spin (the executor
   ``--executor`` names, the allocator set as in every inkdiag node); each publisher spins the
   ``EventsExecutor``;
2. ``inkdiag printer --heads N --processes P`` for each P of ``--processes`` (P <= N).

Each head has an independent publisher process (``graph.replay``'s closed loop on ``/head_ii/traces``:
messages of ``--chunk`` nozzles, at most one head scan, ``ceil(nozzles / chunk)`` messages, in flight
per head; a message unanswered for N x 10x the worst latency of a 1 s warm-up (>= N x 50 ms) is lost and its
slot reused). ``--scan-hz F``: paced instead, as head controllers at F scans a second: each publisher
sends a whole scan every 1/F s whether or not the last was answered (a message unanswered when
its head's next scan is due, 1/F s later, is lost; a late answer is not counted); traces/s and
msgs/s are the answered ones per second of the sending phase (the heads' offer when nothing is
lost), each line also prints answered / sent, and the latencies are a box's at that load. All
publishers start together (every head's scan in one burst) once every one has matched and
warmed up. Latency: the
frame's publish time to its answer arriving at its publisher (one clock). The consumers' CPU
(utime + stime of their processes from /proc/<pid>/stat, over the measured phase) per message answered
says what a message costs the box. The publishers run on the same 2 cores: on a printer they are the
head controllers, elsewhere.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
sys.path.insert(0, str(HERE))
ACK = "bench_ack"


FIRST_HEAD = 40
"""The benchmark's heads are /head_40 .. (``inkdiag printer --first-head``): tests elsewhere on the same
domain run /head_00 nodes, whose traces must not reach these fdi nodes."""


def _ns(i: int) -> str:
    return f"/head_{FIRST_HEAD + i:02d}"


def sink_main(heads, executor: str = "events") -> int:
    """Plain subscribers of ``heads`` in this process: decode each frame, touch it, ack its id.

    Spun as ``inkdiag printer`` spins its fdi processes (its worker's loop): the executor
    ``--executor`` names, the allocator setting with its periodic release, one BLAS thread, the
    startup objects frozen out of the garbage collector, a signal ending the loop. Until 2026-11-26
    the sinks always spun the Python ``SingleThreadedExecutor``: with fdi on the default
    ``EventsExecutor`` the ceiling read below what the transport takes (``reports/printer.md``).
    """
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rclpy.node import Node
    from std_msgs.msg import String

    from inkdiag_ros._spin import freeze_startup_objects, make_executor, stop_on_signals
    from inkdiag_ros.allocator import PeriodicRelease, keep_freed_memory
    from inkdiag_ros.blas import limit_blas_threads
    from msg_defs import RELIABLE_QOS, TRACE_MSG_TYPE, TRACES_QOS, decode_traces, topics

    keep_freed_memory()
    limit_blas_threads()
    with stop_on_signals() as stop:  # entered before rclpy.init, as inkdiag printer's worker: rclpy's handlers chain
        rclpy.init()
        nodes = []
        for i in heads:
            node = Node("bench_sink", namespace=_ns(i))
            pub = node.create_publisher(String, ACK, RELIABLE_QOS)

            def on_frame(msg, pub=pub):
                f = decode_traces(msg)
                float(f.traces[0, 0])  # touch the data
                pub.publish(String(data=f"{f.frame_id}"))

            node.create_subscription(TRACE_MSG_TYPE, topics.TRACES, on_frame, TRACES_QOS)
            nodes.append(node)
        ctx = nodes[0].context
        ex = make_executor(nodes, executor == "events", stop)  # as inkdiag printer's workers
        freeze_startup_objects()
        release = PeriodicRelease()
        try:
            while not stop.requested and ctx.ok():
                ex.spin_once(timeout_sec=0.5)
                release()
        except (KeyboardInterrupt, ExternalShutdownException):
            pass
        finally:
            ex.shutdown()
            for n in nodes:
                n.destroy_node()
            rclpy.try_shutdown()
    return 0


def pub_main(head: int, data: str, seconds: float, window: int, chunk: int, first_id: int, n_heads: int = 1,
             scan_hz: float = 0.0) -> int:
    """One head's independent publisher: match, warm up, say ``ready``, wait for ``go`` on stdin, replay."""
    import rclpy
    from rclpy.experimental import EventsExecutor
    from rclpy.node import Node
    from std_msgs.msg import String

    from graph import replay, wait_for_match
    from msg_defs import LABELS_MSG_TYPE, RELIABLE_QOS, TRACE_MSG_TYPE, TRACES_QOS, decode_labels, encode_traces, topics

    frames = np.load(data)
    msgs = [encode_traces(np.ascontiguousarray(x[i:i + chunk]), first_nozzle=i, frame_id=0, stamp=0.0)
            for x in frames for i in range(0, x.shape[0], chunk)]
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    rclpy.init()
    node = Node("bench_publisher", namespace=_ns(head))
    ex = EventsExecutor(context=node.context)  # the C++ executor, as graph's replayer: it keeps up with the ceiling
    ex.add_node(node)
    pub = node.create_publisher(TRACE_MSG_TYPE, topics.TRACES, TRACES_QOS)
    answered = []
    node.create_subscription(String, ACK, lambda m: answered.append((int(m.data), time.time())), RELIABLE_QOS)
    node.create_subscription(LABELS_MSG_TYPE, topics.LABELS,
                             lambda m: answered.append((decode_labels(m).frame_id, time.time())), RELIABLE_QOS)
    ok = wait_for_match(ex, pub, lambda: node.count_publishers(f"{_ns(head)}/{ACK}")
                        + node.count_publishers(f"{_ns(head)}/{topics.LABELS}") > 0, timeout=120.0)
    if not ok:
        print(json.dumps({"error": "never matched"}), flush=True)
        return 1
    warm, warm_lat, *_ = replay(node, ex, pub, msgs, answered, 1.0, 1, first_id=first_id)
    answered.clear()
    # graph's rule (10x the warm-up's worst latency, >= 50 ms) times the heads sharing the consumers: with one
    # scan in flight per head, a message waits behind the other heads' too (a run of 4 heads in one process
    # had every message "lost" at a head's own threshold)
    lost_after = n_heads * (max(0.05, 10.0 * float(np.max(warm_lat))) if warm_lat.size else 0.25)
    print("ready", flush=True)
    sys.stdin.readline()
    if scan_hz > 0:  # paced: a message unanswered when its head's next scan is due is lost
        lost_after = 1.0 / scan_hz
    scan_msgs = -(-frames.shape[1] // chunk)
    sent, lat, lost, el = replay(node, ex, pub, msgs, answered, seconds, window, lost_after_s=lost_after,
                                 first_id=first_id + warm, scan_hz=scan_hz, scan_msgs=scan_msgs)
    print(json.dumps({"sent": sent, "lat_ms": np.round(1e3 * lat, 3).tolist(), "lost": len(lost), "elapsed": el,
                      "traces_per_msg": float(np.mean([m.layout.dim[0].size for m in msgs])),
                      "lost_after_s": lost_after}), flush=True)
    ex.shutdown()
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


def _stop(proc, timeout=10.0):
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
    try:
        proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def phase(name, consumer_cmds, heads, ns, data_dir, first_id, log_path):
    """Start the consumer processes, N publishers, measure them together; returns a result dict.

    ``consumer_cmds``: one command per consumer process; an ``inkdiag printer`` command's own
    children (the pids its first line names) are the ones whose CPU is measured.
    """
    from graph import cpu_s  # the same CPU count as the graph benchmark's

    env = dict(os.environ)
    consumers = []
    with open(log_path, "w") as log:
        for cmd in consumer_cmds:
            consumers.append(subprocess.Popen(cmd, env=env, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT))
    pubs = []
    try:
        if consumer_cmds[0][2:4] == ["inkdiag_ros.cli", "printer"]:  # its children do the work
            deadline = time.monotonic() + 30
            pids = None
            while pids is None and time.monotonic() < deadline:
                first = Path(log_path).read_text().split("\n", 1)[0]
                if "(pids " in first:
                    pids = [int(p) for p in first.split("(pids ", 1)[1].split(")")[0].split(", ")]
                time.sleep(0.1)
            pids = pids or []
        else:
            pids = [c.pid for c in consumers]
        for i in range(heads):
            pubs.append(subprocess.Popen(
                [sys.executable, __file__, "--role", "pub", "--head", str(i), "--data", str(data_dir / f"frames_{i:02d}.npy"),
                 "--seconds", str(ns.seconds), "--window", str(ns.window), "--chunk", str(ns.chunk),
                 "--first-id", str(first_id), "--n-heads", str(heads), "--scan-hz", str(ns.scan_hz)], env=env, cwd=ROOT, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                text=True))
        for p in pubs:
            line = p.stdout.readline()
            if line.strip() != "ready":
                raise RuntimeError(f"{name}: a publisher said {line!r} (consumer log: {log_path})")
        c0, t0 = cpu_s(pids), time.monotonic()
        for p in pubs:
            p.stdin.write("go\n")
            p.stdin.flush()
        res = [json.loads(p.stdout.readline()) for p in pubs]
        c1, t1 = cpu_s(pids), time.monotonic()
    finally:
        for p in pubs:
            _stop(p)
        for c in consumers:
            _stop(c)
    lat = np.concatenate([np.asarray(r["lat_ms"]) for r in res]) if res else np.empty(0)
    answered = sum(len(r["lat_ms"]) for r in res)
    # paced: per second of the sending phase (a closed loop's elapsed time is its sending time; a
    # paced replay's also holds the wait for its last answers, which would dilute the rates)
    el = ns.seconds if ns.scan_hz > 0 else max(r["elapsed"] for r in res)
    traces = sum(len(r["lat_ms"]) * r["traces_per_msg"] for r in res)
    return {"name": name, "heads": heads, "traces_per_s": traces / el, "msgs_per_s": answered / el,
            "sent": sum(r["sent"] for r in res), "answered": answered, "lost": sum(r["lost"] for r in res),
            "p50_ms": float(np.percentile(lat, 50)) if lat.size else float("nan"),
            "p99_ms": float(np.percentile(lat, 99)) if lat.size else float("nan"),
            "cpu_ms_per_msg": 1e3 * (c1 - c0) / max(answered, 1), "cores": (c1 - c0) / (t1 - t0),
            "processes": len(pids)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--role", default="bench", choices=["bench", "sink", "pub"])
    ap.add_argument("--heads", default="1,2,4", help="comma-separated N to measure (bench); a sink's head indices")
    ap.add_argument("--processes", default="1,2", help="comma-separated P of the fdi processes (P <= N)")
    ap.add_argument("--seconds", type=float, default=8.0, help="measured replay time of each phase")
    ap.add_argument("--nozzles", type=int, default=2656)
    ap.add_argument("--chunk", type=int, default=200, help="nozzles per message")
    ap.add_argument("--window", type=int, default=None, help="messages in flight per head (default one scan)")
    ap.add_argument("--scan-hz", type=float, default=0.0,
                    help="paced: each head sends one scan this many times a second, answered or not (0: closed loop)")
    ap.add_argument("--frames", type=int, default=4, help="distinct frames per head to cycle")
    ap.add_argument("--faulty", type=float, default=0.02, help="fraction of faulty nozzles")
    ap.add_argument("--no-baselines", action="store_true", help="run the fdi nodes without baselines")
    ap.add_argument("--executor", choices=("events", "single"), default="events", help="inkdiag printer --executor")
    ap.add_argument("--model", default=str(ROOT / "models" / "fdi_default.joblib"))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--head", type=int, default=0)
    ap.add_argument("--data", default="")
    ap.add_argument("--first-id", type=int, default=0)
    ap.add_argument("--n-heads", type=int, default=1, help=argparse.SUPPRESS)  # a publisher's: heads measured
    ap.add_argument("--json", default=None, help="also write the results to this JSON file")
    ns = ap.parse_args()
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    if ns.window is None:
        ns.window = -(-ns.nozzles // ns.chunk)
    if ns.role == "sink":
        return sink_main([int(h) for h in ns.heads.split(",")], ns.executor)
    if ns.role == "pub":
        return pub_main(ns.head, ns.data, ns.seconds, ns.window, ns.chunk, ns.first_id, ns.n_heads, ns.scan_hz)

    from graph import realistic_head
    from inkdiag_core.model_cache import ensure_default_model

    model = ensure_default_model(ns.model)
    n_list = [int(x) for x in ns.heads.split(",")]
    p_list = [int(x) for x in ns.processes.split(",")]
    tmp = Path(tempfile.mkdtemp(prefix="bench_printer_"))
    t = time.perf_counter()
    for i in range(max(n_list)):
        frames, baselines, n_faulty = realistic_head(ns.nozzles, ns.frames, ns.seed + 101 * i, faulty=ns.faulty)
        np.save(tmp / f"frames_{i:02d}.npy", np.stack(frames))
        baselines.save(tmp / f"head_{FIRST_HEAD + i:02d}.npz")
    print(f"printer benchmark: per head {ns.frames} frames of {ns.nozzles} nozzles x 512 samples, {n_faulty} faulty "
          f"({ns.faulty:.0%}), baselines of every nozzle ({time.perf_counter() - t:.0f} s for {max(n_list)} heads); "
          f"messages of {ns.chunk} nozzles, "
          + (f"one scan per head every {1 / ns.scan_hz:g} s (paced)" if ns.scan_hz > 0 else f"{ns.window} in flight per head")
          + f"; {ns.seconds:g} s per phase; "
          f"model {Path(model).name}; executor {ns.executor}"
          + ("; fdi WITHOUT baselines" if ns.no_baselines else "")
          + f"; load average {' '.join(Path('/proc/loadavg').read_text().split()[:3])}", flush=True)
    results, first_id = [], 0
    hdr = (f"{'phase':<28} {'traces/s':>10} {'per head':>9} {'msgs/s':>7} {'p50 ms':>7} {'p99 ms':>7} "
           f"{'lost':>5} {'CPU ms/msg':>10} {'cores':>5}  / ceiling" + ("  answered / sent" if ns.scan_hz > 0 else ""))
    print(hdr, flush=True)
    for n in n_list:
        p_sink = min(n, 2)
        phases = [(f"ceiling N={n} ({p_sink} procs)", [
            [sys.executable, __file__, "--role", "sink", "--heads", ",".join(str(i) for i in range(k, n, p_sink)),
             "--executor", ns.executor]
            for k in range(p_sink)])]
        for p in p_list:
            if p > n:
                continue
            cmd = [sys.executable, "-m", "inkdiag_ros.cli", "printer", "--heads", str(n), "--processes", str(p),
                   "--first-head", str(FIRST_HEAD),
                   "--model", str(model), "--executor", ns.executor]
            if not ns.no_baselines:
                cmd += ["--baselines", str(tmp / "head_{i:02d}.npz")]
            cmd += ["--ros-args", "-p", f"n_nozzles:={ns.nozzles}", "--log-level", "warn"]
            phases.append((f"fdi N={n} P={p}", [cmd]))
        ceiling = None
        for name, cmd in phases:
            r = phase(name, cmd, n, ns, tmp, first_id, tmp / f"{name.split(' (')[0].replace(' ', '_')}.log")
            first_id += 10_000_000
            ceiling = r["traces_per_s"] if ceiling is None else ceiling
            r["ratio"] = r["traces_per_s"] / ceiling
            results.append(r)
            print(f"{name:<28} {r['traces_per_s']:>10,.0f} {r['traces_per_s'] / n:>9,.0f} {r['msgs_per_s']:>7.1f} "
                  f"{r['p50_ms']:>7.1f} {r['p99_ms']:>7.1f} {r['lost']:>5d} {r['cpu_ms_per_msg']:>10.2f} "
                  f"{r['cores']:>5.2f}  {r['ratio']:.2f}x"
                  + (f"  {r['answered']} / {r['sent']}" if ns.scan_hz > 0 else ""), flush=True)
    print(f"load average at the end: {' '.join(Path('/proc/loadavg').read_text().split()[:3])}")
    if ns.json:
        Path(ns.json).write_text(json.dumps(results, indent=1))
    shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
