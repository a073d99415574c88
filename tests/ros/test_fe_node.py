"""The fe node alone, real rclpy on a per-test Context, against test publishers/subscribers."""

import numpy as np
from rclpy.parameter import Parameter as P

from _helpers import collect
from inkdiag_core import FaultClass, simulate
from msg_defs import (
    DRYING_MSG_TYPE,
    ESTIMATES_ARRAY_MSG_TYPE,
    ESTIMATES_MSG_TYPE,
    RELIABLE_QOS,
    TRACE_MSG_TYPE,
    TRACES_QOS,
    DryingNozzles,
    decode_estimates,
    decode_estimates_array,
    encode_drying,
    encode_traces,
    topics,
)


def test_fe_estimates_only_the_drying_nozzles(ros):
    from inkdiag_ros.fe_node import FeNode

    fe = ros.add(FeNode(context=ros.context, namespace="/h"))
    probe = ros.node("probe", namespace="/h")
    tpub = probe.create_publisher(TRACE_MSG_TYPE, topics.TRACES, TRACES_QOS)
    dpub = probe.create_publisher(DRYING_MSG_TYPE, topics.DRYING_NOZZLES, RELIABLE_QOS)
    est = collect(ros, probe, ESTIMATES_MSG_TYPE, topics.FM_ESTIMATES, RELIABLE_QOS, decode_estimates)
    arr = collect(ros, probe, ESTIMATES_ARRAY_MSG_TYPE, topics.FM_ESTIMATES_ARRAY, RELIABLE_QOS,
                   decode_estimates_array)
    ros.spin_until(lambda: tpub.get_subscription_count() and dpub.get_subscription_count(), 10, "fe")
    r = simulate({FaultClass.HEALTHY_NOZZLE: 6, FaultClass.DEEPLY_DRIED: 2}, seed=4)
    # rows 6, 7 are deeply dried; nozzle ids 20..27 -> 26, 27
    # frame 1's list, its range unknown (as from an fdi that does not say it): it applies to the
    # rows of frame 1 that it lists
    dpub.publish(encode_drying(DryingNozzles(1, 1.0, (26, 27, 99), ("deeply_dried",) * 3)))
    ros.spin_until(lambda: fe.tracker.drying_received, 5, "the drying list")
    msg = encode_traces(r.traces, first_nozzle=20, frame_id=1, stamp=2.0)
    deadline_msgs = []
    while not est:
        tpub.publish(msg)
        ros.spin_for(0.1)
        deadline_msgs.append(1)
        assert len(deadline_msgs) < 50, "no estimate"
    ros.spin_until(lambda: arr, 5, "array form")
    e = est[0]
    assert e.nozzles.tolist() == [26, 27]  # 99 is not in this frame; healthy rows not estimated
    np.testing.assert_allclose(e.column("fm"), r.fm[6:], rtol=0.15)
    np.testing.assert_array_equal(arr[0].table, e.table)
    assert (e.column("viscosity") > 0.05).all() and (e.column("d_mu") > 0).all()
    # the cap changes at run time (the tracker uses it from the next pair on); the buffer bound does not
    assert fe.set_parameters([P("max_estimates_per_frame", value=1)])[0].successful
    assert fe.tracker.max_estimates == 1
    res = fe.set_parameters([P("max_pending", value=5)])[0]
    assert not res.successful and "fixed at start" in res.reason and fe.tracker.max_pending == 128
    res = fe.set_parameters([P("max_estimates_per_frame", value=0)])[0]  # outside its range
    assert not res.successful and fe.tracker.max_estimates == 1


def test_fe_counts_hostile_messages_malformed_and_stays_up(ros):
    """A drying list with a huge nozzle id or stamp, or a trace message too short to estimate,
    is a malformed message for fe: counted and logged, never a crash of the node."""
    from std_msgs.msg import String

    from inkdiag_ros.fe_node import FeNode

    fe = ros.add(FeNode(context=ros.context, namespace="/h"))
    bad_drying = [
        '{"schema":"inkdiag.drying_nozzles","schema_version":1,"frame_id":1,"stamp":1.0,'
        '"nozzles":[1180591620717411303424],"classes":["deeply_dried"]}',
        '{"schema":"inkdiag.drying_nozzles","schema_version":1,"frame_id":1,"stamp":1' + "0" * 400 + ','
        '"nozzles":[3],"classes":["deeply_dried"]}',
    ]
    for text in bad_drying:
        fe._on_drying(String(data=text))
    short = simulate({FaultClass.DEEPLY_DRIED: 2}, seed=1, n_samples=8).traces
    fe._on_drying(String(data='{"schema":"inkdiag.drying_nozzles","schema_version":1,"frame_id":2,'
                              '"stamp":1.0,"nozzles":[0],"classes":["deeply_dried"]}'))
    fe._on_traces(encode_traces(short, first_nozzle=0, frame_id=2, stamp=2.0))
    assert fe.frames_malformed == 3
