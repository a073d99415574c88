"""Benchmark of the fdi node on a full printhead, against the bare transport ceiling in the same run.

    scripts/bench graph [--case both|realistic|worst|mixed] [--nozzles 2656] [--chunk 200] [--seconds 8]
                        [--window N | --scans] [--no-baselines] [--no-process] [--model models/fdi_default.joblib]
                        [--fdi-param NAME:=VALUE ...] [--rounds N] [--ref COMMIT]

Pre-generates frames of a realistic 2,656-nozzle head (512 samples; :func:`realistic_head`: every nozzle
its own tolerances, the faults the same in every frame, every nozzle's healthy baseline recorded by
``BaselineRecorder`` from 8 healthy frames of the same nozzles and given to the fdi node as its
``baseline_path``) in two cases: ``realistic`` (2 % of the nozzles faulty) and ``worst`` (every nozzle
faulty); ``--case mixed`` is the earlier benchmark's data (10 % faulty, ``simulate_nozzles`` with new
nozzles each frame, no baselines). Then replays them from this process into a second process:

1. ceiling: a plain subscriber in the second process that decodes each frame
   (zero-copy header + view) and answers with a tiny ack carrying the frame id, spun
   as the fdi node is (``spin_node(..., events=True)``: the allocator setting of every
   inkdiag node process, ``inkdiag_ros.allocator``, and rclpy's ``EventsExecutor``);
2. per case, fdi: the real fdi node (``python -m inkdiag_ros.fdi_node``) with the model
   and the case's baselines, whose ``labels`` messages are the answers, labelling on its executor thread;
3. per case, the same node with ``labelling_process:=true`` (the classifier in a child
   process: a third process on the same 2 cores; ``--no-process`` skips it).

``--rounds N`` runs the phases N times in turn (ceiling, fdi, ..., ceiling, fdi, ...) and gives each
round's ratios against that round's ceiling, then their range and median: on a shared machine the
ceiling moves from one minute to the next (a factor 2 within three runs), more than the fdi node does.

``--fdi-param NAME:=VALUE`` (repeatable) gives the fdi node one more ROS parameter in every fdi phase,
e.g. ``max_batch_traces:=800`` (classifier passes of at most 4 messages).

``--ref COMMIT`` adds, per case and right after this tree's fdi node, the fdi node of an older
commit on the same frames (its ``inkdiag_core``, ``msg_defs`` and ``inkdiag_ros`` extracted with
``git archive`` and put first on its PYTHONPATH; its own default model, trained by its own
``model_cache``; its own baselines, recorded by its own ``BaselineRecorder`` from the same healthy
frames), and prints this tree's traces/s over it, round by round: a same-run baseline, e.g.
``--ref 46a687e`` for the node issue 17 was measured on ("the worst case not slower than today").
``--fdi-param`` goes to that node too (one it does not declare is ignored; not ``model_path`` or
``baseline_path``).

Before them, the fdi node's compute alone is timed in this process
(``label_frames``, the plain branch, on the same messages, one per call, and one head scan per
call): what the node could reach if it had a core to itself and no transport.
The CPU of the second process (and its children) over the measured phase, from
``/proc/<pid>/stat``, divided by the messages answered, is the CPU per message.

All use the same closed loop: at most ``--window`` messages in flight
(published, not yet answered), so the consumer sets the pace. The default
window is one head scan (``ceil(nozzles / chunk)`` messages, 14): a printer
controller publishes a scan's nozzle ranges together, once per measurement.
``--scans``: a whole scan goes out together and the next once all of its messages
are answered (one scan in flight, the issue's protocol; the window sliding by one
message keeps the consumer's queue fuller). A frame
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
FDI_REF = "fdi node at --ref"
REF_PACKAGES = ("inkdiag_core", "msg_defs", "inkdiag_ros")
RECORD_REF = """import sys
import numpy as np
from inkdiag_core import BaselineRecorder
healthy = np.load(sys.argv[1])
rec = BaselineRecorder(n_frames=len(healthy))
for traces in healthy:
    rec.add(0, traces)
