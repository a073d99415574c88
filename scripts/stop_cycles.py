"""Stop every node process repeatedly, under CPU contention; count hangs and slow stops.

    scripts/stop_cycles.py [--cycles 20] [--nodes printhead_sim fdi fe record_baseline graph]
                           [--hang-s 2.0] [--busy N] [--unfed] [--dump] [--seed 0]

For each node: its upstream processes start (fe: printhead_sim and fdi, so that fe
estimates drying nozzles; fdi and record_baseline: printhead_sim), then ``--cycles``
times: start the node as its own process, wait until it works (its first output
message; the graph runner's first summary line; record_baseline's name in the ROS
graph and DDS threads in its process), wait a random 0-0.5 s more, send it SIGINT or
SIGTERM (alternately) and time its exit. A stop that exits later than ``--hang-s`` s
after the signal is slow; one still running 5 s after that is a hang (it gets the
signal again, SIGKILL 5 s later; ``--dump``: py-spy dumps it first, if installed).
``--unfed`` also cycles fdi, fe and record_baseline without their upstream nodes
(nothing arrives to wake them). One busy-loop process per core runs throughout
(``--busy``). Prints per node and signal: stops, hangs, slow stops, exits with a status the node does not document (record_baseline: 0, or 1 when stopped before any nozzle's baseline was complete),
and exit-time percentiles (ms) of the stops that exited by themselves.

Runs on the ``ROS_DOMAIN_ID`` of its environment (scripts/_bootstrap.sh sets one) with
discovery on localhost; a small FDI model is trained into a temporary directory first.
The test suite runs the same cycles, two per signal and node (tests/ros/test_node_stops.py).
Run it as ``source scripts/_bootstrap.sh && python scripts/stop_cycles.py``.
"""

from __future__ import annotations

import argparse
import os
import random
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field

import numpy as np

os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
if os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] != "LOCALHOST":  # never leave loopback
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"

NODES = ("printhead_sim", "fdi", "fe", "record_baseline", "graph")
NAMESPACE = "/stop_cycles"
# three drying nozzles, so that fe estimates every frame; fdi labels them dried from the start
SIM = {"n_nozzles": 16, "frame_rate_hz": 10.0, "fault_nozzles": [3], "fault_classes": ["fully_blocked"],
       "drying_nozzles": [5, 9, 13], "drying_start_factor": 2.6, "drying_end_factor": 8.5,
       "drying_duration_s": 600.0}
MODULES = {"printhead_sim": "inkdiag_ros.printhead_sim", "fdi": "inkdiag_ros.fdi_node",
           "fe": "inkdiag_ros.fe_node", "record_baseline": "inkdiag_ros.baseline_node",
           "graph": "inkdiag_ros.graph"}
UPSTREAM = {"printhead_sim": (), "fdi": ("printhead_sim",), "fe": ("printhead_sim", "fdi"),
            "record_baseline": ("printhead_sim",), "graph": ()}


def _p(name, value) -> list[str]:
    if isinstance(value, list):
        value = "[" + ",".join(f"'{x}'" if isinstance(x, str) else str(x) for x in value) + "]"
    return ["-p", f"{name}:={value}"]


def node_command(name: str, model_path: str, tmpdir: str) -> list[str]:
    """The command line of node ``name`` (its console entry point when installed beside python)."""
    exe = os.path.join(os.path.dirname(sys.executable), name)
    head = [exe] if os.path.exists(exe) else [sys.executable, "-m", MODULES[name]]
    sim_args = [a for k, v in SIM.items() for a in _p(k, v)]
    if name == "graph":
        return head + ["--duration", "0", "--model", model_path, "--no-baseline", "--namespace", NAMESPACE,
                       "--ros-args"] + sim_args
    ros = ["--ros-args", "-r", f"__ns:={NAMESPACE}"]
    if name == "printhead_sim":
        return head + ros + sim_args
    if name == "fdi":
        return head + ros + _p("model_path", model_path) + _p("n_nozzles", SIM["n_nozzles"])
    if name == "record_baseline":  # never finishes by itself during a cycle
        return head + ros + _p("output_path", os.path.join(tmpdir, "b.npz")) + _p("n_frames", 1000) \
            + _p("timeout_s", 3600.0)
    return head + ros


