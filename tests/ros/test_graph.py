"""The whole graph: one process on one executor, and three processes on localhost."""

import os
import signal
import subprocess
import sys
import time
import warnings

import numpy as np
import pytest
from rclpy.parameter import Parameter

from msg_defs import (
    ESTIMATES_MSG_TYPE,
    LABELS_MSG_TYPE,
    RELIABLE_QOS,
    decode_estimates,
    decode_labels,
    topics,
)

P = Parameter
FAULTS = {3: "fully_blocked", 9: "mature_air_bubble", 14: "empty_channel_1", 21: "small_air_bubble"}
DRYING = 17
SIM = {"n_nozzles": 24, "frame_rate_hz": 10.0, "fault_nozzles": list(FAULTS),
       "fault_classes": list(FAULTS.values()), "drying_nozzles": [DRYING],
       "drying_start_factor": 2.6, "drying_end_factor": 8.5, "drying_duration_s": 3.0}


def test_graph_end_to_end_in_one_process(ros, fdi_model):
    from inkdiag_ros.fdi_node import FdiNode
    from inkdiag_ros.fe_node import FeNode
    from inkdiag_ros.graph import OperatorMonitor
    from inkdiag_ros.printhead_sim import PrintheadSim

    kw = {"context": ros.context, "namespace": "/head_01"}
    ros.add(PrintheadSim(parameter_overrides=[P(k, value=v) for k, v in SIM.items()], **kw))
    ros.add(FdiNode(parameter_overrides=[P("model_path", value=str(fdi_model)),
                                         P("n_nozzles", value=24)], **kw))
    ros.add(FeNode(**kw))
    mon = ros.add(OperatorMonitor(**kw))
    ros.spin_until(lambda: len(mon.score.fm_rows) >= 25, 15, "25 f_m estimates of the drying nozzle")
    # injected faults -> flagged in most frames, their own class in most of those (nozzle 9's bubble
    # persists near the mature / intermediate boundary: the small test model calls it mature in about
    # two frames of three, the default model in 38 of 40)
    reps = [r for r in mon.score.labels.values()]
    for nz, cls in FAULTS.items():
        got = [dict((n, c) for n, c, _ in r.faults).get(nz) for r in reps]
        flagged, hits = sum(c is not None for c in got), sum(c == cls for c in got)
        assert flagged >= 0.8 * len(reps) and hits > 0.5 * len(reps), (nz, cls, flagged, hits, len(reps))
    assert mon.score.label_scores()["accuracy"] > 0.95
    # the drying nozzle: f_m rising (more negative) and within tolerance of the truth
    rows = np.array([r[2:] for r in mon.score.fm_rows if r[1] == DRYING])
    est, trend, true = rows[:, 0], rows[:, 1], rows[:, 2]
    assert true[-1] < 1.8 * true[0] < 0  # it did dry (truth)
    assert trend[-1] < 1.8 * trend[0]  # and the estimate followed
    assert np.median(np.abs(est - true) / np.abs(true)) < 0.15
    assert abs(trend[-1] - true[-1]) / abs(true[-1]) < 0.2
    assert "faults [3:fully_blocked" in mon.summary(1.0)


def _node_proc(module, ros_args, domain_id):
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    return subprocess.Popen([sys.executable, "-m", module, "--ros-args", "-r", "__ns:=/head_02",
                             *ros_args], env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)


def test_three_processes_on_localhost(ros, fdi_model):
    def p(k, v):
        v = "[" + ",".join(f"'{x}'" if isinstance(x, str) else str(x) for x in v) + "]" if isinstance(v, list) else v
        return ["-p", f"{k}:={v}"]

    sim_args = [a for k, v in SIM.items() for a in p(k, v)]
    procs = [
        _node_proc("inkdiag_ros.printhead_sim", sim_args, ros.domain_id),
        _node_proc("inkdiag_ros.fdi_node", p("model_path", str(fdi_model)) + p("n_nozzles", 24),
                   ros.domain_id),
        _node_proc("inkdiag_ros.fe_node", [], ros.domain_id),
    ]
    try:
        probe = ros.node("probe", namespace="/head_02")
        labels, est = [], []
        probe.create_subscription(LABELS_MSG_TYPE, topics.LABELS, lambda m: labels.append(decode_labels(m)),
                                  RELIABLE_QOS)
        probe.create_subscription(ESTIMATES_MSG_TYPE, topics.FM_ESTIMATES,
                                  lambda m: est.append(decode_estimates(m)), RELIABLE_QOS)
        ros.spin_until(lambda: len(labels) >= 5 and len(est) >= 3, 40,
                       "labels and f_m estimates from the three processes")
        got = dict((nz, c) for nz, c, _ in labels[-1].faults)
        assert sum(got.get(nz) == c for nz, c in FAULTS.items()) >= 3
        assert DRYING in est[-1].nozzles.tolist()
    finally:
        for pr in procs:
            pr.send_signal(signal.SIGINT)
        outs = []
        for pr in procs:
            try:
                outs.append(pr.communicate(timeout=10)[0])
            except subprocess.TimeoutExpired:
                pr.kill()
                outs.append(pr.communicate()[0])
    for pr, out in zip(procs, outs):
        assert pr.returncode == 0, out[-2000:]  # SIGINT: a clean shutdown
        assert "Traceback" not in out, out[-2000:]
        if "Timeout (" in out:  # the teardown deadline ended a Fast DDS livelock (docs/nodes.md): visible, not a failure
            warnings.warn(f"{pr.args[2]}: teardown deadline passed\n{out[-1500:]}", stacklevel=1)


