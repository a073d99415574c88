"""Benchmark of the fdi node on a full printhead, against the bare transport ceiling in the same run.

    scripts/bench graph [--nozzles 2656] [--faulty 0.02] [--no-baselines] [--chunk 200] [--seconds 8]
                        [--window N] [--model models/fdi_default.joblib]

Pre-generates frames of one realistic 2,656-nozzle head (512 samples,
``simulate_nozzles``: each nozzle keeps its tolerances from frame to frame, each
frame its own ink temperatures and noise; ``--faulty`` of the nozzles, 2 % by
default, have a random fault class, the others are healthy, half of them read
after the OK-check pulse; ``--faulty 1`` is the worst case, every nozzle faulty).
Unless ``--no-baselines``, the head's baselines with reference traces are recorded
first (``BaselineRecorder`` on 8 healthy frames of the same head) and given to
the fdi node (``baseline_path``: its healthy gate clears most healthy rows). Then
it replays the frames from this process into a second process, three times:

1. ceiling: a plain subscriber in the second process that decodes each frame
   (zero-copy header + view) and answers with a tiny ack carrying the frame id
   (with the allocator set as in every inkdiag node process, ``inkdiag_ros.allocator``);
2. fdi: the real fdi node (``python -m inkdiag_ros.fdi_node``) with the model,
   whose ``labels`` messages are the answers, labelling on its worker thread;
3. the same node with ``labelling_process:=true`` (the classifier in a child
   process: a third process on the same 2 cores).

Before all three, the fdi node's compute alone is timed in this process
(``FrameLabeller.label`` with the same model and baselines on the same messages,
one per call, and one head scan per call): what the node could reach if it had a core to itself and no transport;
its ratio to the ceiling bounds the node's on this machine.

All use the same closed loop: at most ``--window`` messages in flight
(published, not yet answered), so the consumer sets the pace. The default
window is one head scan (``ceil(nozzles / chunk)`` messages, 14): a printer
controller publishes a scan's nozzle ranges together, once per measurement. A frame
unanswered for 10x the worst latency of a 0.5 s warm-up (at least 50 ms) is
counted lost and its slot reused: the traces topic is best effort, and with 400 kB messages
Fast DDS drops a fraction of a percent of them between the processes, in the
ceiling run as much as in the fdi run; the fdi node's own counters (from
/diagnostics) say how many it received, so what is lost in transport and
what in the node are told apart. Latency is from the frame's source timestamp (set at publish) to its
answer arriving here (one clock). Prints traces/s of each, the ratios, loss,
and p50/p99 latency.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
ACK = "bench_ack"
FDI_THREAD = "fdi node"
FDI_PROCESS = "fdi, labelling process"


def sink_main() -> int:
    """Second process of the ceiling run: decode each frame, ack its id."""
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rclpy.node import Node
    from std_msgs.msg import String

    from inkdiag_ros.allocator import keep_freed_memory
    from msg_defs import RELIABLE_QOS, TRACE_MSG_TYPE, TRACES_QOS, decode_traces, topics

    keep_freed_memory()  # as every inkdiag node process: the same footing as the fdi node
    rclpy.init()
    node = Node("bench_sink")
    pub = node.create_publisher(String, ACK, RELIABLE_QOS)

    def on_frame(msg):
        f = decode_traces(msg)
        float(f.traces[0, 0])  # touch the data
        pub.publish(String(data=f"{f.frame_id}"))

    node.create_subscription(TRACE_MSG_TYPE, topics.TRACES, on_frame, TRACES_QOS)
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


def make_frames(n_nozzles, n_frames, seed, faulty=0.02):
    """``n_frames`` frames of one head (seed ``seed``), a ``faulty`` fraction of its nozzles faulty."""
    from inkdiag_core import FaultClass, simulate_nozzles
    from inkdiag_core.faults import HEALTHY_CLASSES

    rng = np.random.default_rng(seed)
    faults = np.array([c.value for c in FaultClass if c not in HEALTHY_CLASSES], dtype=object)
    jet, ok = FaultClass.HEALTHY_NOZZLE.value, FaultClass.OK_SIGNAL.value
    classes = np.where(rng.random(n_nozzles) < 0.5, jet, ok).astype(object)
    bad = rng.random(n_nozzles) < faulty
    classes[bad] = faults[rng.integers(faults.size, size=int(bad.sum()))]
    return [simulate_nozzles(classes, seed=seed, frame_seed=[seed, 100 + i]).traces for i in range(n_frames)]


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of process ``pid`` and its threads so far, s (Linux /proc)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return float("nan")
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def record_baselines(n_nozzles, seed, path):
    """The head's baselines with reference traces from 8 healthy frames, saved at ``path``."""
    from inkdiag_core import BaselineRecorder, simulate_nozzles

    rec = BaselineRecorder(n_frames=8)
    for f in range(8):
        rec.add(0, simulate_nozzles(["healthy_nozzle"] * n_nozzles, seed=seed, frame_seed=[seed, f]).traces)
    return rec.baselines().save(path)