rec.baselines().save(sys.argv[2])
"""
"""The --ref tree's own baselines from the same healthy frames (its baselines file format may be older)."""
CEILING = "ceiling: plain subscriber"


def sink_main(namespace: str = "/") -> int:
    """Second process of the ceiling run: decode each frame, ack its id; spun as the fdi node is spun.

    ``inkdiag_ros._spin.spin_node(..., events=True)``, fdi's own entry point: the allocator setting,
    one BLAS thread and rclpy's C++ ``EventsExecutor``. (Until 2026-11-26 the sink spun the Python
    ``SingleThreadedExecutor`` while fdi spun the ``EventsExecutor``: the ceiling read below what
    the transport takes, and fdi / ceiling overstated the fair ratio roughly 1.5-2x; ``reports/bench.md``.)
    """
    from rclpy.node import Node
    from std_msgs.msg import String

    from inkdiag_ros._spin import spin_node
    from msg_defs import RELIABLE_QOS, TRACE_MSG_TYPE, TRACES_QOS, decode_traces, topics

    class Sink(Node):
        def __init__(self):
            super().__init__("bench_sink", namespace=namespace)
            pub = self.create_publisher(String, ACK, RELIABLE_QOS)

            def on_frame(msg):
                f = decode_traces(msg)
                float(f.traces[0, 0])  # touch the data
                pub.publish(String(data=f"{f.frame_id}"))

            self.create_subscription(TRACE_MSG_TYPE, topics.TRACES, on_frame, TRACES_QOS)

    return spin_node(Sink, ["bench_sink"], events=True)


def make_frames(n_nozzles, n_frames, seed):
    from inkdiag_core import FaultClass, simulate_nozzles
    from inkdiag_core.faults import HEALTHY_CLASSES

    rng = np.random.default_rng(seed)
    classes = list(FaultClass)
    p = np.full(len(classes), 0.1 / (len(classes) - len(HEALTHY_CLASSES)))
    p[[classes.index(c) for c in HEALTHY_CLASSES]] = 0.45
    return [simulate_nozzles(rng.choice(np.array(classes, dtype=object), size=n_nozzles, p=p),
                             seed=seed + i).traces for i in range(n_frames)]


def realistic_head(n_nozzles, n_frames, seed, *, faulty=0.02, n_baseline_frames=8):
    """Frames of one realistic head and its nozzles' healthy baselines, recorded as commissioning does.

    Every nozzle has its own tolerances (``simulate_nozzles(seed=seed)``) and one of the two
    healthy conditions; ``round(faulty * n_nozzles)`` nozzles (seeded choice) carry a fault of a
    seeded class among the ten fault classes, the same in every frame; frames differ in their
    ink temperature and noise (``frame_seed``). The baselines are recorded from
    ``n_baseline_frames`` frames of the same nozzles all healthy and jetting (``healthy_nozzle``:
    the jetting pulse, as commissioning records them, docs/nodes.md; not the OK-check pulse of an
    ``ok_signal`` nozzle, whose faults the model would then see 1.25x its baseline's amplitude and
    call ``unknown``), by :class:`inkdiag_core.BaselineRecorder` (whatever it records: KPI
    baselines, and the healthy references once the gate records them).

    Returns
    -------
    frames : list of ndarray, shape (n_nozzles, 512), float32
        V.
    baselines : inkdiag_core.NozzleBaselines
        Every nozzle's.
    n_faulty : int
    """
    frames, healthy, n_faulty = head_recordings(n_nozzles, n_frames, seed, faulty=faulty,
                                                n_baseline_frames=n_baseline_frames)
    return frames, record_baselines(healthy), n_faulty


def record_baselines(healthy):
    """The baselines :class:`inkdiag_core.BaselineRecorder` records from ``healthy`` frames of the nozzles 0.., as
    commissioning does (the --ref tree records its own from the same frames: :data:`RECORD_REF`)."""
    from inkdiag_core import BaselineRecorder

    rec = BaselineRecorder(n_frames=len(healthy))
    for traces in healthy:
        rec.add(0, traces)
    return rec.baselines()


