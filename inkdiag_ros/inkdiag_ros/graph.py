"""graph: the simulated printhead, fdi and fe in one process on one executor, with a live summary.

    graph [--duration 20] [--model models/fdi_default.joblib] [--namespace /head_00]
          [--train-if-missing] [--baseline [--baseline-path baselines/head_00.npz]] [--record BAG_DIR]
          [--ros-args -p printhead_sim:n_nozzles:=128 --params-file my.yaml]

Parameters come from the packaged ``config/inkdiag.yaml``, then any
``--ros-args`` given (``-p name:=value`` applies to every node that declares
it; ``--params-file`` with ``/**/fdi:`` style keys targets one node). Prints
once a second what the operator topics say, and at the end (after
``--duration`` s, Ctrl-C or SIGTERM) a scorecard against the ground truth.

With ``--baseline`` the run starts as a printer after a purge: the simulated head
is healthy for its first ``--commissioning`` seconds (``faults_start_s``) while
``record_baseline`` records every nozzle's healthy baseline; then fdi starts with
those baselines (classified by the model's baseline branch: ``--model`` must be a
detector trained with one, as the default is), and fe with the nozzles'
healthy f_m readings from the same file.
"""

from __future__ import annotations

import argparse
import importlib.resources
import math
import sys
import time
from pathlib import Path

import rclpy
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.utilities import remove_ros_args

from msg_defs import (
    DIAGNOSTICS_MSG_TYPE,
    DIAGNOSTICS_QOS,
    DRIED_CLASSES,
    ESTIMATES_MSG_TYPE,
    LABELS_MSG_TYPE,
    RELIABLE_QOS,
    TRUTH_MSG_TYPE,
    UNKNOWN_CLASS,
    decode_estimates,
    decode_labels,
    decode_truth,
    diagnostics_values,
    topics,
)

from ._fatal import FatalNodeError
from ._spin import close_outputs, exit_now, quiet_signal_handling, ros_args_error, shutting_down, sigint_as_shutdown
from .allocator import PeriodicRelease, keep_freed_memory
from .blas import limit_blas_threads
from .bags import HEAD_TOPICS, InProcessRecording, check_new_bag
from . import _params, baseline_node, fdi_node, fe_node, printhead_sim
from .baseline_node import BaselineRecorderNode
from .fdi_node import FdiNode
from .fe_node import FeNode
from .printhead_sim import PrintheadSim
from inkdiag_core.scorecard import Scorecard


#: What ``--record`` records: the head's topics and the simulation's ground truth.
RECORDED_TOPICS = (*HEAD_TOPICS, topics.GROUND_TRUTH)


def default_params_file() -> str:
    """Path of the packaged ``config/inkdiag.yaml``."""
    return str(importlib.resources.files("inkdiag_ros") / "config" / "inkdiag.yaml")


