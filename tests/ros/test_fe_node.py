"""The fe node alone, real rclpy on a per-test Context, against test publishers/subscribers."""

import numpy as np
import pytest
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
    assert not res.successful and "read-only" in res.reason and fe.tracker.max_pending == 128
    # what `ros2 param describe` shows: the one runtime parameter writable, the others read-only
    assert [d.read_only for d in fe.describe_parameters(["max_estimates_per_frame", "max_pending"])] == [False, True]
    res = fe.set_parameters([P("max_estimates_per_frame", value=0)])[0]  # outside its range
    assert not res.successful and fe.tracker.max_estimates == 1


def test_fe_counts_hostile_messages_malformed_and_stays_up(ros):
    """A drying list with a huge nozzle id or stamp, or a trace message too short to estimate,
    is a malformed message for fe: counted and logged, never a crash of the node."""
    from std_msgs.msg import String

    from inkdiag_ros.fe_node import FeNode

    from msg_defs import DIAGNOSTICS_MSG_TYPE, DIAGNOSTICS_QOS, diagnostics_values

    fe = ros.add(FeNode(context=ros.context, namespace="/h", parameter_overrides=[P("diagnostics_period_s",
                                                                                   value=0.2)]))
    probe = ros.node("probe", namespace="/h")
    diag = collect(ros, probe, DIAGNOSTICS_MSG_TYPE, "/diagnostics", DIAGNOSTICS_QOS, diagnostics_values)
    ros.spin_until(lambda: diag, 10, "fe's /diagnostics")
    assert diag[-1]["inkdiag fe: /h"]["level"] == "stale"  # nothing received yet
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
    # said on /diagnostics (helper-113: fe published none, and its logs are throttled): WARN, counted, the reason
    n = len(diag)  # a STALE one may still be on its way: the first WARN after the calls
    ros.spin_until(lambda: any(d["inkdiag fe: /h"]["level"] == "warn" for d in diag[n:]), 10, "fe's WARN")
    st = next(d["inkdiag fe: /h"] for d in diag[n:] if d["inkdiag fe: /h"]["level"] == "warn")
    assert "3 malformed message(s)" in st["message"], st
    assert st["frames_malformed"] == "3" and int(st["drying_received"]) >= 1 and "trace frame" in st["last_error"], st
    n = len(diag)
    ros.spin_until(lambda: len(diag) > n, 10, "a quiet period")
    assert diag[-1]["inkdiag fe: /h"]["level"] == "stale" and diag[-1]["inkdiag fe: /h"]["frames_malformed"] == "3"


def _foreign_profile(path):
    """A 20 MHz x 1024 head of other geometry, with vp_cal constants in its file (no fit at start)."""
    from inkdiag_core import HeadProfile
    from inkdiag_core.estimation import VP_CAL

    p = HeadProfile.default().replace(
        name="foreign20", sample_rate_hz=20e6, n_samples=1024,
        channel={"rho": 1100.0, "mu": 6e-3, "r_n": 11e-6, "L_n": 45e-6, "V_ch": 8e-12, "c": 1300.0, "L_r": 250e-6})
    cal = {k: VP_CAL[k] * 1.5 for k in ("a_sigma", "b_sigma", "a_omega", "b_omega")}
    p = p.replace(calibration={"vp_cal": {**cal, "profile_sha256": p.sha256}})
    p.save(path)
    return p


def test_fe_head_profile_gives_model_constants_and_sampling(ros, tmp_path):
    """With head_profile, fe estimates on that head (its model, vp_cal constants, deeply-dried level)
    and counts a trace frame of another sampling malformed."""
    from std_msgs.msg import String

    from inkdiag_core import DryingTracker
    from inkdiag_core.trend import deeply_dried_fm
    from inkdiag_ros.fe_node import FeNode

    p = _foreign_profile(tmp_path / "head.yaml")
    fe = ros.add(FeNode(context=ros.context, namespace="/h",
                        parameter_overrides=[P("head_profile", value=str(tmp_path / "head.yaml"))]))
    assert fe.tracker.profile == p and fe.tracker.vp_cal["a_sigma"] == 1.5 * 8.80346
    assert fe.tracker.trends.fm_deep == deeply_dried_fm(p.channel_params())
    drying = '{"schema":"inkdiag.drying_nozzles","schema_version":1,"frame_id":%d,"stamp":1.0,' \
             '"nozzles":[1],"classes":["deeply_dried"]}'
    fe._on_drying(String(data=drying % 1))
    fe._on_traces(encode_traces(simulate({FaultClass.DEEPLY_DRIED: 2}, seed=1).traces, first_nozzle=0, frame_id=1,
                                stamp=2.0))  # 10 MHz x 512: another head's sampling
    assert fe.frames_malformed == 1 and fe.tracker.estimates == 0
    r = p.simulate({FaultClass.DEEPLY_DRIED: 2}, seed=2)
    fe._on_drying(String(data=drying % 2))
    fe._on_traces(encode_traces(r.traces, first_nozzle=0, frame_id=2, stamp=2.0, sample_rate_hz=20e6))
    assert fe.frames_malformed == 1 and fe.tracker.estimates == 1 and fe.estimates_published == 1
    ref = DryingTracker(profile=p).estimate_rows(r.traces[1:], [1], stamp=2.0, sample_rate_hz=20e6)
    assert fe.tracker.trends.x[0, 0] == ref.columns["fm_trend"][0]


