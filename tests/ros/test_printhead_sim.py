"""The printhead_sim node alone, real rclpy on a per-test Context, against test subscribers."""

import numpy as np
import pytest
from rclpy.parameter import Parameter as P

from _helpers import collect
from msg_defs import (
    RELIABLE_QOS,
    TRACE_MSG_TYPE,
    TRACES_QOS,
    TRUTH_MSG_TYPE,
    decode_traces,
    decode_truth,
    topics,
)


def test_printhead_sim_publishes_frames_and_truth(ros):
    from inkdiag_ros.printhead_sim import PrintheadSim

    sim = ros.add(PrintheadSim(context=ros.context, namespace="/head_03", parameter_overrides=[
        P("n_nozzles", value=16), P("first_nozzle", value=100), P("frame_rate_hz", value=50.0),
        P("fault_nozzles", value=[102]), P("fault_classes", value=["fully_blocked"]),
        P("drying_nozzles", value=[105]), P("drying_duration_s", value=0.1), P("max_frames", value=12)]))
    probe = ros.node("probe", namespace="/head_03")
    frames = collect(ros, probe, TRACE_MSG_TYPE, topics.TRACES, TRACES_QOS, decode_traces)
    truth = collect(ros, probe, TRUTH_MSG_TYPE, topics.GROUND_TRUTH, RELIABLE_QOS, decode_truth)
    ros.spin_until(lambda: len(truth) >= 12 and len(frames) >= 3, 10, "12 truth messages")
    ros.spin_for(0.2)
    assert sim.frames_published == 12  # max_frames holds
    f = frames[-1]
    assert f.traces.shape == (16, 512) and f.first_nozzle == 100 and f.sample_rate_hz == 10e6
    assert np.isfinite(f.traces).all() and np.ptp(f.traces, axis=1).min() > 0
    # the head's nozzles keep their tolerances: a healthy nozzle's trace changes from frame
    # to frame by the noise and the ink temperature, far less than from nozzle to nozzle
    healthy = [i for i in range(16) if i + 100 not in (102, 105)]
    a, b = frames[-2].traces[healthy], frames[-1].traces[healthy]
    same = np.sqrt(((a - b) ** 2).mean(axis=1)).mean()
    other = np.sqrt(((a - np.roll(b, 1, axis=0)) ** 2).mean(axis=1)).mean()
    assert same < 0.5 * other
    classes = [t.class_of() for t in truth]
    assert all(c[102] == "fully_blocked" for c in classes)
    assert classes[0][105] == "slightly_dried" and classes[-1][105] == "deeply_dried"
    fm = [dict((nz, f) for nz, _, f, _ in t.faults)[105] for t in truth]
    assert fm[-1] < fm[0] < 0  # drying: f_m grows in magnitude


