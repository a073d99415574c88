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
    sim = ros.add(PrintheadSim(context=ros.context))
    res = sim.set_parameters([P("n_nozzles", value=8)])[0]
    assert not res.successful and "fixed at start" in res.reason
    res = sim.set_parameters([P("frame_rate_hz", value=1e6)])[0]  # outside the descriptor's range
    assert not res.successful
