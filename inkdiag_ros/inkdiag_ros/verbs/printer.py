"""``inkdiag printer``: the fdi nodes of N heads in P processes on one DDS domain (a whole printer)."""

from __future__ import annotations

import argparse
import os
import re
import signal
import subprocess
import sys
import time

HELP = "run the fdi nodes of N printheads in P processes (a whole printer), with a live summary"
DESCRIPTION = """\
Run one fdi node per head, namespaces /head_00 .. /head_{N-1} (from /head_K with
--first-head K, so that several boxes share a printer's heads; the topics a single
head uses: /head_07/traces in, /head_07/labels and /head_07/drying_nozzles out,
/diagnostics), in P OS processes on the DDS domain of ROS_DOMAIN_ID. Heads are
assigned to the processes round-robin (head i in process i mod P); each process
spins its nodes on one rclpy executor (--executor: the EventsExecutor by default), one
BLAS thread, the allocator set as in every inkdiag node. No fe node runs: the printer
labels; run fe per head where f_m estimates are wanted. Parameters come from the
packaged config/inkdiag.yaml, then --ros-args (given to every node of every
process), then --model and --baselines.

With --simulate a simulated printhead per head (printhead_sim, seed = head index)
runs too, all of them in one more process, so the command demos on its own.

Prints once a second: heads whose /diagnostics arrived in the last 2.5 s, and the
frames and traces labelled per second summed over the heads (from their
/diagnostics). Ctrl-C or SIGTERM stops every process (exit status 0); a process
that dies is reported with its exit status and the command exits 1; bad options
are one line on stderr and exit status 2, as are parameters the node processes refuse
(each process says why, exit status 2 for the command), and heads that another
printer (or node) on the same domain already runs: until 30 s after its nodes are up, a printer
that finds one of its nodes (/head_03/fdi) twice in the ROS graph stops (exit status 2), unless
another printer over that head started after it: that one stops, this one runs on (the ROS graph
names each printer's heads and start time in its monitor node's name; docs/scaling.md).

Example: inkdiag printer --heads 4 --processes 2 --baselines baselines/head_{i:02d}.npz
"""

#: Seconds without a /diagnostics message after which a head is not counted as up.
STALE_S = 2.5
#: Seconds the processes get to stop on SIGTERM before they are killed.
STOP_GRACE_S = 1.5
#: Seconds, from when all of a printer's nodes are up in the ROS graph, during which a second node of the same name in
#: one of its namespaces (another printer's, or a lone node's, on the same heads and domain) stops it
#: (:class:`ConflictWatch`); later it keeps running.
CONFLICT_WINDOW_S = 30.0
#: At most this long after its start a printer watches the graph, its own nodes up or not (:class:`ConflictWatch`).
WATCH_MAX_S = 120.0
#: Seconds a node of its heads runs twice, no printer started later covering that head, before a printer stops.
DUPLICATE_GRACE_S = 3.0
#: Seconds a printer that started later, over that head, gets to stop before this one stops too.
LATER_GRACE_S = 15.0


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--heads", type=int, required=True, help="printheads N (namespaces /head_00 .. /head_{N-1})")
    p.add_argument("--first-head", type=int, default=0,
                   help="index of the first head K: the heads are /head_K .. /head_{K+N-1} (a printer over several "
                        "boxes: each runs its range), default 0")
    p.add_argument("--processes", type=int, default=1, help="OS processes P running the fdi nodes (1 .. N)")
    p.add_argument("--model", default=None,
                   help="FaultDetector model file for every head (default: models/fdi_default.joblib in the "
                        "current directory, as scripts/run trains it in the repository's root)")
    p.add_argument("--baselines", default=None, metavar="DIR_OR_PATTERN",
                   help="per-head baselines: a pattern with {i} (the head index), e.g. "
                        "baselines/head_{i:02d}.npz, or a directory holding head_00.npz ...; every file must exist")
    p.add_argument("--simulate", action="store_true", help="also run a simulated printhead per head")
    p.add_argument("--duration", type=float, default=0.0, help="seconds to run, 0: until Ctrl-C (default)")
    p.add_argument("--executor", choices=("events", "single"), default="events",
                   help="the executor of each fdi process: rclpy's C++ EventsExecutor (default) or the Python "
                        "SingleThreadedExecutor (the simulators always use the latter)")
    p.add_argument("--ros-args", dest="ros_args", nargs=argparse.REMAINDER, default=[],
                   help="ROS arguments for every node (e.g. -p n_nozzles:=2656), the rest of the line")