def test_fe_refuses_a_bad_or_nominal_head_profile_at_start(ros, tmp_path):
    from inkdiag_ros.fe_node import FeNode

    p = _foreign_profile(tmp_path / "head.yaml")
    p.replace(channel={"r_r": None}).save(tmp_path / "nominal.yaml")
    for path, message in ((tmp_path / "missing.yaml", "no such head profile"),
                          (tmp_path / "nominal.yaml", "inkdiag calibrate")):
        with pytest.raises(ValueError, match=message):
            FeNode(context=ros.context, namespace="/h", parameter_overrides=[P("head_profile", value=str(path))])


def test_fe_node_exits_2_on_a_bad_head_profile(tmp_path):
    import os
    import subprocess
    import sys

    env = dict(os.environ)
    res = subprocess.run([sys.executable, "-m", "inkdiag_ros.fe_node", "--ros-args", "-p",
                          f"head_profile:={tmp_path / 'missing.yaml'}"], capture_output=True, text=True,
                         timeout=60, env=env)
    assert res.returncode == 2 and "no such head profile" in res.stderr, res.stderr


WARM_CHECK = """
import rclpy
from inkdiag_core import _kernels
from inkdiag_ros.fe_node import FeNode
assert not _kernels._screen_sums.signatures
rclpy.init()
fe = FeNode()
assert _kernels._screen_sums.signatures, "screening's kernel not loaded at start"
t = fe.tracker
assert (t.estimates, t.rows_invalid, t.traces_received, len(t.trends)) == (0, 0, 0, 0), "warm-up changed the state"
assert t.warm_up() == 2, "the estimator did not run on the warm-up's rows"
fe.destroy_node()
rclpy.shutdown()
print("ok")
"""


def test_fe_loads_its_kernels_at_start_not_on_the_first_frames():
    """helper-127: fe's first estimates took 0.5-0.6 s (numba's import and cache), and at 33 frames/s a burst behind
    them overflowed its queues: frames 0-8 had no estimates. A fresh fe process now loads them while it starts,
    and the warm-up leaves the tracker's state as it was."""
    import os
    import subprocess
    import sys

    res = subprocess.run([sys.executable, "-c", WARM_CHECK], capture_output=True, text=True, timeout=120,
                         env=dict(os.environ))
    assert res.returncode == 0 and res.stdout.strip().endswith("ok"), res.stderr


def test_fe_folds_a_repeated_frame_once_and_restarts_its_trends_on_a_restarted_clock(ros):
    """A controller that sends a frame twice, then restarts its clock: the repeat's estimate has no trend; the
    frame on the new clock restarts the trend (no rate yet) and fe notes the restart once."""
    from inkdiag_ros.fe_node import FeNode

    fe = ros.add(FeNode(context=ros.context, namespace="/h"))
    probe = ros.node("probe", namespace="/h")
    tpub = probe.create_publisher(TRACE_MSG_TYPE, topics.TRACES, TRACES_QOS)
    dpub = probe.create_publisher(DRYING_MSG_TYPE, topics.DRYING_NOZZLES, RELIABLE_QOS)
    est = collect(ros, probe, ESTIMATES_MSG_TYPE, topics.FM_ESTIMATES, RELIABLE_QOS, decode_estimates)
    ros.spin_until(lambda: tpub.get_subscription_count() and dpub.get_subscription_count(), 10, "fe")
    r = simulate({FaultClass.DEEPLY_DRIED: 2}, seed=4)
    for k, (fid, stamp) in enumerate([(1, 100.0), (2, 100.5), (2, 100.5), (3, 1.0)]):
        dpub.publish(encode_drying(DryingNozzles(fid, stamp, (0, 1), ("deeply_dried",) * 2, 0, 2)))
        ros.spin_until(lambda: fe.tracker.drying_received > k, 5, "the drying list")
        msg = encode_traces(r.traces, first_nozzle=0, frame_id=fid, stamp=stamp)
        while len(est) <= k:  # best effort: again until it is estimated
            tpub.publish(msg)
            ros.spin_for(0.1)
    trend = [e.column("fm_trend") for e in est]
    rate = [e.column("fm_rate") for e in est]
    assert np.isfinite(trend[1]).all() and np.isfinite(rate[1]).all()  # the second frame: a rate
    assert np.isnan(trend[2]).all() and fe.tracker.rows_stale == 2  # frame 2 again: not folded twice
    assert np.isfinite(trend[3]).all() and np.isnan(rate[3]).all()  # the new clock: restarted
    assert fe.tracker.trend_restarts == 2 and fe.tracker.trends.epoch == 1 and fe._clocks_said == 1