def replay(node, executor, pub, msgs, answered, seconds, window, lost_after_s=0.25, first_id=0):
    """Closed-loop replay; returns (published, latencies s, lost ids, elapsed s).

    Frame ids start at ``first_id``: never reuse the ids of an earlier replay,
    or its late answers would be taken for this one's.
    """
    from msg_defs import restamp_traces

    in_flight = {}  # frame_id -> publish time
    lat, lost = [], []
    fid = first_id
    t0 = time.perf_counter()
    end = time.monotonic() + seconds
    while time.monotonic() < end or in_flight:
        if time.monotonic() < end and len(in_flight) < window:
            msg = msgs[fid % len(msgs)]
            now = time.time()
            restamp_traces(msg, frame_id=fid, stamp=now)
            pub.publish(msg)
            in_flight[fid] = now
            fid += 1
            continue
        executor.spin_once(timeout_sec=0.005)
        while answered:
            a_id, t_recv = answered.pop()
            if a_id in in_flight:
                lat.append(t_recv - in_flight.pop(a_id))
        t = time.time()
        for k in [k for k, v in in_flight.items() if t - v > lost_after_s]:
            in_flight.pop(k)
            lost.append(k)
        if time.monotonic() > end + 10:
            break
    return fid - first_id, np.array(lat), lost, time.perf_counter() - t0