class OperatorMonitor(Node):
    """Listens to what an operator would ``ros2 topic echo``; keeps the latest of each."""

    def __init__(self, **kwargs):
        super().__init__("operator_monitor", **kwargs)
        self.score = Scorecard()
        self.last_labels = None
        self.last_estimates = None
        self.last_diag = {}
        self.n_labels = self.n_truth = 0
        self._subs = [
            self.create_subscription(LABELS_MSG_TYPE, topics.LABELS, self._on_labels, RELIABLE_QOS),
            self.create_subscription(TRUTH_MSG_TYPE, topics.GROUND_TRUTH, self._on_truth, RELIABLE_QOS),
            self.create_subscription(ESTIMATES_MSG_TYPE, topics.FM_ESTIMATES, self._on_est, RELIABLE_QOS),
            self.create_subscription(DIAGNOSTICS_MSG_TYPE, topics.DIAGNOSTICS, self._on_diag,
                                     DIAGNOSTICS_QOS),
        ]

    def _on_labels(self, msg):
        self.last_labels = decode_labels(msg)
        self.score.add_labels(self.last_labels)
        self.n_labels += 1

    def _on_truth(self, msg):
        self.score.add_truth(decode_truth(msg))
        self.n_truth += 1

    def _on_est(self, msg):
        self.last_estimates = decode_estimates(msg)
        self.score.add_estimates(self.last_estimates)

    def _on_diag(self, msg):
        self.last_diag.update(diagnostics_values(msg))

    def summary(self, t: float) -> str:
        parts = [f"t={t:5.1f}s frames {self.n_truth:4d} simulated / {self.n_labels:4d} labelled"]
        rep = self.last_labels
        if rep is not None:
            faults = [f"{nz}:{c}({p:.2f})" for nz, c, p in rep.faults if c not in DRIED_CLASSES]
            dried = [f"{nz}:{c}" for nz, c, p in rep.faults if c in DRIED_CLASSES]
            parts.append(f"faults [{', '.join(faults)}]")
            parts.append(f"drying [{', '.join(dried)}]")
            if rep.counts.get(UNKNOWN_CLASS):  # unlike every known class: listed in faults, counted here
                parts.append(f"unknown {rep.counts[UNKNOWN_CLASS]}")
            if rep.counts.get("invalid"):
                parts.append(f"invalid {rep.counts['invalid']}")
        est = self.last_estimates
        if est is not None and est.table.shape[0]:
            r = dict(zip(("nozzle", "fm", "fm_std", "d_mu", "viscosity", "fm_trend", "fm_rate",
                          "eta_deeply_dried_s"), est.table[0]))
            eta = r["eta_deeply_dried_s"]
            eta_s = "deep" if eta == 0 else ("-" if eta != eta else f"{eta:.0f}s")
            parts.append(f"f_m[{int(r['nozzle'])}] {r['fm']:.3g}/s trend {r['fm_trend']:.3g} "
                         f"mu {1e3 * r['viscosity']:.1f} mPa.s ETA deep {eta_s}")
        for name, d in self.last_diag.items():
            if not name.startswith("inkdiag fdi:"):  # fe's status: its own counters, not a labelling rate
                continue
            base = d.get("rows_with_baseline", "0")
            parts.append(f"diag {d['level'].upper()} {d.get('traces_per_s', '?')} traces/s"
                         + (f", {base} rows vs their baseline" if base not in ("", "0") else ""))
        return " | ".join(parts)


def run(duration_s: float, *, namespace: str, model_path: str | None, args=None, out=print,
        context=None, baseline: dict | None = None, record=None) -> Scorecard:
    """Run the graph for ``duration_s`` (0: until shutdown) and return the scorecard.

    ``baseline``: ``{"path": .npz to write, "commissioning_s": healthy time,
    "n_frames": frames per nozzle}`` records the
    head's baselines first (see the module docstring). ``record``: a new bag directory
    that gets every message of :data:`RECORDED_TOPICS` (:class:`inkdiag_ros.bags.InProcessRecording`),
    closed valid at the end whatever stops the run.
    """
    own = context is None
    shipped = shipped_scenario(args)
    if own:
        with sigint_as_shutdown():
            rclpy.init(args=args)
            return _run(duration_s, namespace=namespace, model_path=model_path, out=out, context=None,
                        baseline=baseline, own=True, record=record, shipped=shipped)
    return _run(duration_s, namespace=namespace, model_path=model_path, out=out, context=context,
                baseline=baseline, own=False, record=record, shipped=shipped)


SCENARIO_LISTS = ("fault_nozzles", "fault_classes", "drying_nozzles")
"""printhead_sim's lists of fixed faults: the packaged config's are defaults (left out where not on the head)."""


def shipped_scenario(args) -> tuple:
    """The :data:`SCENARIO_LISTS` whose values come from the packaged ``config/inkdiag.yaml`` alone (``args``: the
    ROS arguments after it name none of them, neither as ``-p`` nor in a ``--params-file``): printhead_sim takes
    them as its own defaults, so that a smaller head (``-p n_nozzles:=32``) runs with those on it instead of
    refusing a list its user never gave."""
    args = list(args or [])
    if default_params_file() not in args:
        return ()
    user = args[args.index(default_params_file()) + 1:]
    text = " ".join(user)
    for i, a in enumerate(user[:-1]):
        if a == "--params-file":
            try:
                text += Path(user[i + 1]).read_text()
            except (OSError, UnicodeDecodeError):  # rclpy says what is wrong with it
                return ()
    return () if any(k in text for k in SCENARIO_LISTS) else SCENARIO_LISTS  # one named: the user's scenario


class BadParameters(ValueError):
    """A node of the graph refused its parameters (the message says which and why)."""


def _make(node_cls, **kwargs):
    try:
        return node_cls(**kwargs)
    except (ValueError, ParameterException) as exc:
        raise BadParameters(f"{node_cls.__name__}: {exc}") from exc


