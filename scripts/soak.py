"""Soak the node graph: printhead_sim, fdi and fe as separate processes, for minutes.

    scripts/soak [--duration 600] [--nozzles 1024] [--rate 10] [--fault-fraction 0.05]
                 [--drying 40 600] [--model models/fdi_default.joblib] [--out reports/soak.md]

Starts the three node processes in a namespace of their own (the processes a
printer runs, with their own settings: BLAS threads, allocator), watches
them from this process (an rclpy subscriber of ``/diagnostics``, ``labels``,
``fm_estimates`` and ``ground_truth``), samples each process's resident
memory (``VmRSS``) and CPU time (``/proc/<pid>/stat``) every few seconds,
then stops them with SIGINT and prints:

- RSS per node at the end of the first third and at the end, and the growth;
- CPU per node in cores (CPU seconds / wall seconds after the warm-up);
- fdi's counters (received, labelled, malformed, failed, dropped) against the
  frames the simulator published, labels and estimates received;
- each process's exit status and the seconds it took to exit.

Exit status 1 when a target is missed (RSS growth >= 5 %, a dropped or
failed frame, fe >= 0.1 core at the nominal frame rate, a non-zero exit or a stop
slower than 2 s). fe's CPU is scaled to ``--rate`` by the rate the simulator kept
(frames published / duration): on a busy machine it publishes fewer frames, and
fe's CPU falls with them.
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _rss_kb(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    return 0


def _cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime + stime


class Watcher:
    """Counts what the graph publishes, from a node of this process."""

    def __init__(self, namespace: str):
        import rclpy
        from rclpy.executors import SingleThreadedExecutor

        import msg_defs
        from msg_defs import topics

        self._rclpy = rclpy
        rclpy.init()
        self.node = rclpy.create_node("soak_watcher", namespace=namespace)
        self.truth = self.labels = self.estimates = 0
        self.diag = {}
        n = self.node
        n.create_subscription(msg_defs.TRUTH_MSG_TYPE, topics.GROUND_TRUTH, self._on_truth, msg_defs.RELIABLE_QOS)
        n.create_subscription(msg_defs.LABELS_MSG_TYPE, topics.LABELS, self._on_labels, msg_defs.RELIABLE_QOS)
        n.create_subscription(msg_defs.ESTIMATES_MSG_TYPE, topics.FM_ESTIMATES, self._on_estimates,
                              msg_defs.RELIABLE_QOS)
        n.create_subscription(msg_defs.DIAGNOSTICS_MSG_TYPE, topics.DIAGNOSTICS, self._on_diag,
                              msg_defs.DIAGNOSTICS_QOS)
        self._values = msg_defs.diagnostics_values
        self._decode_truth = msg_defs.decode_truth
        self._exec = SingleThreadedExecutor()
        self._exec.add_node(n)
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _spin(self):
        try:
            self._exec.spin()
        except Exception:  # noqa: BLE001 - shutdown
            pass

    def _on_truth(self, msg):
        self.truth = max(self.truth, self._decode_truth(msg).frame_id + 1)  # frames published so far

    def _on_labels(self, msg):
        self.labels += 1

    def _on_estimates(self, msg):
        self.estimates += 1

    def _on_diag(self, msg):
        for name, values in self._values(msg).items():
            if name == f"inkdiag fdi: {self.node.get_namespace()}":  # not fe's status of the same head
                self.diag = values

    def close(self):
        self._rclpy.try_shutdown()  # wakes the spinning thread
        self._thread.join(5.0)
        self._exec.shutdown()
        self.node.destroy_node()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=600.0, help="seconds of soak (default 600)")
    ap.add_argument("--nozzles", type=int, default=1024)
    ap.add_argument("--rate", type=float, default=10.0, help="frames per second")
    ap.add_argument("--fault-fraction", type=float, default=0.05)
    ap.add_argument("--drying", type=int, nargs="+", default=[40, 600], help="drying nozzle ids")
    ap.add_argument("--model", default="models/fdi_default.joblib")
    ap.add_argument("--sample-every", type=float, default=5.0, help="seconds between RSS/CPU samples")
    ap.add_argument("--namespace", default="/soak")
    args = ap.parse_args(argv)

    subprocess.run([sys.executable, "-m", "inkdiag_ros.model_cache"], check=True, cwd=ROOT)
    ns = ["--ros-args", "-r", f"__ns:={args.namespace}"]
    drying = "[" + ",".join(str(i) for i in args.drying) + "]"
    cmds = {
        "printhead_sim": ["printhead_sim", *ns, "-p", f"n_nozzles:={args.nozzles}",
                          "-p", f"frame_rate_hz:={args.rate}", "-p", f"random_fault_fraction:={args.fault_fraction}",
                          "-p", f"drying_nozzles:={drying}", "-p", "drying_duration_s:=60.0"],
        "fdi": ["fdi", *ns, "-p", f"model_path:={args.model}", "-p", f"n_nozzles:={args.nozzles}"],
        "fe": ["fe", *ns],
    }
    watcher = Watcher(args.namespace)
    procs = {}
    for name in ("fdi", "fe", "printhead_sim"):  # the subscribers first
        procs[name] = subprocess.Popen(cmds[name], cwd=ROOT, stdout=subprocess.DEVNULL,
                                       stderr=open(f"/tmp/soak_{name}.log", "w"))
        time.sleep(1.0)
    t0 = time.monotonic()
    samples = []  # (t, {name: (rss_kb, cpu_s)})
    try:
        while (t := time.monotonic() - t0) < args.duration:
            bad = {n: p.returncode for n, p in procs.items() if p.poll() is not None}
            if bad:
                print(f"soak: a node exited early: {bad} (logs /tmp/soak_*.log)", file=sys.stderr)
                return 1
            samples.append((t, {n: (_rss_kb(p.pid), _cpu_s(p.pid)) for n, p in procs.items()}))
            time.sleep(min(args.sample_every, max(args.duration - t, 0.01)))
        samples.append((time.monotonic() - t0, {n: (_rss_kb(p.pid), _cpu_s(p.pid)) for n, p in procs.items()}))
        diag = dict(watcher.diag)
        truth, labels, estimates = watcher.truth, watcher.labels, watcher.estimates
    finally:
        stops = {}
        for name in ("printhead_sim", "fdi", "fe"):
            p = procs.get(name)
            if p is None:
                continue
            ts = time.monotonic()
            p.send_signal(signal.SIGINT)
            try:
                p.wait(10.0)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
            stops[name] = (p.returncode, time.monotonic() - ts)
        watcher.close()

    third = min(samples, key=lambda s: abs(s[0] - args.duration / 3))
    warm = min(samples, key=lambda s: abs(s[0] - min(30.0, args.duration / 10)))
    end = samples[-1]
    ok = True
    truth_rate = truth / max(end[0], 1e-9)  # frames/s the simulator published
    kept = truth_rate if truth_rate > 0 else args.rate
    fe_cores = float("nan")
    print(f"soak: {args.duration:g} s, {args.nozzles} nozzles at {args.rate:g} Hz, "
          f"{args.fault_fraction:.0%} random faults, drying {args.drying}")
    print(f"{'node':14s} {'RSS @T/3 (MB)':>14s} {'RSS end (MB)':>13s} {'growth':>7s} {'CPU (cores)':>12s} "
          f"{'exit':>5s} {'stop (s)':>9s}")
    for name in procs:
        r3, rend = third[1][name][0] / 1024, end[1][name][0] / 1024
        cores = (end[1][name][1] - warm[1][name][1]) / max(end[0] - warm[0], 1e-9)
        code, stop_s = stops.get(name, (None, float("nan")))
        growth = (rend - r3) / r3
        print(f"{name:14s} {r3:14.1f} {rend:13.1f} {growth:+7.1%} {cores:12.3f} {code!s:>5s} {stop_s:9.2f}")
        ok &= growth < 0.05 and code == 0 and stop_s < 2.0
        if name == "fe":
            fe_cores = cores
            ok &= cores * args.rate / kept < 0.1
    print(f"frames published per second {truth_rate:.2f} (nominal {args.rate:g}); fe at the nominal rate "
          f"{fe_cores * args.rate / kept:.3f} cores ({1e3 * fe_cores / kept:.1f} ms CPU per frame)")
    keys = ("frames_received", "frames_labelled", "frames_malformed", "frames_failed", "frames_dropped")
    print("fdi /diagnostics: " + ", ".join(f"{k} {diag.get(k, '?')}" for k in keys))
    print(f"frames published (last ground_truth frame id + 1) {truth}, labels received {labels}, "
          f"fm_estimates received {estimates}")
    ok &= str(diag.get("frames_failed")) == "0" and str(diag.get("frames_dropped")) == "0"
    print("soak: all targets met" if ok else "soak: a target was missed")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