#: A busy loop that ends when the process that started it is gone (a killed test run
#: must not leave loops spinning on the machine's cores).
_BUSY_LOOP = (
    "import os, sys\n"
    "parent = int(sys.argv[1])\n"
    "while os.getppid() == parent:\n"
    "    for _ in range(2_000_000):\n"
    "        pass\n"
)


class _Proc:
    """A node process whose output a thread collects (lines)."""

    def __init__(self, cmd, env):
        self.popen = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                      text=True, start_new_session=True)
        self.lines: list[str] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self):
        for line in self.popen.stdout:
            self.lines.append(line)

    def output(self) -> str:
        self._reader.join(timeout=2.0)
        return "".join(self.lines)

    def stop(self, timeout_s: float = 5.0):
        if self.popen.poll() is None:
            self.popen.send_signal(signal.SIGINT)
            try:
                self.popen.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.popen.kill()
                self.popen.wait()


def _has_dds(pid: int) -> bool:
    """Whether process ``pid`` runs Fast DDS threads yet (its rclpy is initialised)."""
    try:
        return any(open(f"/proc/{pid}/task/{t}/comm").read().startswith("dds.")
                   for t in os.listdir(f"/proc/{pid}/task"))
    except OSError:
        return False


class Probe:
    """An rclpy node in this process that tells when a node process works."""

    def __init__(self, context):
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node

        from msg_defs import ESTIMATES_MSG_TYPE, LABELS_MSG_TYPE, RELIABLE_QOS, TRUTH_MSG_TYPE, topics

        self.node = Node("stop_cycles_probe", namespace=NAMESPACE, context=context)
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.node)
        self.seen = {"printhead_sim": 0, "fdi": 0, "fe": 0}
        for key, msg_type, topic in (("printhead_sim", TRUTH_MSG_TYPE, topics.GROUND_TRUTH),
                                     ("fdi", LABELS_MSG_TYPE, topics.LABELS),
                                     ("fe", ESTIMATES_MSG_TYPE, topics.FM_ESTIMATES)):
            self.node.create_subscription(msg_type, topic, lambda _m, k=key: self._count(k), RELIABLE_QOS)

    def _count(self, key):
        self.seen[key] += 1

    def works(self, name: str, proc: _Proc, fed: bool = True) -> bool:
        """Whether node ``name`` has shown it works since the counts were last reset."""
        self.executor.spin_once(timeout_sec=0.02)
        if name == "graph":
            return any(line.startswith("t=") for line in proc.lines)
        if name == "record_baseline" or not fed:  # its name (which outlives a process) and its DDS threads
            return (name, NAMESPACE) in self.node.get_node_names_and_namespaces() and _has_dds(proc.popen.pid)
        return self.seen[name] > 0

    def reset(self):
        """Take what earlier processes left queued (0.2 s), then count from zero."""
        deadline = time.monotonic() + 0.2
        while time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=0.02)
        for k in self.seen:
            self.seen[k] = 0

    def close(self):
        self.executor.shutdown()
        self.node.destroy_node()


def _py_spy_dump(pid: int) -> str:
    """Where the threads of ``pid`` are (py-spy, if installed: a diagnosis aid, not a dependency)."""
    exe = os.path.join(os.path.dirname(sys.executable), "py-spy")
    try:
        r = subprocess.run([exe, "dump", "--native", "--pid", str(pid)], capture_output=True, text=True,
                           timeout=30)
        return "--- py-spy dump of the hung process:\n" + r.stdout + r.stderr
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"--- no py-spy dump: {exc}\n"