def head_recordings(n_nozzles, n_frames, seed, *, faulty=0.02, n_baseline_frames=8):
    """:func:`realistic_head`'s frames, and the healthy frames its baselines are recorded from.

    Returns
    -------
    frames : list of ndarray, shape (n_nozzles, 512), float32
        V.
    healthy : list of ndarray, shape (n_nozzles, 512), float32
        ``n_baseline_frames`` frames of the same nozzles all healthy and jetting (``healthy_nozzle``), V.
    n_faulty : int
    """
    from inkdiag_core import FaultClass, simulate_nozzles
    from inkdiag_core.faults import HEALTHY_CLASSES

    rng = np.random.default_rng(seed)
    healthy = np.array(sorted(HEALTHY_CLASSES, key=lambda c: c.value), dtype=object)
    faults = np.array([c for c in FaultClass if c not in HEALTHY_CLASSES], dtype=object)
    classes = rng.choice(healthy, size=n_nozzles)  # each nozzle's healthy condition
    jetting = np.full(n_nozzles, FaultClass.HEALTHY_NOZZLE, dtype=object)  # commissioning: the jetting pulse
    recorded = [simulate_nozzles(jetting, seed=seed, frame_seed=1_000_000 + k).traces for k in range(n_baseline_frames)]
    n_faulty = int(round(faulty * n_nozzles))
    idx = rng.choice(n_nozzles, n_faulty, replace=False)
    classes[idx] = rng.choice(faults, size=n_faulty)
    frames = [simulate_nozzles(classes, seed=seed, frame_seed=k).traces for k in range(n_frames)]
    return frames, recorded, n_faulty


def replay(node, executor, pub, msgs, answered, seconds, window, lost_after_s=0.25, first_id=0,
           scan_hz=0.0, scan_msgs=1, scans=False):
    """Replay; returns (published, latencies s, lost ids, elapsed s).

    Closed loop (``scan_hz`` 0): a message goes out whenever fewer than ``window`` are
    unanswered; with ``scans``, the next head scan (``scan_msgs`` messages, together) once
    every message of the one before is answered or lost (one scan in flight). Paced (``scan_hz`` > 0): every ``1 / scan_hz`` s the next ``scan_msgs``
    messages (one head scan: ``msgs`` holds whole scans in order) go out together,
    answered or not, as a head controller sends them; a publisher that falls behind skips
    the missed scan (never two at a time); an answer later than ``lost_after_s`` is lost. Frame ids start at ``first_id``: never
    reuse the ids of an earlier replay, or its late answers would be taken for this one's.
    """
    from msg_defs import restamp_traces

    in_flight = {}  # frame_id -> publish time
    lat, lost = [], []
    fid = first_id
    t0 = time.perf_counter()
    end = time.monotonic() + seconds
    next_scan = time.monotonic()
    while time.monotonic() < end or in_flight:
        now_m = time.monotonic()
        due = scan_msgs if scan_hz > 0 and now_m < end and now_m >= next_scan else 0
        if scan_hz <= 0 and now_m < end and (not in_flight if scans else len(in_flight) < window):
            due = scan_msgs if scans else 1
        if due:
            for _ in range(due):
                msg = msgs[(fid - first_id if scan_hz > 0 or scans else fid) % len(msgs)]  # scans whole
                now = time.time()
                restamp_traces(msg, frame_id=fid, stamp=now)
                pub.publish(msg)
                in_flight[fid] = now
                fid += 1
            if scan_hz > 0:
                next_scan += 1.0 / scan_hz
                if next_scan <= time.monotonic():  # behind: the missed scan is skipped, never two at once
                    next_scan = time.monotonic() + 1.0 / scan_hz
            continue
        now_m = time.monotonic()
        wait = 0.005 if scan_hz <= 0 or now_m >= end else min(0.005, max(0.0, next_scan - now_m))
        executor.spin_once(timeout_sec=wait)
        while answered:
            a_id, t_recv = answered.pop()
            if a_id in in_flight:
                d = t_recv - in_flight.pop(a_id)
                if scan_hz > 0 and d > lost_after_s:  # paced: an answer later than the rule is a loss
                    lost.append(a_id)
                else:
                    lat.append(d)
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


