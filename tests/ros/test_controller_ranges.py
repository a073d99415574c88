"""A printer controller that sends each frame of a head as several nozzle ranges (issue 12).

Real fdi and fe nodes (real rclpy, Fast DDS), a head of 600 nozzles published
as three 200-nozzle trace messages per frame: every nozzle that fdi labels
dried, in any range, gets an estimate for that same frame, from its first
dried frame on, and no longer once it recovered.
"""

import numpy as np
import pytest
from rclpy.parameter import Parameter

from inkdiag_core import FaultClass, simulate_nozzles
from msg_defs import (
    DRYING_MSG_TYPE,
    ESTIMATES_MSG_TYPE,
    RELIABLE_QOS,
    TRACE_MSG_TYPE,
    TRACES_QOS,
    decode_drying,
    decode_estimates,
    encode_traces,
    topics,
)

P = Parameter
N, RANGE = 600, 200
# dried nozzles per frame: frame 0 healthy; nozzles dry in each range from frame 1 or 2 on;
# 30 and 460 recover in frame 3
DRIED = {0: [], 1: [30, 150, 230, 380, 460, 590], 2: [30, 90, 150, 230, 310, 380, 460, 520, 590],
         3: [90, 150, 230, 310, 380, 520, 590]}


def _frames():
    out = {}
    for f, dried in DRIED.items():
        classes = np.array([FaultClass.HEALTHY_NOZZLE.value] * N, dtype=object)
        classes[dried] = FaultClass.DEEPLY_DRIED.value
        out[f] = simulate_nozzles(classes, seed=12, frame_seed=100 + f).traces
    return out


def test_every_range_of_a_frame_is_estimated_with_that_frames_drying_list(ros, fdi_model):
    from inkdiag_ros.fdi_node import FdiNode
    from inkdiag_ros.fe_node import FeNode

    kw = {"context": ros.context, "namespace": "/h"}
    fdi = ros.add(FdiNode(parameter_overrides=[P("model_path", value=str(fdi_model)),
                                               P("n_nozzles", value=N)], **kw))
    fe = ros.add(FeNode(**kw))
    probe = ros.node("controller", namespace="/h")
    pub = probe.create_publisher(TRACE_MSG_TYPE, topics.TRACES, TRACES_QOS)
    drying, est = [], []
    probe.create_subscription(DRYING_MSG_TYPE, topics.DRYING_NOZZLES, lambda m: drying.append(decode_drying(m)),
                              RELIABLE_QOS)
    probe.create_subscription(ESTIMATES_MSG_TYPE, topics.FM_ESTIMATES,
                              lambda m: est.append(decode_estimates(m)), RELIABLE_QOS)
    ros.spin_until(lambda: pub.get_subscription_count() >= 2, 10, "fdi's and fe's subscriptions")
    frames = _frames()
    for f, x in frames.items():
        for first in range(0, N, RANGE):
            msg = encode_traces(x[first:first + RANGE], first_nozzle=first, frame_id=f, stamp=100.0 + 0.1 * f)
            got = (fdi.stats.frames_received, fe.tracker.traces_received)
            for _ in range(20):  # best effort: resend until both nodes have it
                pub.publish(msg)
                try:
                    ros.spin_until(lambda: fdi.stats.frames_received > got[0]
                                   and fe.tracker.traces_received > got[1], 0.5, "the trace message")
                    break
                except pytest.fail.Exception:
                    continue
    keys = {(f, first) for f in frames for first in range(0, N, RANGE)}
    ros.spin_until(lambda: {(d.frame_id, d.first_nozzle) for d in drying} >= keys
                   and fe.tracker.drying_received >= len(keys), 30, "every range's drying list")
    ros.spin_for(0.3)  # the last estimates

    assert all(d.n_nozzles == RANGE for d in drying)
    labelled = {(d.frame_id, d.first_nozzle): set(d.nozzles) for d in drying}
    estimated = {}
    for e in est:
        estimated.setdefault((e.frame_id, e.first_nozzle), set()).update(e.nozzles.tolist())
    # every range of every frame: estimated exactly the nozzles fdi labelled dried there
    assert estimated == {k: v for k, v in labelled.items() if v}
    # and the case is not empty: each range has dried nozzles that fdi found
    for first in range(0, N, RANGE):
        assert any(labelled[(f, first)] for f in (1, 2, 3)), first
    found = set().union(*labelled.values())
    truly = set().union(*map(set, DRIED.values()))
    assert len(found & truly) >= 0.8 * len(truly)
    # a nozzle is estimated in the first frame it is labelled dried, and not in the frame it recovered
    for nz in found:
        dried_in = [f for f in frames if nz in labelled[(f, nz // RANGE * RANGE)]]
        est_in = [f for f in frames if nz in estimated.get((f, nz // RANGE * RANGE), ())]
        assert est_in == dried_in, nz
    assert fe.tracker.traces_unmatched == 0