@pytest.fixture(scope="module")
def baseline_model(tmp_path_factory):
    from inkdiag_core.fdi import train_default_model

    path = tmp_path_factory.mktemp("model") / "fdi_baseline_small.joblib"
    train_default_model(path, n_per_class=80, baseline=True)  # a detector with its baseline branch
    return path


@pytest.mark.parametrize(("sig", "baseline"), [(signal.SIGTERM, False), (signal.SIGINT, True)])
def test_graph_runner_stops_cleanly_on_signal(ros, fdi_model, baseline_model, tmp_path, sig, baseline):
    env = dict(os.environ, ROS_DOMAIN_ID=str(ros.domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    extra = (["--baseline", "--baseline-path", str(tmp_path / "b.npz"),
              "--commissioning", "2.5"] if baseline else ["--no-baseline"])
    pr = subprocess.Popen([sys.executable, "-m", "inkdiag_ros.graph", "--duration", "0", "--model",
                           str(baseline_model if baseline else fdi_model), *extra, "--ros-args", "-p", "n_nozzles:=16", "-p", "fault_nozzles:=[3]",
                           "-p", "fault_classes:=['fully_blocked']", "-p", "drying_nozzles:=[9]", "-p", "bogus_x:=1",
                           "-p", "fm_frames:=2"],
                          env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines = []
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        line = pr.stdout.readline()
        lines.append(line)
        if "faults [3:" in line and (not baseline or "rows vs their baseline" in line):
            break
    pr.send_signal(sig)
    try:
        rest = pr.communicate(timeout=15)[0]
    except subprocess.TimeoutExpired:
        pr.kill()
        pytest.fail("graph runner did not stop on the signal:\n" + "".join(lines))
    out = "".join(lines) + rest
    assert pr.returncode == 0, out[-2000:]
    assert "scorecard against the simulator's ground truth" in out and "Traceback" not in out
    assert ("rows vs their baseline" in out) == baseline, out[-2000:]
    # a -p reaches every node: the sim's own (fault_nozzles, ...) unsaid by the others, a name none has said, and
    # record_baseline's fm_frames said when there is no record_baseline
    ignoring = [line for line in out.splitlines() if "ignoring parameter(s)" in line]
    assert len(ignoring) == (4 if baseline else 3), ignoring  # sim, fdi, fe (and record_baseline)
    assert all("does not have: bogus_x" in line and ("fm_frames" in line) != baseline for line in ignoring), ignoring


def test_graph_records_baselines_then_labels_against_them(ros, baseline_model, tmp_path):
    from inkdiag_core import NozzleBaselines
    from inkdiag_ros.graph import run

    lines = []
    # 4 s of commissioning: 8 healthy frames at 5 Hz need 1.6 s, and a loaded 2-core machine can halve that rate
    score = run(8.5, namespace="/head_05", model_path=str(baseline_model), context=ros.context, out=lines.append,
                baseline={"path": tmp_path / "b" / "head_05.npz", "commissioning_s": 4.0})
    assert any("baselines of 64 nozzles recorded" in line for line in lines), lines[:5]
    assert len(NozzleBaselines.load(tmp_path / "b" / "head_05.npz")) == 64
    assert lines[0].startswith("t=") and "commissioning" in lines[0]
    assert "rows vs their baseline" in lines[-1]  # fdi classified against the recorded baselines
    assert score.label_scores()["accuracy"] > 0.95
    assert any("faults [3:fully_blocked" in line for line in lines)
    b = NozzleBaselines.load(tmp_path / "b" / "head_05.npz")
    assert b.fm is not None and np.isfinite(b.fm).all()  # and each nozzle's healthy f_m for fe
    assert score.fm_scores()["estimates"] > 0


def test_graph_runner_refuses_a_bad_scenario_in_one_line(ros):
    env = dict(os.environ, ROS_DOMAIN_ID=str(ros.domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    pr = subprocess.run([sys.executable, "-m", "inkdiag_ros.graph", "--duration", "5", "--ros-args",
                         "-p", "fault_nozzles:=[3]", "-p", "fault_classes:=['fully_blocked']",
                         "-p", "drying_nozzles:=[3]"], env=env, capture_output=True, text=True, timeout=60)
    assert pr.returncode == 2, pr.stdout + pr.stderr
    assert pr.stderr.strip() == "graph: PrintheadSim: nozzles both faulty and drying: [3]", pr.stderr


def test_graph_runner_cleans_up_the_nodes_it_built_when_a_later_one_refuses(ros, fdi_model):
    env = dict(os.environ, ROS_DOMAIN_ID=str(ros.domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    pr = subprocess.run([sys.executable, "-m", "inkdiag_ros.graph", "--duration", "3", "--no-baseline",
                         "--model", str(fdi_model), "--ros-args", "-p", "labelling_process:=true",
                         "-p", "trend_accel_std:=0.5"], env=env, capture_output=True, text=True, timeout=60)
    assert pr.returncode == 2, pr.stdout + pr.stderr
    assert pr.stderr.strip().splitlines()[-1].startswith("graph: FeNode:"), pr.stderr
    assert "leaked" not in pr.stderr and "Traceback" not in pr.stderr  # fdi, its child and buffers released


def test_shutting_down_waits_a_moment_for_the_context_to_go_down():
    from inkdiag_ros._spin import shutting_down

    class Ctx:
        def __init__(self, down_after_s):
            self.t_down = time.monotonic() + down_after_s

        def ok(self):
            return time.monotonic() < self.t_down

    assert shutting_down(Ctx(0.0))
    assert shutting_down(Ctx(0.05), grace_s=0.5)  # an error a moment before the shutdown shows
    assert not shutting_down(Ctx(10.0), grace_s=0.05)  # a real error: the context stays up


def test_sigint_as_shutdown_replaces_keyboard_interrupt_and_restores_the_handler():
    from inkdiag_ros._spin import sigint_as_shutdown

    before = signal.getsignal(signal.SIGINT)
    with sigint_as_shutdown():
        assert signal.getsignal(signal.SIGINT) is not before
        os.kill(os.getpid(), signal.SIGINT)  # no KeyboardInterrupt: rclpy's handler (if any) does the work
        time.sleep(0.05)
    assert signal.getsignal(signal.SIGINT) is before


def test_graph_runs_a_smaller_head_with_the_packaged_faults_on_it(ros, fdi_model):
    """`-p n_nozzles:=32` was refused: the packaged config's fault list (35, 51; drying 40) counted as the user's
    (helper-139's review). Those not on the head are left out with a warning; a list the user names is theirs."""
    env = dict(os.environ, ROS_DOMAIN_ID=str(ros.domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    base = [sys.executable, "-m", "inkdiag_ros.graph", "--duration", "2", "--model", str(fdi_model), "--ros-args",
            "-p", "n_nozzles:=32"]
    pr = subprocess.run(base, env=env, capture_output=True, text=True, timeout=120)
    assert pr.returncode == 0, pr.stdout + pr.stderr
    assert "default fault or drying nozzles [35, 51, 40] are not on this head (nozzles 0..31): left out" in pr.stderr
    pr = subprocess.run(base + ["-p", "drying_nozzles:=[40]"], env=env, capture_output=True, text=True, timeout=120)
    assert pr.returncode == 2 and "outside this head's nozzles 0..31" in pr.stderr, pr.stdout + pr.stderr


def test_the_packaged_fault_lists_are_defaults_unless_the_user_names_one(tmp_path):
    from inkdiag_ros.graph import SCENARIO_LISTS, default_params_file, shipped_scenario

    pkg = ["graph", "--ros-args", "--params-file", default_params_file()]
    assert shipped_scenario(pkg + ["-p", "n_nozzles:=32"]) == SCENARIO_LISTS
    assert shipped_scenario(pkg + ["-p", "fault_classes:=['fully_blocked']"]) == ()
    mine = tmp_path / "mine.yaml"
    mine.write_text("/**/printhead_sim:\n  ros__parameters:\n    drying_nozzles: [5]\n")
    assert shipped_scenario(pkg + ["--params-file", str(mine)]) == ()
    assert shipped_scenario(["graph", "--ros-args", "-p", "n_nozzles:=32"]) == ()  # not the packaged file: given