def tree_pids(pid: int) -> list:
    """``pid`` and its descendants (from /proc/<pid>/task/*/children)."""
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        try:
            for task in os.listdir(f"/proc/{p}/task"):
                with open(f"/proc/{p}/task/{task}/children") as f:
                    todo += [int(c) for c in f.read().split()]
        except OSError:
            pass
    return out


def cpu_s(pids) -> float:
    """utime + stime of ``pids`` (from /proc/<pid>/stat), s; a process gone counts 0."""
    tick = os.sysconf("SC_CLK_TCK")
    total = 0.0
    for pid in pids:
        try:
            with open(f"/proc/{pid}/stat") as f:
                fields = f.read().rsplit(") ", 1)[1].split()
            total += (int(fields[11]) + int(fields[12])) / tick
        except OSError:
            pass
    return total


CASES = {"realistic": 0.02, "worst": 1.0}
"""Fraction of faulty nozzles of each case (``--case``)."""


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--role", default="bench", choices=["bench", "sink"])
    ap.add_argument("--nozzles", type=int, default=2656)
    ap.add_argument("--frames", type=int, default=8, help="distinct frames to pre-generate and cycle")
    ap.add_argument("--seconds", type=float, default=8.0, help="replay time of each phase")
    loop = ap.add_mutually_exclusive_group()
    loop.add_argument("--window", type=int, default=None,
                    help="messages in flight at most (closed loop: a new one is published when one is "
                         "answered); default one head scan, ceil(nozzles / chunk)")
    loop.add_argument("--scans", action="store_true",
                    help="closed loop by head scans instead of --window: a scan's messages go out together, the "
                         "next scan once all of them are answered (one scan in flight, as a controller that "
                         "waits for a scan's labels)")
    ap.add_argument("--chunk", type=int, default=200,
                    help="nozzles per message: a head scan travels as contiguous nozzle ranges")
    ap.add_argument("--case", choices=["both", "realistic", "worst", "mixed"], default="both",
                    help="realistic: 2 %% of the nozzles faulty; worst: every nozzle faulty; both (default); "
                         "mixed: the earlier benchmark's frames (10 %% faulty, new nozzles every frame, no baselines)")
    ap.add_argument("--no-baselines", action="store_true", help="the fdi node without the recorded baselines")
    ap.add_argument("--no-process", action="store_true", help="skip the labelling_process phase")
    ap.add_argument("--fdi-param", action="append", default=[], metavar="NAME:=VALUE",
                    help="one more ROS parameter of the fdi node (repeatable), e.g. max_batch_traces:=800")
    ap.add_argument("--model", default=str(ROOT / "models" / "fdi_default.joblib"))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--rounds", type=int, default=1, help="the phases this many times in turn, each round's ratios "
                    "against its own ceiling")
    ap.add_argument("--ref", metavar="COMMIT", help="also the fdi node of an older commit, in each round right after "
                    "this tree's, on the same frames: its inkdiag_core, msg_defs and inkdiag_ros extracted with "
                    "git archive, its own default model trained by its own code, its own baselines recorded from "
                    "the same healthy frames (e.g. 46a687e, the tree issue 17 was filed against)")
    ap.add_argument("--namespace", default="/", help=argparse.SUPPRESS)  # the sink's
    ns = ap.parse_args()
    if bad := [p for p in ns.fdi_param if ":=" not in p]:
        ap.error(f"--fdi-param takes NAME:=VALUE, got {bad[0]!r}")
    if ns.rounds < 1:
        ap.error(f"--rounds must be >= 1, got {ns.rounds}")
    if ns.ref and (own := [p for p in ns.fdi_param if p.split(":=")[0] in ("model_path", "baseline_path")]):
        ap.error(f"--fdi-param {own[0]} with --ref: each tree's node takes its own model and baselines")
    if ns.role == "sink":
        return sink_main(ns.namespace)
    if ns.window is None:
        ns.window = -(-ns.nozzles // ns.chunk)

    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    import tempfile

    import rclpy
    from rclpy.experimental import EventsExecutor
    from rclpy.node import Node
    from std_msgs.msg import String

    from inkdiag_core import label_frames, load_model
    from inkdiag_core.model_cache import ensure_default_model
    from inkdiag_core.persistence import read_manifest
    from msg_defs import (DIAGNOSTICS_MSG_TYPE, DIAGNOSTICS_QOS, LABELS_MSG_TYPE, RELIABLE_QOS,
                          TRACE_MSG_TYPE, TRACES_QOS, decode_labels, decode_traces, diagnostics_values,
                          encode_traces, topics)

    model = ensure_default_model(ns.model)
    cfg = read_manifest(model).get("config", {})
    pipe, manifest = load_model(model)
    thr = float(manifest.get("config", {}).get("fd_threshold", 0.5))
    per_scan = -(-ns.nozzles // ns.chunk)
    tmp = Path(tempfile.mkdtemp(prefix="bench_graph_"))
    cases = ["realistic", "worst"] if ns.case == "both" else [ns.case]
    data = {}
    for case in cases:
        t = time.perf_counter()
        if case == "mixed":
            frames, base, what = make_frames(ns.nozzles, ns.frames, ns.seed), None, "10 % faulty (mixed), no baselines"
        else:
            frames, healthy, n_faulty = head_recordings(ns.nozzles, ns.frames, ns.seed, faulty=CASES[case])
            base = None if ns.no_baselines else str(record_baselines(healthy).save(tmp / f"{case}.npz"))
            if ns.ref and base:
                np.save(tmp / f"{case}_healthy.npy", np.stack(healthy))
            what = (f"{n_faulty} faulty ({CASES[case]:.0%}), "
                    + ("baselines NOT given to fdi" if ns.no_baselines else "baselines of every nozzle recorded"))
        msgs = [encode_traces(x[i:i + ns.chunk], first_nozzle=i, frame_id=0, stamp=0.0)
                for x in frames for i in range(0, ns.nozzles, ns.chunk)]
        data[case] = (msgs, base, what, time.perf_counter() - t)
    ref = prepare_ref(ns.ref, tmp, [c for c in cases if data[c][1]]) if ns.ref else None
    print(f"graph benchmark: {ns.frames} pre-generated frames of {ns.nozzles} nozzles x 512 samples per case "
          f"({frames[0].nbytes / 1e6:.1f} MB each) as messages of {ns.chunk} nozzles; "
          + ("one head scan in flight (--scans); " if ns.scans else
             f"window {ns.window} messages in flight ({ns.window / per_scan:.2g} head scans); ")
          + f"{ns.seconds:g} s per phase; model {Path(model).name} ({cfg.get('kind')}, {cfg.get('features')})"
          + (f"; fdi parameters {' '.join(ns.fdi_param)}" if ns.fdi_param else "")
          + (f"; {FDI_REF}: {ns.ref}'s node with its own default model ({ref[2]}) and baselines" if ref else ""))
    for case in cases:
        msgs, base, what, gen_s = data[case]
        print(f"case {case}: {what} ({gen_s:.1f} s to generate)")
        # the node's own compute alone, in this process (label_frames: the plain branch, no baselines)
        blocks = [decode_traces(m).traces for m in msgs]
        for per_call, label in ((1, "message"), (per_scan, "head scan")):
            t0, done, k = time.perf_counter(), 0, 0
            while time.perf_counter() - t0 < min(ns.seconds, 2.0):
                scan = blocks[(k * per_call) % len(blocks):][:per_call]
                label_frames(pipe, scan, fd_threshold=thr)
                done += sum(b.shape[0] for b in scan)
                k += 1
            data[case] += (done / (time.perf_counter() - t0),)
            print(f"  {'labelling alone (no ROS)':<30} {data[case][-1]:>9,.0f} traces/s  (label_frames, plain branch, "
                  f"one {label} per call, one thread, this process)")

    rclpy.init()
    # a namespace of its own: another process on this domain (a test elsewhere) is not taken for ours
    bench_ns = f"/bench_graph_{os.getpid()}"
    node = Node("bench_replayer", namespace=bench_ns)
    ex = EventsExecutor(context=node.context)  # the C++ executor: the publisher keeps up with the ceiling
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
    fdi = [sys.executable, "-m", "inkdiag_ros.fdi_node", "--ros-args", "-r", f"__ns:={bench_ns}", "-p", f"model_path:={model}",
           "-p", f"n_nozzles:={ns.nozzles}", "-p", "diagnostics_period_s:=0.5", "--log-level", "warn"]
    for param in ns.fdi_param:
        fdi += ["-p", param]
    phases = [(CEILING, cases[0], [sys.executable, __file__, "--role", "sink", "--namespace", bench_ns],
               lambda: node.count_publishers(f"{bench_ns}/{ACK}") > 0)]
    for case in cases:
        cmd = fdi + (["-p", f"baseline_path:={data[case][1]}"] if data[case][1] else [])
        phases.append((f"{case}: {FDI_THREAD}", case, cmd, lambda: node.count_publishers(f"{bench_ns}/{topics.LABELS}") > 0))
        if ref:
            ref_env, ref_model, _ = ref
            ref_cmd = [a.replace(f"model_path:={model}", f"model_path:={ref_model}") for a in fdi]
            ref_cmd += ["-p", f"baseline_path:={tmp / f'{case}_ref.npz'}"] if data[case][1] else []
            phases.append((f"{case}: {FDI_REF}", case, (ref_cmd, ref_env),
                           lambda: node.count_publishers(f"{bench_ns}/{topics.LABELS}") > 0))
        if not ns.no_process:
            phases.append((f"{case}: {FDI_PROCESS}", case, cmd + ["-p", "labelling_process:=true"],
                           lambda: node.count_publishers(f"{bench_ns}/{topics.LABELS}") > 0))
    if ns.rounds > 1:  # each phase's name with its round: "ceiling: plain subscriber [2]"
        phases = [(f"{name} [{r + 1}]", case, cmd, matched)
                  for r in range(ns.rounds) for name, case, cmd, matched in phases]
    try:
        for name, case, cmd, matched in phases:
            msgs = data[case][0]
            diag.clear()
            cmd, penv = cmd if isinstance(cmd, tuple) else (cmd, env)  # the --ref node: its own PYTHONPATH
            proc = subprocess.Popen(cmd, env=penv, cwd=ROOT)
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
                pids = tree_pids(proc.pid)  # with labelling_process: its child too
                c0 = cpu_s(pids)
                sent, lat, lost, el = replay(node, ex, pub, msgs, answered, ns.seconds, ns.window,
                                             lost_after_s=lost_after, first_id=next_id, scan_msgs=per_scan,
                                             scans=ns.scans)
                cpu = cpu_s(pids) - c0
                next_id += sent
                mine = f"inkdiag fdi: {bench_ns}"
                during = dict(diag.get(mine, {}))  # the last period under load
                ex.spin_once(timeout_sec=0.6)
                t_end = time.monotonic() + 1.5
                while time.monotonic() < t_end:
                    ex.spin_once(timeout_sec=0.05)
                final = dict(diag.get(mine, {}))
                if final:
                    final.update({k: during.get(k) for k in ("frames_per_batch", "labeller_busy")})
                per_msg = float(np.mean([m.layout.dim[0].size for m in msgs]))
                results[name] = (sent, lat, lost, el, final, warm, lost_after, cpu, per_msg, case)
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
    for name, (sent, lat, lost, el, d, warm, lost_after, cpu, per_msg, case) in results.items():
        done = lat.size
        if not done:
            print(f"{name:<34} nothing answered: published {sent}, lost {len(lost)}")
            continue
        rates[name] = done * per_msg / el
        print(f"{name:<34} {rates[name]:>9,.0f} traces/s ({done / el:6.1f} msgs/s)  "
              f"published {sent}, answered {done}, lost {len(lost)} (> {1e3 * lost_after:.0f} ms)  "
              f"latency p50 {1e3 * np.percentile(lat, 50):6.1f} ms  p99 {1e3 * np.percentile(lat, 99):6.1f} ms  "
              f"CPU {1e3 * cpu / done:.2f} ms per message ({cpu / el:.2f} cores)")
        if d:
            print(f"{'':<34} fdi's own counters: received {d.get('frames_received')} "
                  f"(published {sent + warm}: {sent + warm - int(d.get('frames_received', 0))} lost in transport), labelled "
                  f"{d.get('frames_labelled')}, malformed {d.get('frames_malformed')}, "
                  f"failed {d.get('frames_failed')}, dropped {d.get('frames_dropped')} "
                  f"(of which {warm} warm-up frames), rows vs their baseline {d.get('rows_with_baseline')}"
                  + (f", cleared by the gate {d['gate_cleared']}" if "gate_cleared" in d else "")
                  + f"; under load: {d.get('frames_per_batch')} frames per classifier pass, "
                  f"classifier busy {d.get('labeller_busy')} of the time")
    import shutil

    shutil.rmtree(tmp, ignore_errors=True)
    ratios = {}
    for tag in ([""] if ns.rounds == 1 else [f" [{r + 1}]" for r in range(ns.rounds)]):
        c = rates.get(CEILING + tag)
        for case in cases:
            if c:
                alone_scan = data[case][5]
                print(f"{case + ': labelling alone' + tag:<34} / ceiling = {alone_scan / c:.2f}x at one head scan per "
                      "call: what a node could reach with a core to itself and no ROS cost at all (plain branch)")
            for kind in (FDI_THREAD, FDI_PROCESS, FDI_REF):
                name = f"{case}: {kind}{tag}"
                f = rates.get(name)
                if c and f:
                    ratios.setdefault(f"{case}: {kind}", []).append(f / c)
                    p99 = np.percentile(results[name][1], 99)
                    print(f"{name + ':':<34} / ceiling = {f / c:.2f}x (aim >= 0.5x); p99 "
                          f"{1e3 * p99:.1f} ms ({'<=' if p99 <= 0.05 else '>'} 50 ms); lost {len(results[name][2])}")
            if (f := rates.get(f"{case}: {FDI_THREAD}{tag}")) and (r := rates.get(f"{case}: {FDI_REF}{tag}")):
                ratios.setdefault(f"{case}: {FDI_THREAD} / {FDI_REF}", []).append(f / r)
                print(f"{case + ': ' + FDI_THREAD + tag:<34} / {ns.ref}'s node = {f / r:.2f}x (traces/s)")
    if ns.rounds > 1:
        for name, r in ratios.items():
            what = f"{name}:" if " / " in name else f"{name + ':':<34} / its round's ceiling"
            print(f"{what} over {len(r)} rounds: {min(r):.2f}-{max(r):.2f}x, median {float(np.median(r)):.2f}x")
    return 0


def prepare_ref(commit: str, tmp: Path, cases) -> tuple:
    """``commit``'s packages under ``tmp / "ref"``, its default model trained by its own code, its own baselines.

    Returns (the environment its node runs in, its model's path, the model's kind and features).
    """
    import json

    from node import extract

    path = extract(commit, tmp / "ref", REF_PACKAGES)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([*(str(path / p) for p in REF_PACKAGES),
                                                         *filter(None, [os.environ.get("PYTHONPATH")])])}
    model = tmp / "ref_model" / "fdi_default.joblib"  # the default's name: its default's settings (baseline branch)
    model.parent.mkdir()
    subprocess.run([sys.executable, "-m", "inkdiag_ros.model_cache", str(model)], env=env, cwd=path, check=True,
                   stdout=subprocess.DEVNULL)
    for case in cases:
        subprocess.run([sys.executable, "-c", RECORD_REF, str(tmp / f"{case}_healthy.npy"), str(tmp / f"{case}_ref.npz")],
                       env=env, cwd=path, check=True)
    # its compiled kernels into its own cache now (as its bootstrap would), not while the phase waits for its node
    # (a first start compiling them all outlasted the 30 s wait once); a commit before the kernels has none
    subprocess.run([sys.executable, "-m", "inkdiag_core._kernels"], env=env, cwd=path, check=False,
                   stderr=subprocess.DEVNULL)
    cfg = json.loads(Path(f"{model}.manifest.json").read_text()).get("config", {})
    return env, str(model), f"{cfg.get('kind')}, {cfg.get('features')}"


if __name__ == "__main__":
    sys.exit(main())