def _run(duration_s, **kwargs) -> Scorecard:
    """:func:`run` on an initialised context (``own``: shut it down at the end)."""
    # a -p NAME:=VALUE reaches every node: only those that have NAME take it, the others say nothing of it
    built = (printhead_sim, fdi_node, fe_node) + ((baseline_node,) if kwargs.get("baseline") else ())
    with _params.shared_by(*(m.PARAMS for m in built)):  # a name only a node not built has: each warns
        return _run_graph(duration_s, **kwargs)


def _run_graph(duration_s, *, namespace, model_path, out, context, baseline, own, record=None, shipped=()
               ) -> Scorecard:
    kw = {"namespace": namespace}
    if context is not None:
        kw["context"] = context
    nodes = []
    monitor = bag = None
    executor = SingleThreadedExecutor(**({"context": context} if context is not None else {}))
    try:
        if record:  # subscribed before the head publishes its first frame
            nodes.append(Node("inkdiag_record", **kw))
            bag = InProcessRecording(nodes[0], record, RECORDED_TOPICS)
            executor.add_node(nodes[0])
            out(f"recording {', '.join(bag.recorder.wanted)} into {bag.bag}")
        fdi_over = [Parameter("model_path", value=str(model_path))] if model_path else []
        if baseline:
            sim = _make(PrintheadSim, parameter_overrides=[
                Parameter("faults_start_s", value=float(baseline["commissioning_s"]))], shipped=shipped, **kw)
            recorder = _make(BaselineRecorderNode, parameter_overrides=[
                Parameter("output_path", value=str(baseline["path"])),
                Parameter("n_frames", value=int(baseline.get("n_frames", 8))),
                Parameter("n_nozzles", value=sim.config["n_nozzles"]),
                Parameter("first_nozzle", value=sim.config["first_nozzle"]),
                Parameter("timeout_s", value=float(baseline["commissioning_s"]))], **kw)
            head = [sim, recorder]
        else:
            head = [_make(PrintheadSim, shipped=shipped, **kw)]
        for n in head:
            executor.add_node(n)
        nodes += head
        first = len(nodes) - len(head)  # the head's nodes: nodes[first] the sim, nodes[first + 1] the recorder

        def start_labelling():
            extra, fe_over = [], []
            if baseline and nodes[first + 1].written:
                extra = [Parameter("baseline_path", value=str(nodes[first + 1].written))]
                fe_over = [Parameter("baseline_path", value=str(nodes[first + 1].written))]
            for make in (lambda: _make(FdiNode, parameter_overrides=fdi_over + extra, **kw),
                         lambda: _make(FeNode, parameter_overrides=fe_over, **kw), lambda: OperatorMonitor(**kw)):
                nodes.append(make())  # at once: if a later one fails, the finally destroys this one
                executor.add_node(nodes[-1])
            return nodes[-1]

        if not baseline:
            monitor = start_labelling()
        t0 = time.monotonic()
        next_print = t0 + 1.0
        ctx = executor.context
        release = PeriodicRelease()  # as spin_node: a drained backlog's free heap goes back
        while ctx.ok() and (duration_s <= 0 or time.monotonic() - t0 < duration_s):
            release()
            try:
                executor.spin_once(timeout_sec=0.05)
            except FatalNodeError:  # a recording's full disk: said even when a signal came at the same time
                raise
            except Exception:
                if not shutting_down(ctx):
                    raise
                break  # SIGINT/SIGTERM shut the context down while a callback ran
            if monitor is None and nodes[first + 1].done:
                rec = nodes[first + 1]
                out(f"t={time.monotonic() - t0:5.1f}s "
                    + (f"baselines of {rec.recorder.n_complete} nozzles recorded ({rec.frames} frames) "
                       f"-> {rec.written}; starting fdi and fe" if rec.written else
                       f"no baselines recorded ({rec.frames} frames, {rec.recorder.n_frames} needed per "
                       "nozzle); starting fdi and fe without them"))
                monitor = start_labelling()
            if time.monotonic() >= next_print:
                out(monitor.summary(time.monotonic() - t0) if monitor is not None else
                    f"t={time.monotonic() - t0:5.1f}s commissioning: head healthy, recording baselines "
                    f"({nodes[first + 1].recorder.n_complete} nozzles complete)")
                next_print += 1.0
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except FatalNodeError:
        raise
    except Exception:  # a signal shut the context down as a node was built (RCLError, NotInitializedException)
        if not shutting_down(executor.context):
            raise
    finally:
        if own:  # before anything is destroyed (_spin.quiet_signal_handling)
            quiet_signal_handling()
        executor.shutdown()
        try:
            close_outputs(nodes)  # fdi's last labels out before the bag closes
        finally:  # each step whatever the one before raised (a full disk at the bag's close): the error after them
            try:
                if bag is not None:  # a valid bag before any node goes
                    try:
                        bag.close()
                    finally:
                        out(bag.summary())
            finally:
                for n in nodes:
                    n.destroy_node()
                if own:
                    rclpy.try_shutdown()
    return monitor.score if monitor is not None else Scorecard()