def baseline_paths(spec: str | None, heads) -> list:
    """The baselines file of each head index of ``heads`` from ``--baselines`` (None: none), checked to exist.

    Raises
    ------
    ValueError
        A bad pattern or a missing file (the first one).
    """
    if not spec:
        return [None] * len(heads)
    if os.path.isdir(spec):
        spec = os.path.join(spec, "head_{i:02d}.npz")
    elif "{" not in spec:
        raise ValueError(f"--baselines {spec!r} is neither a directory nor a pattern with {{i}} "
                         "(e.g. baselines/head_{i:02d}.npz)")
    try:
        paths = [spec.format(i=i) for i in heads]
    except (KeyError, IndexError, ValueError) as exc:
        raise ValueError(f"--baselines {spec!r}: bad pattern ({exc}); use {{i}} for the head index") from None
    from inkdiag_core import BaselineFileError, NozzleBaselines

    for path in paths:
        if not os.path.isfile(path):
            raise ValueError(f"baselines file {path} not found (--baselines {spec!r})")
        try:  # a file its fdi node could not read would leave the head without baselines, said only on /diagnostics
            NozzleBaselines.load(path)
        except BaselineFileError as exc:
            raise ValueError(f"--baselines {spec!r}: {exc}") from None
    return paths


def _check(args) -> None:
    if not 1 <= args.heads <= 100:
        raise ValueError(f"--heads must be 1 .. 100, got {args.heads}")
    if not 0 <= args.first_head <= 99 - (args.heads - 1):
        raise ValueError(f"--first-head must be 0 .. {100 - args.heads} (head indices up to 99), got {args.first_head}")
    if not 1 <= args.processes <= args.heads:
        raise ValueError(f"--processes must be 1 .. --heads ({args.heads}), got {args.processes}")
    if not args.duration >= 0:
        raise ValueError(f"--duration must be >= 0 s, got {args.duration}")
    if not os.path.exists(args.model):
        raise ValueError(f"model file {args.model} not found (pass --model, or train one: inkdiag train)")
    from inkdiag_core.persistence import verify_model_file

    verify_model_file(args.model)  # ModelFileError (a ValueError): each fdi node would run without a model
    from .._spin import ros_args_error

    if why := ros_args_error(["inkdiag", "--ros-args", *args.ros_args]):  # before any child: each would say it
        raise ValueError(why)


