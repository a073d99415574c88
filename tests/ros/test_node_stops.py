"""Every node process stops on SIGINT and on SIGTERM, repeatedly, under CPU contention.

The cycles of scripts/stop_cycles.py (how many per signal: below): start the node as a
process (with its upstream nodes running), wait until it works, signal it, and
require exit status 0 within 2 s (record_baseline: 0 or its documented 1, stopped
before any nozzle was complete), no traceback. One busy-loop process per core runs
throughout (the fe node missed about one stop in three that way). fe and fdi, which
spin the events executor and take bursts of frames, get two cycles per signal; graph,
printhead_sim and record_baseline one (suite time). A stop's time was mostly the interpreter's
own teardown after the node's (graph's SIGTERM stops took 2.0-2.6 s in a CI run of 2026-11-28);
node processes now end at once after theirs (inkdiag_ros._spin.exit_now).
"""

import importlib
import importlib.util
import os
import signal
import sys

import pytest

TESTS = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
_spec = importlib.util.spec_from_file_location(
    "stop_cycles", os.path.join(os.path.dirname(TESTS), "scripts", "stop_cycles.py"))
stop_cycles = importlib.util.module_from_spec(_spec)
sys.modules["stop_cycles"] = stop_cycles  # dataclasses look their module up
_spec.loader.exec_module(stop_cycles)


@pytest.mark.timeout(300)
@pytest.mark.parametrize("name", stop_cycles.NODES)
def test_node_process_stops_on_every_signal_under_contention(ros, fdi_model, name):
    with stop_cycles.StopCycles(ros.context, ros.domain_id, model_path=str(fdi_model), hang_s=2.0,
                                grace_s=3.0) as sc:
        stops = sc.run(name, cycles=4 if name in ("fe", "fdi") else 2, signals=(signal.SIGINT, signal.SIGTERM))
    report = stop_cycles.summary(stops)
    for s in stops:
        assert not s.hung, f"{name} ignored {s.sig}:\n{report}\n{s.output[-3000:]}"
        ok = (0, 1) if name == "record_baseline" else (0,)  # record_baseline: 1 = stopped, nothing written
        assert s.returncode in ok and not s.slow, f"{name} {s.sig}: exit {s.returncode} after {s.exit_s:.2f} s\n" \
                                                 f"{report}\n{s.output[-3000:]}"
        assert "Traceback" not in s.output, s.output[-3000:]