def test_printhead_sim_rejects_bad_scenarios_and_runtime_changes(ros):
    from inkdiag_ros.printhead_sim import PrintheadSim

    with pytest.raises(ValueError, match="unknown fault class 'melted'"):
        PrintheadSim(context=ros.context, parameter_overrides=[
            P("fault_nozzles", value=[1]), P("fault_classes", value=["melted"])])
    with pytest.raises(ValueError, match="outside this head's nozzles"):
        PrintheadSim(context=ros.context, parameter_overrides=[P("drying_nozzles", value=[64])])
    with pytest.raises(ValueError, match=r"fault_nozzles lists \[3\] more than once"):  # the later one won
        PrintheadSim(context=ros.context, parameter_overrides=[
            P("fault_nozzles", value=[3, 3, 11]), P("fault_classes", value=["fully_blocked", "mature_air_bubble",
                                                                            "deeply_dried"])])
    # helper-118: the node started, then died at its first frame (nozzle ids past the wire's 2**24; a frame of
    # 24 GiB)
    def at(first):  # the head's first nozzle, one fixed fault and one drying nozzle among its own
        return [P("first_nozzle", value=first), P("fault_nozzles", value=[first]),
                P("fault_classes", value=["fully_blocked"]), P("drying_nozzles", value=[first + 1])]

    with pytest.raises(ValueError, match=r"nozzles 16777215\.\.16777278: the traces carry nozzle ids below 16777216"):
        PrintheadSim(context=ros.context, parameter_overrides=at(2**24 - 1))
    with pytest.raises(ValueError, match="a frame of 100000 nozzles x 65536 samples is more than 134,217,728"):
        PrintheadSim(context=ros.context, parameter_overrides=[P("n_nozzles", value=100_000),
                                                               P("n_samples", value=65536)])
    # helper-138: a head of 40 nozzles or fewer did not start on the default faults (19, 27, drying 40)
    small = ros.add(PrintheadSim(context=ros.context, parameter_overrides=[P("n_nozzles", value=16)]))
    assert small.config["fault_nozzles"] == [3, 11] and small.config["drying_nozzles"] == []
    assert small.config["fault_classes"] == ["fully_blocked", "mature_air_bubble"]
    off = ros.add(PrintheadSim(context=ros.context, parameter_overrides=[P("first_nozzle", value=10),
                                                                         P("n_nozzles", value=32)]))
    assert off.config["fault_nozzles"] == [11, 19, 27] and off.config["drying_nozzles"] == [40]
    far = ros.add(PrintheadSim(context=ros.context, parameter_overrides=[P("first_nozzle", value=100)]))
    assert far.config["fault_nozzles"] == far.config["drying_nozzles"] == []  # none on it: left out, said
    from inkdiag_core.simulation.scenario import defaults_on_head

    p = {"n_nozzles": 32, "first_nozzle": 0, "fault_nozzles": [3, 40], "fault_classes": ["a", "b"],
         "drying_nozzles": [40]}
    assert defaults_on_head(p, {"fault_nozzles"}) == [40] and p["fault_nozzles"] == [3, 40]  # given: the scenario's
    with pytest.raises(ValueError, match="outside this head's nozzles"):  # a list given is the user's: refused
        PrintheadSim(context=ros.context, parameter_overrides=[P("n_nozzles", value=16),
                                                               P("fault_nozzles", value=[3, 11, 19, 27])])
    last = ros.add(PrintheadSim(context=ros.context, parameter_overrides=at(2**24 - 64)))
    assert last.scenario.first_nozzle == 2**24 - 64  # its last nozzle, 2**24 - 1, is on the wire
    sim = ros.add(PrintheadSim(context=ros.context))
    res = sim.set_parameters([P("n_nozzles", value=8)])[0]
    assert not res.successful and "read-only" in res.reason and sim.describe_parameter("n_nozzles").read_only
    res = sim.set_parameters([P("frame_rate_hz", value=1e6)])[0]  # outside the descriptor's range
    assert not res.successful


def _foreign_profile(tmp_path, head):
    """Another head as a YAML file: the default head at 20 MHz x 1024 with other ink, nozzle and sense
    gain, or the true profile of a head of ``tests/foreign_head.py`` (h5: 5 MHz x 256)."""
    from inkdiag_core import HeadProfile

    if head == "replaced":
        prof = HeadProfile.default().replace(
            name="foreign", sample_rate_hz=20e6, n_samples=1024,
            channel={"rho": 1100.0, "mu": 6e-3, "r_n": 11e-6, "L_n": 45e-6}, sensor={"gain_v_per_m3s": 2.0e10})
        return prof, prof.save(tmp_path / "foreign.yaml")
    from foreign_head import write_true_yaml

    write_true_yaml(tmp_path / f"{head}.yaml", head)
    return HeadProfile.load(tmp_path / f"{head}.yaml"), tmp_path / f"{head}.yaml"