def _die_with_parent() -> None:  # children get SIGTERM if the printer process dies (Linux)
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def run(args) -> int:
    from inkdiag_core.model_cache import DEFAULT_MODEL

    args.model = os.path.abspath(args.model or str(DEFAULT_MODEL))
    _check(args)
    heads = list(range(args.first_head, args.first_head + args.heads))
    paths = dict(zip(heads, baseline_paths(args.baselines, heads)))
    groups = [heads[k::args.processes] for k in range(args.processes)]
    base = [sys.executable, "-m", __name__]
    ros = ["--ros-args", *args.ros_args]
    children = []  # (description, Popen)
    started_ns = time.time_ns()  # before any child: the start other printers compare theirs with (monitor_name)
    try:
        for k, group in enumerate(groups):
            cmd = base + ["--role", "fdi", "--heads", ",".join(map(str, group)), "--model", args.model,
                          "--executor", args.executor] + (["--with-sim"] if args.simulate else [])
            for i in group:
                cmd += ["--baseline", f"{i}={paths[i]}"] if paths[i] else []
            children.append((f"fdi process {k} (heads {', '.join(f'{i:02d}' for i in group)})",
                             subprocess.Popen(cmd + ros, preexec_fn=_die_with_parent, start_new_session=True)))
        if args.simulate:
            cmd = base + ["--role", "sim", "--heads", ",".join(map(str, heads)), "--executor", "single"]
            children.append(("simulator process", subprocess.Popen(cmd + ros, preexec_fn=_die_with_parent,
                                                                   start_new_session=True)))
        print(f"inkdiag printer: {args.heads} heads' fdi nodes (/head_{heads[0]:02d} .. /head_{heads[-1]:02d}) "
              f"in {args.processes} processes (pids {', '.join(str(p.pid) for _, p in children[:len(groups)])})"
              + (", simulated printheads in one more" if args.simulate else "")
              + f"; {'until Ctrl-C' if args.duration <= 0 else f'{args.duration:g} s'}", flush=True)
        died, conflict = _monitor(args, children, started_ns)
    finally:
        _stop(children)
    if conflict:
        print(f"inkdiag printer: error: {conflict}", file=sys.stderr)
        return 2
    for what, proc in died:
        rc = proc.returncode
        how = f"was killed by signal {-rc}{_signal_name(-rc)}" if rc < 0 else f"exited with status {rc}"
        print(f"inkdiag printer: {what} {how}" + {2: " (bad input: its own line above says which)",
                                                   0: " before the printer stopped it (stopped from outside?)"}.get(
            rc, ""), file=sys.stderr)
    if died and all(proc.returncode == 2 for _, proc in died):  # e.g. --ros-args -p n_nozzles:=-1: bad input
        return 2
    return 1 if died else 0


def ended(children, *, wait_s: float = 0.0) -> list:
    """The ``(description, Popen)`` of ``children`` that have ended; with ``wait_s``, those that end within that
    many seconds too (as long as any runs)."""
    until = time.monotonic() + wait_s
    died = [(w, p) for w, p in children if p.poll() is not None]
    while len(died) < len(children) and time.monotonic() < until:
        time.sleep(0.05)
        died = [(w, p) for w, p in children if p.poll() is not None]
    return died


def _signal_name(n: int) -> str:
    """`` (SIGKILL)`` for a signal number Python names, else "" (a real-time signal: SIGRTMIN+k)."""
    try:
        return f" ({signal.Signals(n).name})"
    except ValueError:
        return ""


#: Seconds the printer waits, after one child ended on its own, for the others that end too (each is reported).
DIED_TOGETHER_S = 2.0

_MONITOR = re.compile(r"printer_monitor_h(\d+)_(\d+)_t(\d+)_p(\d+)")


def monitor_name(first_head: int, n_heads: int, started_ns: int, pid: int) -> str:
    """The ROS name of a printer's monitor node: its heads, its start (ns since the epoch) and process id, so that
    printers that find each other's nodes in the ROS graph can tell which of them started first."""
    return f"printer_monitor_h{first_head:02d}_{first_head + n_heads - 1:02d}_t{started_ns}_p{pid}"


def _monitor_fields(name: str):
    """``(first_head, last_head, (started_ns, pid))`` of a :func:`monitor_name`, or None for another name."""
    m = _MONITOR.fullmatch(name)
    return None if m is None else (int(m[1]), int(m[2]), (int(m[3]), int(m[4])))


def started_first(names_and_namespaces, mine: str) -> tuple:
    """``(earlier, later)``: the other printers' monitor names (:func:`monitor_name`) in the graph whose heads overlap
    ``mine``'s and that started before it, and after it (by start time, then process id)."""
    first, last, key = _monitor_fields(mine)
    earlier, later = [], []
    for name, _ in names_and_namespaces:
        f = _monitor_fields(name)
        if f is None or name == mine or f[1] < first or f[0] > last:
            continue
        (earlier if f[2] < key else later).append(name)
    return sorted(earlier), sorted(later)