def _commissioning_s(text: str) -> float:
    value = float(text)
    if not 0.1 <= value <= 86400.0:
        raise argparse.ArgumentTypeError(f"must be between 0.1 and 86400 s, got {text}")
    return value


def main(args=None) -> int:
    argv = list(sys.argv if args is None else args)
    parser = argparse.ArgumentParser(prog="graph", description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=20.0, help="seconds to run (0: until Ctrl-C)")
    parser.add_argument("--namespace", default="/head_00", help="the printhead's namespace")
    parser.add_argument("--model", default=None, help="FDI model file (default: the params file's)")
    parser.add_argument("--train-if-missing", action="store_true",
                        help="train and cache the default model first if the file is missing or stale")
    parser.add_argument("--baseline", action=argparse.BooleanOptionalAction, default=False,
                        help="record every nozzle's healthy baseline first and label against it")
    parser.add_argument("--baseline-path", default=None,
                        help="where --baseline writes the baselines (default baselines/<namespace>.npz)")
    parser.add_argument("--commissioning", type=_commissioning_s, default=3.0,
                        help="seconds the head is healthy at the start with --baseline (0.1 .. 86400)")
    parser.add_argument("--record", default=None, metavar="BAG_DIR",
                        help="write a rosbag2 bag (MCAP) of the head's topics: traces, labels, drying_nozzles, "
                        "fm_estimates, fm_estimates/array, /diagnostics, ground_truth (a new directory)")
    if why := ros_args_error(argv):
        parser.error(why)
    ns = parser.parse_args(remove_ros_args(argv)[1:])
    if not (math.isfinite(ns.duration) and ns.duration >= 0):
        parser.error(f"--duration must be a number of seconds >= 0 (0: until Ctrl-C), got {ns.duration:g}")
    if ns.record:
        try:
            check_new_bag(ns.record)
        except ValueError as exc:
            parser.error(f"--record: {exc}")
    keep_freed_memory()
    limit_blas_threads()
    # the packaged params first, the user's --ros-args after it (later wins)
    ros_args = ["--ros-args", "--params-file", default_params_file()]
    if "--ros-args" in argv:
        i = argv.index("--ros-args")
        ros_args += argv[i + 1:]
        argv = argv[:i]
    if ns.train_if_missing:
        from inkdiag_core.model_cache import DEFAULT_MODEL, ensure_default_model

        try:
            ns.model = str(ensure_default_model(ns.model or DEFAULT_MODEL))
        except KeyboardInterrupt:  # Ctrl-C in the first run's training (seconds): one line, no traceback
            print("graph: interrupted while checking or training the default model (a model is written only whole)",
                  file=sys.stderr)
            return 130
    baseline = None
    if ns.baseline:
        path = ns.baseline_path or f"baselines/{ns.namespace.strip('/').replace('/', '_') or 'head'}.npz"
        baseline = {"path": path, "commissioning_s": ns.commissioning}
    print(f"inkdiag graph: printhead_sim -> fdi -> fe in {ns.namespace}, "
          f"{'until Ctrl-C' if ns.duration <= 0 else f'{ns.duration:g} s'} (Ctrl-C stops early)"
          + (f"; per-nozzle baselines recorded in the first {ns.commissioning:g} s" if baseline else "")
          + (f"; recording its topics into {ns.record}" if ns.record else ""), flush=True)
    try:
        score = run(ns.duration, namespace=ns.namespace, model_path=ns.model, args=argv[:1] + ros_args,
                    baseline=baseline, record=ns.record)
    except (BadParameters, FatalNodeError) as exc:  # FatalNodeError: --record's disk is full (the bag closed first)
        print(f"graph: {exc}", file=sys.stderr)
        return 2
    print(score.format())
    return 0


if __name__ == "__main__":
    exit_now(main())  # the nodes down: not the interpreter's teardown too