@dataclass
class Stop:
    node: str
    sig: str
    exit_s: float  # signal -> exit, s (NaN: hung)
    returncode: int | None
    hung: bool  # not exited hang_s + grace_s after the signal (then signalled again, killed 5 s later)
    slow: bool = False  # exited, but later than hang_s
    output: str = ""


@dataclass
class StopCycles:
    """Busy loops, a model, a probe and the upstream processes of the node being stopped."""

    context: object
    domain_id: int
    busy: int | None = None
    seed: int = 0
    hang_s: float = 2.0
    ready_timeout_s: float = 60.0
    dump: bool = False
    grace_s: float = 5.0
    model_path: str | None = None  # an FDI model (default: a small one trained here)
    stops: list = field(default_factory=list)

    def __enter__(self):
        from inkdiag_core.fdi import train_default_model

        self._tmp = tempfile.TemporaryDirectory(prefix="stop_cycles_")
        if self.model_path is None:
            self.model_path = os.path.join(self._tmp.name, "fdi_small.joblib")
            train_default_model(self.model_path, n_per_class=80, features="kpi_y", seed=0)
        self.env = dict(os.environ, ROS_DOMAIN_ID=str(self.domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
        self.probe = Probe(self.context)
        self._rng = random.Random(self.seed)
        n_busy = (os.cpu_count() or 1) if self.busy is None else self.busy
        self._busy = [subprocess.Popen([sys.executable, "-c", _BUSY_LOOP, str(os.getpid())]) for _ in range(n_busy)]
        return self

    def __exit__(self, *exc):
        for b in self._busy:
            b.kill()
            b.wait()
        self.probe.close()
        self._tmp.cleanup()

    def _start(self, name) -> _Proc:
        self.probe.reset()
        return _Proc(node_command(name, self.model_path, self._tmp.name), self.env)

    def _wait_works(self, name, proc, fed=True):
        deadline = time.monotonic() + self.ready_timeout_s
        while not self.probe.works(name, proc, fed):
            if proc.popen.poll() is not None or time.monotonic() > deadline:
                proc.stop()
                raise RuntimeError(f"{name} did not start working (exit {proc.popen.returncode}):\n"
                                   + proc.output()[-3000:])

    def run(self, name: str, cycles: int, signals=(signal.SIGINT, signal.SIGTERM), fed: bool = True) -> list[Stop]:
        """``cycles`` start-work-signal-exit cycles of node ``name``, the signals taken in turn.

        ``fed=False``: without its upstream nodes (nothing arrives to wake it; it works once
        its name is in the ROS graph).
        """
        upstream = []
        try:
            for up in UPSTREAM[name] if fed else ():
                upstream.append(self._start(up))
                self._wait_works(up, upstream[-1])
            out = []
            for i in range(cycles):
                sig = signals[i % len(signals)]
                proc = self._start(name)
                self._wait_works(name, proc, fed)
                time.sleep(self._rng.uniform(0.0, 0.5))
                dumped = False
                proc.popen.send_signal(sig)
                t0 = time.monotonic()
                while proc.popen.poll() is None and time.monotonic() - t0 < self.hang_s + self.grace_s:
                    time.sleep(0.002)
                    if self.dump and proc.popen.poll() is None and not dumped and time.monotonic() - t0 > self.hang_s:
                        dumped = True
                        proc.lines.append(_py_spy_dump(proc.popen.pid))
                hung = proc.popen.poll() is None  # still running: it ignored the signal
                exit_s = time.monotonic() - t0 if not hung else float("nan")
                if hung:
                    proc.popen.send_signal(sig)
                    try:
                        proc.popen.wait(5.0)
                    except subprocess.TimeoutExpired:
                        proc.popen.kill()
                        proc.popen.wait()
                out.append(Stop(name if fed or not UPSTREAM[name] else f"{name}-unfed", signal.Signals(sig).name, exit_s, proc.popen.returncode, hung,
                                exit_s > self.hang_s, proc.output()))
            self.stops += out
            return out
        finally:
            for up in reversed(upstream):
                up.stop()


def bad_exit(s: Stop) -> bool:
    """An exit status the node does not document for a stop (record_baseline: 1 = stopped before
    any nozzle's baseline was complete, nothing written)."""
    ok = (0, 1) if s.node.split("-")[0] == "record_baseline" else (0,)
    return s.returncode not in ok


def summary(stops: list[Stop]) -> str:
    """One line per node and signal: stops, hangs, slow stops, bad exits, exit-time percentiles."""
    lines = [f"{'node':16s} {'signal':7s} {'stops':>5s} {'hangs':>5s} {'slow':>5s} {'bad rc':>6s} "
             f"{'p50 ms':>7s} {'p90 ms':>7s} {'max ms':>7s}"]
    keys = sorted({(s.node, s.sig) for s in stops}, key=lambda k: (NODES.index(k[0].split("-")[0]), k[0], k[1]))
    for node, sig in keys:
        sel = [s for s in stops if (s.node, s.sig) == (node, sig)]
        t = np.array([s.exit_s for s in sel if not s.hung]) * 1e3
        p50, p90, pmax = (np.percentile(t, 50), np.percentile(t, 90), t.max()) if t.size else (np.nan,) * 3
        lines.append(f"{node:16s} {sig:7s} {len(sel):5d} {sum(s.hung for s in sel):5d} {sum(s.slow for s in sel):5d} "
                     f"{sum(bad_exit(s) for s in sel):6d} {p50:7.0f} {p90:7.0f} {pmax:7.0f}")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cycles", type=int, default=20, help="stop cycles per node (signals alternate)")
    ap.add_argument("--nodes", nargs="+", choices=NODES, default=list(NODES))
    ap.add_argument("--hang-s", type=float, default=2.0, help="a stop slower than this is slow, s (5 s more: a hang)")
    ap.add_argument("--busy", type=int, default=None, help="busy-loop processes (default: one per core)")
    ap.add_argument("--unfed", action="store_true",
                    help="also stop each node that has inputs without its upstream nodes (nothing wakes it)")
    ap.add_argument("--dump", action="store_true", help="py-spy dump a hung process (py-spy installed)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the random delays before each signal")
    ns = ap.parse_args(argv)

    import rclpy
    from rclpy.context import Context

    domain_id = int(os.environ.get("ROS_DOMAIN_ID", "0"))
    ctx = Context()
    rclpy.init(context=ctx, domain_id=domain_id)
    t0 = time.monotonic()
    try:
        with StopCycles(ctx, domain_id, busy=ns.busy, seed=ns.seed, hang_s=ns.hang_s, dump=ns.dump) as sc:
            print(f"stop_cycles: {ns.cycles} cycles per node, {len(sc._busy)} busy-loop processes, "
                  f"ROS_DOMAIN_ID={domain_id}, slow = exit later than {ns.hang_s:g} s after the signal, hang = no exit after {ns.hang_s + 5:g} s", flush=True)
            for name in ns.nodes:
                stops = sc.run(name, ns.cycles)
                if ns.unfed and UPSTREAM[name]:
                    stops += sc.run(name, ns.cycles, fed=False)
                for s in stops:
                    if s.hung or s.slow or bad_exit(s):
                        print(f"--- {name} {s.sig}: {'hung' if s.hung else f'{s.exit_s:.2f} s'} exit {s.returncode}\n"
                              + s.output[-6000:], flush=True)
                print(f"{name}: {len(stops)} stops, {sum(s.hung for s in stops)} hangs", flush=True)
            print(summary(sc.stops))
    finally:
        rclpy.try_shutdown(context=ctx)
    print(f"({time.monotonic() - t0:.0f} s)")
    return 1 if any(s.hung or s.slow or bad_exit(s) for s in sc.stops) else 0


if __name__ == "__main__":
    sys.exit(main())