class ConflictWatch:
    """Whether a printer must stop because another printer (or a lone node) runs some of its heads.

    Fed the ROS graph once a second (:meth:`check`). A node of this printer's heads that runs twice stops it:
    at once when another printer over some of its heads started before it (:func:`started_first`); after
    :data:`DUPLICATE_GRACE_S` of being seen when no printer explains it (a lone node, or a printer whose monitor
    is not in the graph yet); after :data:`LATER_GRACE_S` when a printer that started later covers that head
    (it stops on seeing this one; still there, its clock may be behind this one's). The watch ends
    :data:`CONFLICT_WINDOW_S` after this printer's own nodes are up (every node name more often in its
    namespaces than at the first check, before they could start), or :data:`WATCH_MAX_S` after the start.

    Parameters
    ----------
    me : str
        This printer's monitor name (:func:`monitor_name`).
    namespaces, names : set of str
        Its heads' namespaces (``/head_03``) and the node names it runs in each.
    """

    def __init__(self, me: str, namespaces, names):
        self.me, self.namespaces, self.names = me, set(namespaces), set(names)
        self._base = None  # per (namespace, name): how often it ran at the first check
        self._t0 = self._up_at = None
        self._seen: dict = {}  # duplicate -> when first seen (while it lasts)

    @property
    def open(self) -> bool:
        """Whether the graph should still be watched."""
        return self._t0 is None or (self._now - self._t0 <= WATCH_MAX_S and (
            self._up_at is None or self._now - self._up_at <= CONFLICT_WINDOW_S))

    def check(self, names_and_namespaces, now: float) -> str:
        """Why this printer must stop ("" if it may run on), from the graph at ``now`` (s, monotonic)."""
        self._now = now
        if self._t0 is None:
            self._t0 = now
        count: dict = {}
        for name, ns in names_and_namespaces:
            if name in self.names and ns in self.namespaces:
                count[ns, name] = count.get((ns, name), 0) + 1
        mine = [(ns, n) for ns in self.namespaces for n in self.names]
        if self._base is None:
            self._base = {k: count.get(k, 0) for k in mine}
        if self._up_at is None and all(count.get(k, 0) > self._base[k] for k in mine):
            self._up_at = now
        twice = sorted(f"{ns}/{n}" for (ns, n), c in count.items() if c > 1)
        self._seen = {d: self._seen.get(d, now) for d in twice}
        if not twice:
            return ""
        earlier, later = started_first(names_and_namespaces, self.me)
        covered = {h for m in later for h in range(_monitor_fields(m)[0], _monitor_fields(m)[1] + 1)}
        late = [d for d in twice if int(d.split("/")[1].split("_")[1]) in covered]
        if earlier:
            who = "another inkdiag printer started before this one"
        elif any(now - self._seen[d] >= DUPLICATE_GRACE_S for d in twice if d not in late):
            who = "another inkdiag printer (or node)"
        elif any(now - self._seen[d] >= LATER_GRACE_S for d in late):
            who = (f"an inkdiag printer that started after this one did not stop in {LATER_GRACE_S:g} s (its clock "
                   "behind this one's?) and")
        else:
            return ""
        domain = os.environ.get("ROS_DOMAIN_ID", "0")
        return (f"{', '.join(twice)} run{'s' if len(twice) == 1 else ''} twice on ROS_DOMAIN_ID {domain}: {who} has "
                "these heads; stopped this one. Give each box its own heads (--first-head) or its own ROS_DOMAIN_ID")