def test_spin_node_exits_when_the_context_goes_down_after_the_wake_up(ros):
    """rclpy's signal thread wakes the executors, then shuts the contexts down: a node
    with no timer and no traffic must not wait for another wake-up (issue 12)."""
    import subprocess
    import time

    env = dict(os.environ, ROS_DOMAIN_ID=str(ros.domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    pr = subprocess.Popen([sys.executable, os.path.join(TESTS, "procs", "missed_wakeup.py")],
                          env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines = []
    for line in pr.stdout:
        lines.append(line)
        if "context shut down" in line:
            break
    t0 = time.monotonic()
    try:
        rest = pr.communicate(timeout=5)[0]
    except subprocess.TimeoutExpired:
        pr.kill()
        pytest.fail("the node went on waiting after its context was shut down:\n" + "".join(lines))
    assert pr.returncode == 0, "".join(lines) + rest
    assert time.monotonic() - t0 < 3.0


_BLAS_CHILD = """
import json
from rclpy.node import Node
from threadpoolctl import threadpool_info
import inkdiag_ros.fe_node  # numpy and scipy (their OpenBLAS) loaded, as in the fe process
from inkdiag_ros._spin import spin_node

seen = []

class Probe(Node):
    def __init__(self):
        super().__init__("blas_probe")
        seen.extend(i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas")

spin_node(Probe, ["blas_probe"], until=lambda node: True)
print(json.dumps(seen))
"""


def test_node_processes_run_one_blas_thread_unless_the_environment_says(ros):
    """An OpenBLAS worker per core busy-waits between the fe estimator's tiny calls (issue 12)."""
    import json
    import subprocess

    from inkdiag_ros.blas import BLAS_ENV

    env = {k: v for k, v in os.environ.items() if k not in BLAS_ENV}
    env.update(ROS_DOMAIN_ID=str(ros.domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")

    def threads(**extra):
        out = subprocess.run([sys.executable, "-c", _BLAS_CHILD], env=dict(env, **extra), capture_output=True,
                             text=True, timeout=60)
        assert out.returncode == 0, out.stdout + out.stderr
        return json.loads(out.stdout.strip().splitlines()[-1])

    got = threads()
    assert got and all(n == 1 for n in got), got
    assert all(n == 2 for n in threads(OPENBLAS_NUM_THREADS="2")), "the user's choice wins"


_GC_CHILD = """
import gc
from rclpy.node import Node
import inkdiag_ros.fe_node  # the fe process's imports
from inkdiag_ros._spin import spin_node

class Probe(Node):
    def __init__(self):
        super().__init__("gc_probe")

frozen = []
spin_node(Probe, ["gc_probe"], until=lambda node: frozen.append(gc.get_freeze_count()) or True)
print(frozen[0])
"""


def test_node_processes_freeze_their_startup_objects_out_of_the_collector(ros):
    """Full garbage collections walked ~100,000 startup objects: 13 % of fe's soak samples (issue 12)."""
    import subprocess

    env = dict(os.environ, ROS_DOMAIN_ID=str(ros.domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    out = subprocess.run([sys.executable, "-c", _GC_CHILD], env=env, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stdout + out.stderr
    frozen = int(out.stdout.strip().splitlines()[-1])
    assert frozen > 10_000, f"only {frozen} objects frozen before spinning"


_EVENTS_CHILD = """
import signal, threading, time
from rclpy.node import Node
from inkdiag_ros._spin import spin_node

class Probe(Node):
    def __init__(self):
        super().__init__("events_probe")
        self.ticks = 0
        self.timer = self.create_timer(0.01, self._tick)

    def _tick(self):
        self.ticks += 1

seen = []
def until(node):
    seen.append((type(node.executor).__name__, node.ticks))
    if node.ticks >= 20 and not seen[0][0].startswith("_"):
        threading.Thread(target=lambda: signal.raise_signal(signal.SIGTERM)).start()
    return False

t0 = time.monotonic()
code = spin_node(Probe, ["events_probe"], events=True, until=until)
print(seen[-1][0], seen[-1][1], code, round(time.monotonic() - t0, 2))
"""


def test_spin_node_runs_the_events_executor_and_stops_on_a_signal(ros):
    """fe spins rclpy's C++ EventsExecutor (issue 12: the Python executor's cost per message)."""
    import subprocess

    env = dict(os.environ, ROS_DOMAIN_ID=str(ros.domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    out = subprocess.run([sys.executable, "-c", _EVENTS_CHILD], env=env, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stdout + out.stderr
    kind, ticks, code, _ = out.stdout.strip().splitlines()[-1].split()
    assert "Events" in kind and int(ticks) >= 20 and code == "0", out.stdout


_TEARDOWN_CHILD = """
import signal, threading
import rclpy.signals
from rclpy.node import Node
from std_msgs.msg import String
from inkdiag_ros._spin import spin_node

class Probe(Node):
    def __init__(self):
        super().__init__("teardown_probe")
        self.ticks = 0
        self.timer = self.create_timer(0.01, self._tick)
        self.pub = self.create_publisher(String, "teardown_probe", 10)

    def _tick(self):
        self.ticks += 1
        if self.ticks == 10:
            threading.Thread(target=lambda: signal.raise_signal(signal.SIGINT)).start()

    def destroy_node(self):
        print("handlers at destroy:", rclpy.signals.get_current_signal_handlers_options().name, flush=True)
        return super().destroy_node()

print("exit", spin_node(Probe, ["teardown_probe"]))
"""


def test_a_signal_stops_rclpys_signal_thread_before_the_node_is_destroyed(ros):
    """rclpy's signal thread shut the context down while the main thread destroyed the node's
    services: a SIGSEGV in ``Service.destroy`` about once per 100 Ctrl-Cs (CI, 2026-11-24). The
    handlers (and their thread) go first now (``_spin.tear_down``)."""
    import subprocess

    env = dict(os.environ, ROS_DOMAIN_ID=str(ros.domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    out = subprocess.run([sys.executable, "-c", _TEARDOWN_CHILD], env=env, capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 0, out.stdout + out.stderr
    assert "handlers at destroy: NO" in out.stdout and "exit 0" in out.stdout, out.stdout + out.stderr


@pytest.mark.parametrize("module", ["inkdiag_ros.fdi_node", "inkdiag_ros.fe_node"])
def test_the_trace_consuming_nodes_spin_the_events_executor(module, monkeypatch):
    """fdi and fe take every trace message: rclpy's Python executor rebuilt its wait set per message,
    ~0.4 ms of CPU per 400 kB message more than the EventsExecutor (``scripts/bench take --raw --events``)."""
    import importlib

    mod = importlib.import_module(module)
    calls = []
    monkeypatch.setattr(mod, "spin_node", lambda node_cls, args=None, **kw: calls.append(kw) or 0)
    assert mod.main([]) == 0
    assert calls == [{"events": True}]


@pytest.mark.parametrize(("module", "name", "extra"), [
    ("inkdiag_ros.fdi_node", "fdi", []), ("inkdiag_ros.fe_node", "fe", []),
    ("inkdiag_ros.baseline_node", "record_baseline", []),
    ("inkdiag_ros.printhead_sim", "printhead_sim", ["--record", "B"]),
])
def test_a_node_asked_for_help_prints_its_parameters_and_does_not_start(tmp_path, module, name, extra):
    import subprocess

    from inkdiag_ros.paramdoc import NODES

    params = importlib.import_module(module).PARAMS
    r = subprocess.run([sys.executable, "-m", module, *extra, "--help"], capture_output=True, text=True, timeout=60,
                       cwd=tmp_path, env=dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST"))
    assert r.returncode == 0 and r.stderr == "", r.stderr
    assert all(f"  {p[0]} (" in r.stdout for p in params) and "docs/parameters.md" in r.stdout
    assert dict((n, m) for n, m, _ in NODES)[name] == module
    assert not (tmp_path / "B").exists()  # printhead_sim --record: no bag begun


@pytest.mark.parametrize(("module", "ros_args", "says"), [
    ("inkdiag_ros.fdi_node", ["-p", "model_path"], "Couldn't parse parameter override rule: '-p model_path'"),
    ("inkdiag_ros.baseline_node", ["-p", "head_profile:="], "an empty string is written -p \"NAME:=''\""),
])
def test_ros_arguments_rcl_cannot_parse_are_one_line_and_status_2(tmp_path, module, ros_args, says):
    """rclpy.init raised on them: rcl's log line, a traceback, exit status 1 (helper-82's QA)."""
    import subprocess

    r = subprocess.run([sys.executable, "-m", module, "--ros-args", *ros_args], capture_output=True, text=True,
                       timeout=60, cwd=tmp_path, env=dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST"))
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1 and "bad ROS arguments: " in lines[0] and says in lines[0], r.stderr


def test_bad_ros_arguments_are_found_before_anything_starts(tmp_path, capfd, fdi_model):
    from inkdiag_ros import echo, graph
    from inkdiag_ros._spin import ros_args_error
    from inkdiag_ros.cli import main

    assert ros_args_error(["fdi", "--ros-args", "-r", "__ns:=/h", "-p", "n_nozzles:=8"]) is None
    assert ros_args_error(["fdi"]) is None
    assert ros_args_error(["fdi", "--ros-args", "--foo", "bar"]) == "unknown ROS arguments: --foo bar"
    assert ros_args_error(["x", "--ros-args", "--params-file", str(tmp_path / "none.yaml")]) == (
        f"bad ROS arguments: Couldn't parse params file: '--params-file {tmp_path / 'none.yaml'}'. "
        "Error: Error opening YAML file")
    assert capfd.readouterr().err == ""  # rcl's own log of it held back
    for run in (graph.main, echo.main):
        with pytest.raises(SystemExit) as exc:
            run(["prog", *(["labels"] if run is echo.main else []), "--ros-args", "-r", "badremap"])
        assert exc.value.code == 2 and "bad ROS arguments: Couldn't parse remap rule: '-r badremap'" in capfd.readouterr().err
    capfd.readouterr()
    assert main(["printer", "--heads", "1", "--model", str(fdi_model), "--ros-args", "-p", "x"]) == 2  # no child started
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("inkdiag printer: error: bad ROS arguments: "), err


def _sigint_as_a_terminal_gives_it():
    """In the child before it execs: SIGINT not ignored (a test run started as a shell's background job passes
    SIGINT ignored to its children)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _sigint_as_a_scripts_background_job_gets_it():
    """In the child before it execs: SIGINT ignored, as a non-interactive shell starts `fdi ... &`."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


@pytest.mark.parametrize("name", ["fdi", "fe", "printhead_sim", "record_baseline", "graph", "inkdiag_echo", "loopback"])
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_node_stopped_while_it_imports_exits_0(ros, fdi_model, name, sig, start=_sigint_as_a_terminal_gives_it):
    """The console scripts (inkdiag_ros._launch): a stop in the seconds the imports take ends the process with
    status 0 and no traceback (helper-69's QA: 130 with a KeyboardInterrupt traceback, 143 for SIGTERM)."""
    import shutil
    import subprocess
    import time

    exe = shutil.which(name)
    assert exe, f"{name}: the console script is not installed"
    env = dict(os.environ, ROS_DOMAIN_ID=str(ros.domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    args = {"fdi": ["--ros-args", "-p", f"model_path:={fdi_model}"], "inkdiag_echo": ["labels"]}.get(name, [])
    pr = subprocess.Popen([exe, *args], env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                          preexec_fn=start)
    time.sleep(0.8)  # past the entry point's first lines (0.14 s), within the imports (3.3-3.7 s here)
    pr.send_signal(sig)
    out = pr.communicate(timeout=30)[0]
    assert pr.returncode == 0 and out == "", (pr.returncode, out[-2000:])  # nothing: stopped before it ran


def test_a_node_started_ignoring_sigint_still_stops_on_it_while_it_imports(ros, fdi_model):
    """`fdi ... &` from a script starts it with SIGINT ignored; `kill -INT` in its first seconds was lost and the
    node ran on (helper-85's QA: 882 s), where the running node stops on it (rclpy takes SIGINT over)."""
    test_a_node_stopped_while_it_imports_exits_0(ros, fdi_model, "fdi", signal.SIGINT,
                                                 start=_sigint_as_a_scripts_background_job_gets_it)


def test_the_entry_point_gives_the_signals_back_before_the_node_runs(monkeypatch):
    """_launch._run: the node's main() sees the handlers the process had (Python's, or a signal it was started
    ignoring), not the import-time ones; a signal ignored at start is taken while importing, as the running node
    takes it (helper-85's QA: `fdi &` then `kill -INT` in its first seconds was lost, and the node ran on)."""
    import types

    from inkdiag_ros import _launch

    seen = {}
    mod = types.ModuleType("inkdiag_ros._stub_node")
    mod.main = lambda: seen.update({s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}) or 7
    monkeypatch.setitem(sys.modules, "inkdiag_ros._stub_node", mod)
    before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        assert _launch._run("_stub_node") == 7 and seen == before
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        taken = []
        monkeypatch.setattr(importlib, "import_module", lambda name: taken.append(signal.getsignal(signal.SIGINT)) or mod)
        _launch._run("_stub_node")
        assert taken[0] not in (signal.SIG_IGN, signal.SIG_DFL) and seen[signal.SIGINT] is signal.SIG_IGN
    finally:
        for s, h in before.items():
            signal.signal(s, h)


def test_a_console_script_node_once_running_stops_as_python_m_does(ros, fdi_model):
    """The entry point gives the signals back before the node runs: a running fdi stops on SIGINT with 0."""
    import shutil
    import subprocess

    env = dict(os.environ, ROS_DOMAIN_ID=str(ros.domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    pr = subprocess.Popen([shutil.which("fdi"), "--ros-args", "-p", f"model_path:={fdi_model}"], env=env,
                          stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                          preexec_fn=_sigint_as_a_terminal_gives_it)
    seen = []
    for line in pr.stdout:  # up: its model loaded, spinning (pytest's timeout bounds the wait)
        seen.append(line)
        if "FDI model" in line and "loaded from" in line:
            break
    pr.send_signal(signal.SIGINT)
    rest = pr.communicate(timeout=30)[0]
    assert pr.returncode == 0 and "Traceback" not in rest, (pr.returncode, "".join(seen) + rest)


@pytest.mark.parametrize("at_s", [0.3, 3.0, "header+0.12", "header+0.3"])
def test_inkdiag_printer_stopped_at_any_time_exits_0(ros, fdi_model, at_s):
    """docs/scaling.md: SIGTERM gives 0, also while `inkdiag printer` imports and starts its children (helper-73's
    QA: 143 before its header line) and as it imports rclpy or builds its monitor's node after that line
    ("header+S": S s after it; an ImportError or RCLError traceback and 1 before); its children are gone after it."""
    import shutil
    import subprocess
    import time

    env = dict(os.environ, ROS_DOMAIN_ID=str(ros.domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    pr = subprocess.Popen([shutil.which("inkdiag"), "printer", "--heads", "2", "--processes", "2", "--simulate",
                           "--model", str(fdi_model)], env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                          text=True)
    head = ""
    if str(at_s).startswith("header+"):
        head = pr.stdout.readline()
        time.sleep(float(at_s.split("+")[1]))
    else:
        time.sleep(at_s)
    pr.send_signal(signal.SIGTERM)
    out = head + _finish(pr)[0]
    assert pr.returncode == 0 and "Traceback" not in out, (pr.returncode, out[-2000:])
    pids = [int(p) for p in out.split("(pids ", 1)[1].split(")", 1)[0].split(", ")] if "(pids " in out else []
    deadline = time.monotonic() + 10
    while any(os.path.exists(f"/proc/{p}") for p in pids) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not any(os.path.exists(f"/proc/{p}") for p in pids), out


@pytest.mark.parametrize("verb", ["record", "replay"])
def test_inkdiag_record_and_replay_stopped_while_starting_as_a_background_job_exit_0(ros, tmp_path, verb):
    """helper-123's QA: `inkdiag record B &` then `kill -INT` 1 s later ran on until killed (a shell's background
    job starts with SIGINT ignored, and the node's handler was not in yet). Stopped while starting, each says
    'interrupted' and exits 130, as from a terminal (or 0, had it got that far)."""
    import shutil
    import subprocess
    import time

    from _bags import write_bag
    from inkdiag_core import HeadProfile

    env = dict(os.environ, ROS_DOMAIN_ID=str(ros.domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    if verb == "record":
        argv = [shutil.which("inkdiag"), "record", str(tmp_path / "new"), "--topics", "traces"]
    else:
        x = HeadProfile.default().simulate({"healthy_nozzle": 8}, seed=0).traces
        argv = [shutil.which("inkdiag"), "replay", str(write_bag(tmp_path / "bag", [(0, x)])), "--wait-s", "30"]
    pr = subprocess.Popen(argv, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                          preexec_fn=_sigint_as_a_scripts_background_job_gets_it)
    try:
        time.sleep(0.5)
        pr.send_signal(signal.SIGINT)
        out = pr.communicate(timeout=30)[0]
    finally:
        if pr.poll() is None:  # it ran on: no orphan left behind the failure
            pr.kill()
            pr.wait()
    assert "Traceback" not in out, out[-2000:]
    assert (pr.returncode, out.strip()) == (130, f"inkdiag {verb}: interrupted") or pr.returncode == 0, out


def test_a_bag_is_not_written_inside_another(tmp_path):
    """helper-123: `inkdiag record run1/inner`, run1 a bag, wrote a bag inside it."""
    from _bags import write_bag
    from inkdiag_core import HeadProfile
    from inkdiag_ros.bags import check_new_bag

    bag = write_bag(tmp_path / "run1", [(0, HeadProfile.default().simulate({"healthy_nozzle": 2}, seed=0).traces)])
    (bag / "sub").mkdir()
    for inner in (bag / "inner", bag / "sub" / "deeper"):
        with pytest.raises(ValueError, match="inside the bag .*run1; write the new bag beside it"):
            check_new_bag(inner)
    assert check_new_bag(tmp_path / "beside") == tmp_path / "beside"
    (tmp_path / "exports").mkdir()  # a folder of other tools' single-file MCAP recordings: no bag of its own
    (tmp_path / "exports" / "drive_test.mcap").write_bytes(b"\x89MCAP0\r\n")
    assert check_new_bag(tmp_path / "exports" / "new") == tmp_path / "exports" / "new"


@pytest.mark.parametrize("value", ["-1", "nan", "inf"])
def test_graph_refuses_a_duration_that_is_not_a_number_of_seconds(value):
    """helper-73's QA: --duration -1 ran until killed, nan stopped at once with 0 frames and exit 0."""
    import subprocess

    r = subprocess.run([sys.executable, "-m", "inkdiag_ros.graph", "--duration", value], capture_output=True,
                       text=True, timeout=60, env=dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST"))
    assert r.returncode == 2 and "graph: error: --duration must be a number of seconds >= 0" in r.stderr, r.stderr


def test_a_stop_whose_exit_was_swallowed_still_exits_at_the_end_of_the_block(capsys):
    """A CI run lost a SIGINT while printhead_sim imported: its SystemExit landed in a weakref callback of the
    import machinery, which Python ignores ('Exception ignored in ... _get_module_lock', a traceback), and the
    node ran on. stop_means_exit_0 exits at the end of the block then, and prints no such traceback."""
    import types

    from inkdiag_ros._launch import stop_means_exit_0

    before = sys.unraisablehook
    with pytest.raises(SystemExit) as got:
        with stop_means_exit_0():
            try:
                signal.raise_signal(signal.SIGTERM)
            except SystemExit:  # where Python ignores it
                sys.unraisablehook(types.SimpleNamespace(exc_type=SystemExit, exc_value=SystemExit(0),
                                                         exc_traceback=None, err_msg=None, object=None))
            reached = True
    assert got.value.code == 0 and reached and capsys.readouterr().err == "" and sys.unraisablehook is before
    with stop_means_exit_0():  # no signal: nothing happens
        pass


def test_a_stop_swallowed_before_stop_on_signals_is_requested_there():
    """A CI run's printer, SIGTERMed 0.3 s after its start, ran on until killed: the SIGTERM's SystemExit was
    swallowed as the printer imported (inside stop_means_exit_0) and its monitor's stop_on_signals, entered
    after, started with no stop. Entered after a swallowed stop, it starts with the stop requested."""
    from inkdiag_ros._launch import stop_means_exit_0
    from inkdiag_ros._spin import stop_on_signals

    with pytest.raises(SystemExit) as got:
        with stop_means_exit_0():
            try:
                signal.raise_signal(signal.SIGTERM)
            except SystemExit:  # where Python ignores it
                pass
            with stop_on_signals() as stop:
                requested = stop.requested
    assert got.value.code == 0 and requested
    with stop_means_exit_0(), stop_on_signals() as stop:  # no signal: no stop
        assert not stop.requested


def test_after_a_stop_a_half_built_rclpy_objects_finalizer_error_is_not_printed(monkeypatch):
    """A CI run's printer, SIGTERMed as its monitor built its executor, printed "Exception ignored in
    <function Executor.__del__>" and an AttributeError traceback (the half-built executor had no _sigint_gc)."""
    import types

    from rclpy.executors import Executor

    from inkdiag_ros._spin import stop_on_signals

    seen = []
    monkeypatch.setattr(sys, "unraisablehook", seen.append)

    def ignored(obj):
        return types.SimpleNamespace(exc_type=AttributeError, exc_value=AttributeError("_sigint_gc"),
                                     exc_traceback=None, err_msg=None, object=obj)

    with stop_on_signals() as stop:
        sys.unraisablehook(ignored(Executor.__del__))  # before a stop: printed
        stop._on_signal(signal.SIGTERM, None)
        sys.unraisablehook(ignored(Executor.__del__))  # after it: not
        sys.unraisablehook(ignored(_finish))  # not rclpy's: printed
        other = ignored(Executor.__del__)
        other.exc_type = ValueError  # not a half-built object's missing attribute: printed
        sys.unraisablehook(other)
        sys.unraisablehook(ignored([].append))  # a builtin's __module__ is None (helper-80: the hook crashed)
    assert [u.object for u in seen] == [Executor.__del__, _finish, Executor.__del__, seen[-1].object]
    assert seen[-1].exc_type is AttributeError and sys.unraisablehook == seen.append


def test_a_signal_as_stop_on_signals_installs_its_handlers_is_not_lost(monkeypatch):
    """helper-80: a SIGTERM between stop_on_signals installing its handler and reading the handler it replaced was
    set back to no stop (nothing would wake the loop again)."""
    from inkdiag_ros._spin import stop_on_signals

    real = signal.signal

    def install_then_signal(sig, handler):
        old = real(sig, handler)
        if sig == signal.SIGTERM and getattr(handler, "__name__", "") == "_on_signal":
            signal.raise_signal(signal.SIGTERM)  # its handler runs before the next line of stop_on_signals
        return old

    monkeypatch.setattr(signal, "signal", install_then_signal)
    with stop_on_signals() as stop:
        assert stop.requested


def _finish(pr, timeout=60):
    """``pr.communicate(timeout=...)``; a process still running after it is killed (no leftover on a CI box)."""
    try:
        return pr.communicate(timeout=timeout)
    finally:
        if pr.poll() is None:
            pr.kill()
            pr.communicate()


@pytest.mark.parametrize("at_s", [0.5, 2.5])
def test_inkdiag_record_interrupted_at_any_time_says_so_in_one_line(ros, tmp_path, at_s):
    """Ctrl-C of `inkdiag record` while it imports (seconds): 'interrupted' and 130, not a KeyboardInterrupt
    traceback; once it has started (or as its node is built), 0 with a valid bag."""
    import shutil
    import subprocess
    import time

    env = dict(os.environ, ROS_DOMAIN_ID=str(ros.domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    pr = subprocess.Popen([shutil.which("inkdiag"), "record", str(tmp_path / "bag")], env=env,
                          stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                          preexec_fn=_sigint_as_a_terminal_gives_it)
    time.sleep(at_s)
    pr.send_signal(signal.SIGINT)
    out = _finish(pr)[0]
    assert "Traceback" not in out, out[-2000:]
    assert (pr.returncode, out.strip()) == (130, "inkdiag record: interrupted") or (
        pr.returncode == 0 and "wrote 0 messages" in out and (tmp_path / "bag" / "metadata.yaml").is_file()), out


def test_a_stop_that_comes_out_as_another_exception_still_exits_0():
    """CI: a SIGTERM while rclpy's C extension initialised came out of the import as an ImportError (pybind11
    turns any error of a module's init into one): a traceback and status 1. After a stop, whatever leaves the
    block is that stop; without one, an error goes on up as it is."""
    from inkdiag_ros._launch import stop_means_exit_0

    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(SystemExit) as got:
        with stop_means_exit_0():
            try:
                signal.raise_signal(signal.SIGTERM)
            except SystemExit as exc:  # as pybind11's module init does
                raise ImportError("initialization failed") from exc
    assert got.value.code == 0 and signal.getsignal(signal.SIGTERM) is before
    with pytest.raises(ImportError):
        with stop_means_exit_0():
            raise ImportError("no stop: a real error")
    with pytest.raises(RuntimeError, match="after the stop"):  # a stop does not hide an error of its own
        with stop_means_exit_0():
            try:
                signal.raise_signal(signal.SIGTERM)
            except SystemExit:
                pass
            raise RuntimeError("a real error after the stop")


def test_inkdiag_says_interrupted_for_a_ctrl_c_that_comes_out_as_another_exception(monkeypatch, capsys):
    """helper-78's review: a Ctrl-C in rclpy's C extension's init reaches the verb as an ImportError caused by the
    KeyboardInterrupt; that is 'interrupted' and 130 too; an ImportError of its own is not."""
    from inkdiag_ros import cli

    def ctrl_c_in_init(argv):
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as exc:
            raise ImportError("initialization failed") from exc

    monkeypatch.setattr(cli, "_main", ctrl_c_in_init)
    assert cli.main(["record", "bag"]) == 130
    assert capsys.readouterr().err == "inkdiag record: interrupted\n"

    def broken(argv):
        raise ImportError("a module really missing")

    monkeypatch.setattr(cli, "_main", broken)
    with pytest.raises(ImportError, match="really missing"):
        cli.main(["record", "bag"])


def test_graph_interrupted_while_it_trains_the_default_model_says_so_and_writes_nothing(tmp_path):
    """scripts/run's first run trains the default model (seconds): a Ctrl-C then is one line and 130, not a
    KeyboardInterrupt traceback, and leaves no model file behind (the next run trains it)."""
    import subprocess

    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    model = tmp_path / "models" / "fdi_default.joblib"
    pr = subprocess.Popen([sys.executable, "-m", "inkdiag_ros.graph", "--train-if-missing", "--model", str(model)],
                          env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                          preexec_fn=_sigint_as_a_terminal_gives_it)
    seen = ""
    while "training the default FDI model" not in seen:  # tqdm's bar: no newline to read a line up to
        ch = pr.stderr.read(1)
        assert ch, seen
        seen += ch
    pr.send_signal(signal.SIGINT)
    err = seen + _finish(pr)[1]
    assert pr.returncode == 130 and "Traceback" not in err, (pr.returncode, err[-2000:])
    assert "graph: interrupted while checking or training the default model" in err and not model.exists()
    assert not model.parent.exists() or not any(model.parent.iterdir())  # no temporary file left either


@pytest.mark.parametrize("after_s", [0.2, 0.5])
def test_graph_stopped_while_it_builds_its_nodes_exits_0(ros, fdi_model, after_s):
    """helper-77's QA: a Ctrl-C of `graph` (no --baseline) just after its header line, as it built the fdi node,
    gave an RCLError or NotInitializedException traceback and status 1 (both delays failed before)."""
    import subprocess
    import time

    env = dict(os.environ, ROS_DOMAIN_ID=str(ros.domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               PYTHONUNBUFFERED="1")  # its header line now, not at exit (else the signal finds it gone)
    pr = subprocess.Popen([sys.executable, "-m", "inkdiag_ros.graph", "--duration", "20", "--model", str(fdi_model)],
                          env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                          preexec_fn=_sigint_as_a_terminal_gives_it)
    t0 = time.monotonic()
    head = pr.stdout.readline()
    assert head.startswith("inkdiag graph:"), head
    time.sleep(after_s)
    pr.send_signal(signal.SIGINT)
    err = _finish(pr)[1]
    assert pr.returncode == 0 and "Traceback" not in err, (pr.returncode, err[-2000:])
    assert time.monotonic() - t0 < 15, "it ran its 20 s: the SIGINT did not stop it"