def wait_for_match(executor, pub, sub_topic_count, timeout=30.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.05)
        if pub.get_subscription_count() > 0 and sub_topic_count():
            return True
    return False


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--role", default="bench", choices=["bench", "sink"])
    ap.add_argument("--nozzles", type=int, default=2656)
    ap.add_argument("--frames", type=int, default=8, help="distinct frames to pre-generate and cycle")
    ap.add_argument("--seconds", type=float, default=8.0, help="replay time of each phase")
    ap.add_argument("--window", type=int, default=None,
                    help="messages in flight at most (closed loop: a new one is published when one is "
                         "answered); default one head scan, ceil(nozzles / chunk)")
    ap.add_argument("--chunk", type=int, default=200,
                    help="nozzles per message: a head scan travels as contiguous nozzle ranges")
    ap.add_argument("--model", default=str(ROOT / "models" / "fdi_default.joblib"))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--faulty", type=float, default=0.02, help="fraction of faulty nozzles (1: the worst case)")
    ap.add_argument("--no-baselines", action="store_true", help="give the fdi node no baselines (no gate)")
    ns = ap.parse_args()
    if ns.role == "sink":
        return sink_main()
    if ns.window is None:
        ns.window = -(-ns.nozzles // ns.chunk)

    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from std_msgs.msg import String

    from inkdiag_core.persistence import read_manifest
    from inkdiag_core.model_cache import ensure_default_model
    from msg_defs import (DIAGNOSTICS_MSG_TYPE, DIAGNOSTICS_QOS, LABELS_MSG_TYPE, RELIABLE_QOS,
                          TRACE_MSG_TYPE, TRACES_QOS, decode_labels, diagnostics_values, encode_traces,
                          topics)

    model = ensure_default_model(ns.model)
    cfg = read_manifest(model).get("config", {})
    t = time.perf_counter()
    frames = make_frames(ns.nozzles, ns.frames, ns.seed, ns.faulty)
    import tempfile

    tmp = tempfile.TemporaryDirectory()
    base_path = None if ns.no_baselines else record_baselines(ns.nozzles, ns.seed, Path(tmp.name) / "head.npz")
    msgs = [encode_traces(x[i:i + ns.chunk], first_nozzle=i, frame_id=0, stamp=0.0)
            for x in frames for i in range(0, ns.nozzles, ns.chunk)]
    per_msg = [m.layout.dim[0].size for m in msgs]
    print(f"graph benchmark: {ns.frames} pre-generated frames of {ns.nozzles} nozzles x 512 samples "
          f"({frames[0].nbytes / 1e6:.1f} MB each, {time.perf_counter() - t:.1f} s) as messages of {ns.chunk} nozzles; "
          f"window {ns.window} messages in flight ({ns.window / -(-ns.nozzles // ns.chunk):.2g} head scans); "
          f"{ns.seconds:g} s per phase; model {Path(model).name} "
          f"({cfg.get('kind')}, {cfg.get('features')}); {100 * ns.faulty:g} % faulty; "
          f"{'no baselines' if base_path is None else 'baselines with references recorded (gate on)'}")

    # the fdi node's own compute alone, in this process: label_frames on one message per call
    # (the node's pace at light batching), same messages, same model
    from inkdiag_core import FrameLabeller, NozzleBaselines, load_detector
    from msg_defs import decode_traces

    labeller = FrameLabeller(load_detector(model), None if base_path is None else NozzleBaselines.load(base_path))
    blocks = [decode_traces(m).traces for m in msgs]
    firsts = [i for _ in frames for i in range(0, ns.nozzles, ns.chunk)]
    t0, done, k = time.perf_counter(), 0, 0
    while time.perf_counter() - t0 < min(ns.seconds, 3.0):
        labeller.label([blocks[k % len(blocks)]], [firsts[k % len(blocks)]])
        done += blocks[k % len(blocks)].shape[0]
        k += 1
    alone = done / (time.perf_counter() - t0)
    print(f"{'labelling alone (no ROS)':<26} {alone:>9,.0f} traces/s  (FrameLabeller, one {ns.chunk}-nozzle "
          "message per call, one thread, this process)")
    per_scan = -(-ns.nozzles // ns.chunk)
    t0, done, k = time.perf_counter(), 0, 0
    while time.perf_counter() - t0 < min(ns.seconds, 3.0):
        at = (k * per_scan) % len(blocks)
        scan = blocks[at:][:per_scan]
        labeller.label(scan, firsts[at:][:per_scan])
        done += sum(b.shape[0] for b in scan)
        k += 1
    alone_scan = done / (time.perf_counter() - t0)
    print(f"{'':<26} {alone_scan:>9,.0f} traces/s  (the same, one head scan of {per_scan} messages per call)")

    rclpy.init()
    node = Node("bench_replayer")
    ex = SingleThreadedExecutor()
    ex.add_node(node)
    pub = node.create_publisher(TRACE_MSG_TYPE, topics.TRACES, TRACES_QOS)
    answered, diag = [], {}
    node.create_subscription(String, ACK, lambda m: answered.append((int(m.data), time.time())), RELIABLE_QOS)
    node.create_subscription(LABELS_MSG_TYPE, topics.LABELS,
                             lambda m: answered.append((decode_labels(m).frame_id, time.time())), RELIABLE_QOS)
    node.create_subscription(DIAGNOSTICS_MSG_TYPE, topics.DIAGNOSTICS,
                             lambda m: diag.update(diagnostics_values(m)), DIAGNOSTICS_QOS)
    env = dict(os.environ)
    results = {}
    next_id = 0
    fdi = [sys.executable, "-m", "inkdiag_ros.fdi_node", "--ros-args", "-p", f"model_path:={model}",
           "-p", f"n_nozzles:={ns.nozzles}", "-p", "diagnostics_period_s:=0.5", "--log-level", "warn"]
    if base_path is not None:
        fdi += ["-p", f"baseline_path:={base_path}"]
    phases = [
        ("ceiling: plain subscriber", [sys.executable, __file__, "--role", "sink"],
         lambda: node.count_publishers(ACK) > 0),
        (FDI_THREAD, fdi, lambda: node.count_publishers(topics.LABELS) > 0),
        (FDI_PROCESS, fdi + ["-p", "labelling_process:=true"], lambda: node.count_publishers(topics.LABELS) > 0),
    ]
    try:
        for name, cmd, matched in phases:
            diag.clear()
            proc = subprocess.Popen(cmd, env=env, cwd=ROOT)
            try:
                if not wait_for_match(ex, pub, matched):
                    print(f"{name}: the second process never matched", file=sys.stderr)
                    return 1
                # warm-up: one frame through, unmeasured
                warm, warm_lat, *_ = replay(node, ex, pub, msgs, answered, 0.5, 1, first_id=next_id)
                next_id += warm
                answered.clear()
                # a frame is lost when unanswered for 10x the warm-up's worst latency (>= 50 ms):
                # a lost frame holds its window slot that long, so a fixed long timeout would
                # let transport losses, not the consumer, set the pace of a fast consumer
                lost_after = max(0.05, 10.0 * float(np.max(warm_lat))) if warm_lat.size else 0.25
                cpu0 = cpu_seconds(proc.pid)
                sent, lat, lost, el = replay(node, ex, pub, msgs, answered, ns.seconds, ns.window,
                                             lost_after_s=lost_after, first_id=next_id)
                cpu = cpu_seconds(proc.pid) - cpu0
                next_id += sent
                during = dict(next(iter(diag.values()), {}))  # the last period under load
                ex.spin_once(timeout_sec=0.6)
                t_end = time.monotonic() + 1.5
                while time.monotonic() < t_end:
                    ex.spin_once(timeout_sec=0.05)
                final = dict(next(iter(diag.values()), {}))
                if final:
                    final.update({k: during.get(k) for k in ("frames_per_batch", "labeller_busy")})
                results[name] = (sent, lat, lost, el, final, warm, lost_after, cpu)
            finally:
                proc.send_signal(2)
                try:
                    proc.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    proc.kill()
    finally:
        ex.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()

    rates = {}
    for name, (sent, lat, lost, el, d, warm, lost_after, cpu) in results.items():
        done = lat.size
        if not done:
            print(f"{name:<26} nothing answered: published {sent}, lost {len(lost)}")
            continue
        rates[name] = done * float(np.mean(per_msg)) / el
        line = (f"{name:<26} {rates[name]:>9,.0f} traces/s ({done / el:6.1f} msgs/s)  "
                f"published {sent}, answered {done}, lost {len(lost)} (> {1e3 * lost_after:.0f} ms)  "
                f"latency p50 {1e3 * np.percentile(lat, 50):6.1f} ms  p99 {1e3 * np.percentile(lat, 99):6.1f} ms  "
                f"CPU {1e3 * cpu / done:.2f} ms per message (the second process"
                f"{'; not its labelling child' if name == FDI_PROCESS else ''})")
        print(line)
        if d:
            print(f"{'':<26} fdi's own counters: received {d.get('frames_received')} "
                  f"(published {sent + warm}: {sent + warm - int(d.get('frames_received', 0))} lost in transport), labelled "
                  f"{d.get('frames_labelled')}, malformed {d.get('frames_malformed')}, "
                  f"failed {d.get('frames_failed')}, dropped {d.get('frames_dropped')} "
                  f"(of which {warm} warm-up frames); under load: {d.get('frames_per_batch')} frames per "
                  f"classifier pass, classifier busy {d.get('labeller_busy')} of the time; healthy gate cleared "
                  f"{d.get('count.gate_cleared', 'n/a')} rows")
    c = rates.get("ceiling: plain subscriber")
    if c:
        print(f"{'labelling alone:':<26} / ceiling = {alone_scan / c:.2f}x at one head scan per call: what a node "
              "could reach with a core to itself and no ROS cost at all")
    for name in (FDI_THREAD, FDI_PROCESS):
        f = rates.get(name)
        if c and f:
            p99 = np.percentile(results[name][1], 99)
            print(f"{name + ':':<26} / ceiling = {f / c:.2f}x (aim >= 0.5x); p99 {'<=' if p99 <= 0.05 else '>'} 50 ms; "
                  f"/ labelling alone = {f / alone:.2f}x (one message per call), "
                  f"{f / alone_scan:.2f}x (one head scan per call)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