def _monitor(args, children, started_ns: int) -> tuple:
    """Print the summary once a second until the duration, a signal or a child's death.

    Returns ``(died, conflict)``: the dead children, and why this printer must not run ("" if it may): another
    printer or node runs some of its heads (:class:`ConflictWatch`)."""
    import rclpy
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.signals import SignalHandlerOptions

    from msg_defs import DIAGNOSTICS_MSG_TYPE, DIAGNOSTICS_QOS, diagnostics_values

    from .._spin import stop_on_signals, tear_down

    latest = {}  # head namespace -> (arrival time, values)
    wanted = {f"{i:02d}" for i in range(args.first_head, args.first_head + args.heads)}
    namespaces = {f"/head_{i}" for i in wanted}
    names = {"fdi", "printhead_sim"} if args.simulate else {"fdi"}

    def on_diag(msg):
        for name, d in diagnostics_values(msg).items():
            if name.startswith("inkdiag fdi: /head_") and name.split(": /head_", 1)[1] in wanted:
                latest[name.split(": ", 1)[1]] = (time.monotonic(), d)

    with stop_on_signals() as stop:
        if stop.requested:  # a stop whose SystemExit was swallowed as this process imported
            return [], ""
        # no rclpy signal handlers: a signal sets ``stop.requested`` and never takes the context down under the
        # node or the executor being built (RCLError, and a half-built executor's AttributeError traceback)
        rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
        node = executor = None
        try:
            node = Node(me := monitor_name(args.first_head, args.heads, started_ns, os.getpid()))
            executor = SingleThreadedExecutor(context=node.context)
            executor.add_node(node)
            stop.attach(node)
            node.create_subscription(DIAGNOSTICS_MSG_TYPE, "/diagnostics", on_diag, DIAGNOSTICS_QOS)
            t0 = time.monotonic()
            next_print, watch = t0 + 1.0, ConflictWatch(me, namespaces, names)
            while not stop.requested and node.context.ok():
                executor.spin_once(timeout_sec=0.1)
                if ended(children):  # the others may be on their way out for the same reason (a bad parameter)
                    return ended(children, wait_s=DIED_TOGETHER_S), ""
                now = time.monotonic()
                if args.duration > 0 and now - t0 >= args.duration:
                    break
                if now >= next_print:
                    if watch.open and (why := watch.check(node.get_node_names_and_namespaces(), now)):
                        return [], why
                    print(summary(latest, args.heads, now - t0, now), flush=True)
                    next_print += 1.0
        except (KeyboardInterrupt, ExternalShutdownException):
            pass
        finally:
            tear_down(executor, [node])
    return [], ""


def summary(latest: dict, n_heads: int, t: float, now: float) -> str:
    """One line: heads up, frames and traces labelled per second summed over the heads that are up."""
    fresh = [d for at, d in latest.values() if now - at <= STALE_S]
    fps = sum(float(d.get("frames_per_s", 0) or 0) for d in fresh)
    tps = sum(float(d.get("traces_per_s", 0) or 0) for d in fresh)
    bad = sum(int(d.get("frames_dropped", 0) or 0) + int(d.get("frames_failed", 0) or 0) for d in fresh)
    levels = {}
    for d in fresh:
        if d.get("level") != "ok":
            levels[d.get("level")] = levels.get(d.get("level"), 0) + 1
    starting = "" if latest else " (starting: no head's /diagnostics yet)"
    return (f"t={t:6.1f}s heads up {len(fresh)}/{n_heads}{starting} | {fps:7.1f} frames/s labelled "
            f"({tps:,.0f} traces/s) | dropped+failed {bad}" + "".join(f" | {k} {v}" for k, v in sorted(levels.items())))


def _stop(children) -> None:
    """SIGTERM every child still running; kill what is left after :data:`STOP_GRACE_S`. A second SIGINT or SIGTERM
    meanwhile does not cut this short (a child past the grace is killed all the same)."""
    old = {sig: signal.signal(sig, signal.SIG_IGN) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        for _, p in children:
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + STOP_GRACE_S
        for _, p in children:
            try:
                p.wait(timeout=max(deadline - time.monotonic(), 0.01))
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)


# --- a child process: several nodes on one executor -------------------------------------------------