@pytest.mark.parametrize("head", ["replaced", "h5"])
def test_printhead_sim_publishes_the_traces_of_its_head_profile(ros, tmp_path, head):
    from inkdiag_ros.printhead_sim import PrintheadSim

    prof, path = _foreign_profile(tmp_path, head)
    fs, n = prof.sample_rate_hz, prof.n_samples
    sim = ros.add(PrintheadSim(context=ros.context, namespace="/head_09", parameter_overrides=[
        P("head_profile", value=str(path)), P("n_nozzles", value=12), P("frame_rate_hz", value=50.0),
        P("fault_nozzles", value=[2]), P("fault_classes", value=["fully_blocked"]),
        P("drying_nozzles", value=[5]), P("max_frames", value=4)]))
    assert sim.profile == prof
    probe = ros.node("probe", namespace="/head_09")
    frames = collect(ros, probe, TRACE_MSG_TYPE, topics.TRACES, TRACES_QOS, decode_traces)
    ros.spin_until(lambda: len(frames) >= 2, 10, "two frames")
    f = frames[-1]
    assert f.traces.shape == (12, n) and f.sample_rate_hz == fs and (fs, n) != (10e6, 512)
    healthy = f.traces[[i for i in range(12) if i not in (2, 5)]]
    x = healthy - healthy.mean(axis=1, keepdims=True)
    n_fft = 16 * n
    peak_hz = (np.argmax(np.abs(np.fft.rfft(x, n=n_fft, axis=1))[:, 1:], axis=1) + 1) / n_fft * fs
    f0, _ = prof.healthy_mode()
    assert abs(np.median(peak_hz) / f0 - 1) < 0.03, (np.median(peak_hz), f0)
    assert abs(f0 / 237.15e3 - 1) > 0.1  # not the default head's mode


@pytest.mark.parametrize("case", ["missing file", "not yaml", "other schema", "nominal profile", "bad unit"])
def test_printhead_sim_refuses_a_bad_head_profile_in_one_line(ros, tmp_path, case):
    import os
    import subprocess
    import sys

    from inkdiag_core import HeadProfile

    path = tmp_path / "head.yaml"
    text = HeadProfile.default().dumps()
    if case == "not yaml":
        path.write_text("schema: [unclosed\n")
    elif case == "other schema":
        path.write_text(text.replace("inkdiag.head_profile", "someone.else"))
    elif case == "nominal profile":
        HeadProfile.default().replace(channel={"r_r": None, "L_r": None, "B_act": None, "b": None}).save(path)
    elif case == "bad unit":
        path.write_text(text.replace("rho: 1000.0", "rho: -1000.0"))
    match = {"missing file": "no such head profile file", "not yaml": "not valid YAML",
             "other schema": "schema is 'someone.else'", "nominal profile": "is nominal",
             "bad unit": "channel.rho: expected a positive number in kg/m^3"}[case]
    env = dict(os.environ, ROS_DOMAIN_ID=str(ros.domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    out = subprocess.run([sys.executable, "-m", "inkdiag_ros.printhead_sim", "--ros-args", "-p",
                          f"head_profile:={path}"], env=env, capture_output=True, text=True, timeout=60)
    assert out.returncode == 2, out.stderr[-2000:]
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("printhead_sim: ") and match in lines[0], out.stderr[-2000:]


def test_an_empty_list_on_the_command_line_is_an_empty_list(ros):
    """`-p drying_nozzles:=[]` (rclpy cannot type an empty list and leaves the parameter uninitialised): no drying
    nozzle, no fixed fault; a 12-nozzle head then runs (with the defaults its nozzle ids were out of range)."""
    import os
    import subprocess
    import sys

    env = dict(os.environ, ROS_DOMAIN_ID=str(ros.domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    out = subprocess.run([sys.executable, "-m", "inkdiag_ros.printhead_sim", "--ros-args", "-p", "n_nozzles:=12",
                          "-p", "drying_nozzles:=[]", "-p", "fault_nozzles:=[]", "-p", "fault_classes:=[]",
                          "-p", "max_frames:=1", "-p", "frame_rate_hz:=20.0"],
                         env=env, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "faults {}, drying []" in out.stderr and "published 1 frames" in out.stderr