def worker_main(argv=None) -> int:
    """One child: ``--role fdi|sim --heads 0,2,4 [--model M] [--baseline I=PATH ...] [--executor events|single] [--with-sim]
    [--ros-args ...]``: its heads' nodes on one executor until SIGINT/SIGTERM (exit 0); a node refusing its
    parameters: one line, exit 2."""
    import numpy  # noqa: F401 - loaded before the BLAS limit
    import rclpy
    import scipy.linalg  # noqa: F401
    from rclpy.exceptions import ParameterException
    from rclpy.executors import ExternalShutdownException
    from rclpy.parameter import Parameter
    from rclpy.utilities import remove_ros_args

    from .. import _params, fdi_node, printhead_sim
    from .._spin import TEARDOWN_DEADLINE_S, freeze_startup_objects, make_executor, stop_on_signals, tear_down
    from ..allocator import PeriodicRelease, keep_freed_memory
    from ..blas import limit_blas_threads
    from ..graph import default_params_file, shipped_scenario

    argv = list(sys.argv if argv is None else argv)
    ap = argparse.ArgumentParser(prog="inkdiag printer (child)")
    ap.add_argument("--role", choices=("fdi", "sim"), required=True)
    ap.add_argument("--heads", required=True)
    ap.add_argument("--model", default=None)
    ap.add_argument("--baseline", action="append", default=[])
    ap.add_argument("--executor", choices=("events", "single"), default="events")
    ap.add_argument("--with-sim", action="store_true", help="simulated heads run beside (their parameters are shared)")
    ns = ap.parse_args(remove_ros_args(argv)[1:])
    ros = argv[argv.index("--ros-args") + 1:] if "--ros-args" in argv else []
    heads = [int(h) for h in ns.heads.split(",")]
    baselines = dict(b.split("=", 1) for b in ns.baseline)
    keep_freed_memory()
    limit_blas_threads()
    if ns.role == "fdi":
        from ..fdi_node import FdiNode as cls
    else:
        from ..printhead_sim import PrintheadSim as cls

    args = [argv[0], "--ros-args", "--params-file", default_params_file(), *ros]
    kwargs = {"shipped": shipped_scenario(args)} if ns.role == "sim" else {}  # the packaged faults: defaults

    def overrides(i):
        if ns.role == "sim":
            return [Parameter("seed", value=i)]
        over = [Parameter("model_path", value=ns.model)] if ns.model else []
        if str(i) in baselines:
            over.append(Parameter("baseline_path", value=baselines[str(i)]))
        return over

    prog = f"inkdiag printer ({ns.role} heads {ns.heads})"
    with stop_on_signals() as stop:
        rclpy.init(args=args)
        ctx = rclpy.utilities.get_default_context()
        nodes, executor, status = [], None, 0
        try:
            # --ros-args reach every process: a name only the other role has is not this node's to warn of
            shared = (fdi_node.PARAMS, printhead_sim.PARAMS) if ns.role == "sim" or ns.with_sim else (fdi_node.PARAMS,)
            with _params.shared_by(*shared):
                for i in heads:
                    nodes.append(cls(namespace=f"/head_{i:02d}", parameter_overrides=overrides(i), **kwargs))
            # with the SingleThreadedExecutor a timer callback failing at shutdown raises here
            # (the EventsExecutor logs it as FATAL)
            executor = make_executor(nodes, ns.executor == "events", stop)
            freeze_startup_objects()
            release = PeriodicRelease()
            while not stop.requested and ctx.ok():
                executor.spin_once(timeout_sec=0.5)
                release()
        except (ValueError, ParameterException) as exc:
            if not stop.explains_an_error(ctx):
                print(f"{prog}: {exc}", file=sys.stderr)
                status = 2
        except (KeyboardInterrupt, ExternalShutdownException):
            pass
        except Exception:
            if not stop.explains_an_error(ctx):
                raise
        finally:  # a process of its own (started by run_printer): bounded like every node process
            tear_down(executor, nodes, deadline_s=TEARDOWN_DEADLINE_S,
                      deadline_status=1 if sys.exc_info()[1] is not None else status)
    return status


if __name__ == "__main__":
    sys.exit(worker_main())
