"""Each node alone, real rclpy on a per-test Context, against test publishers/subscribers."""

import shutil

import numpy as np
import pytest
from rclpy.parameter import Parameter
from std_msgs.msg import Float32MultiArray

from inkdiag_core import FaultClass, simulate
from msg_defs import (
    DIAGNOSTICS_MSG_TYPE,
    DIAGNOSTICS_QOS,
    DRYING_MSG_TYPE,
    ESTIMATES_ARRAY_MSG_TYPE,
    ESTIMATES_MSG_TYPE,
    LABELS_MSG_TYPE,
    RELIABLE_QOS,
    TRACE_MSG_TYPE,
    TRACES_QOS,
    TRUTH_MSG_TYPE,
    DryingNozzles,
    decode_drying,
    decode_estimates,
    decode_estimates_array,
    decode_labels,
    decode_traces,
    decode_truth,
    diagnostics_values,
    encode_drying,
    encode_traces,
    topics,
)

P = Parameter


def _collect(ros, node, msg_type, topic, qos, decode=lambda m: m):
    got = []
    node.create_subscription(msg_type, topic, lambda m: got.append(decode(m)), qos)
    return got


def test_printhead_sim_publishes_frames_and_truth(ros):
    from inkdiag_ros.printhead_sim import PrintheadSim

    sim = ros.add(PrintheadSim(context=ros.context, namespace="/head_03", parameter_overrides=[
        P("n_nozzles", value=16), P("first_nozzle", value=100), P("frame_rate_hz", value=50.0),
        P("fault_nozzles", value=[102]), P("fault_classes", value=["fully_blocked"]),
        P("drying_nozzles", value=[105]), P("drying_duration_s", value=0.1), P("max_frames", value=12)]))
    probe = ros.node("probe", namespace="/head_03")
    frames = _collect(ros, probe, TRACE_MSG_TYPE, topics.TRACES, TRACES_QOS, decode_traces)
    truth = _collect(ros, probe, TRUTH_MSG_TYPE, topics.GROUND_TRUTH, RELIABLE_QOS, decode_truth)
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


def _frames_of(classes_counts, seed=0, n_samples=512):
    r = simulate(classes_counts, seed=seed, n_samples=n_samples)
    return r.traces, r.label_values()


class _Rig:
    """fdi node + a trace publisher + subscribers on labels, drying nozzles and diagnostics."""

    def __init__(self, ros, model_path, **over):
        from inkdiag_ros.fdi_node import FdiNode

        params = {"model_path": str(model_path), "n_nozzles": 64, "diagnostics_period_s": 0.2, **over}
        self.ros = ros
        self.fdi = ros.add(FdiNode(context=ros.context, namespace="/h",
                                   parameter_overrides=[P(k, value=v) for k, v in params.items()]))
        probe = ros.node("probe", namespace="/h")
        self.pub = probe.create_publisher(TRACE_MSG_TYPE, topics.TRACES, TRACES_QOS)
        self.labels = _collect(ros, probe, LABELS_MSG_TYPE, topics.LABELS, RELIABLE_QOS, decode_labels)
        self.drying = _collect(ros, probe, DRYING_MSG_TYPE, topics.DRYING_NOZZLES, RELIABLE_QOS,
                               decode_drying)
        self.diag = _collect(ros, probe, DIAGNOSTICS_MSG_TYPE, topics.DIAGNOSTICS, DIAGNOSTICS_QOS,
                             diagnostics_values)
        ros.spin_until(lambda: self.pub.get_subscription_count() > 0, 10, "fdi's subscription")

    def send(self, msg, expect_labels: bool):
        """Publish one frame and wait until the fdi node has counted it."""
        before, n_labels = self.fdi.stats.frames_received, len(self.labels)
        for _ in range(20):  # best effort: resend until it was received
            self.pub.publish(msg)
            try:
                self.ros.spin_until(lambda: self.fdi.stats.frames_received > before, 0.5, "frame")
                break
            except pytest.fail.Exception:
                continue
        if expect_labels:
            # A generous bound: a labelling process that must start anew (spawn, imports,
            # the model) takes seconds on a contended 2-core machine.
            self.ros.spin_until(lambda: len(self.labels) > n_labels, 30, "labels")


IN_CHILD = pytest.mark.parametrize("in_child", [False, True], ids=["thread", "labelling_process"])


@IN_CHILD
def test_fdi_labels_injected_faults_and_publishes_drying_and_diagnostics(ros, fdi_model, in_child):
    traces, truth = _frames_of({FaultClass.HEALTHY_NOZZLE: 20, FaultClass.FULLY_BLOCKED: 4,
                                FaultClass.EMPTY_CHANNEL_1: 4, FaultClass.DEEPLY_DRIED: 4})
    rig = _Rig(ros, fdi_model, labelling_process=in_child)
    assert (type(rig.fdi._pipeline.backend).__name__ == "ProcessBackend") == in_child
    rig.send(encode_traces(traces, first_nozzle=10, frame_id=5, stamp=100.25), expect_labels=True)
    rep = rig.labels[-1]
    assert (rep.frame_id, rep.stamp, rep.first_nozzle, rep.n_nozzles) == (5, 100.25, 10, 32)
    assert rep.model_id.startswith("fdi-rf-kpi_y-") and sum(rep.counts.values()) == 32
    got = dict((nz, c) for nz, c, _ in rep.faults)
    true = {10 + i: c for i, c in enumerate(truth) if c not in ("healthy_nozzle", "ok_signal")}
    agree = sum(got.get(nz) == c for nz, c in true.items())
    assert agree >= 10, (got, true)  # 12 injected faults, a small model
    ros.spin_until(lambda: rig.drying, 5, "drying nozzles")
    assert set(rig.drying[-1].nozzles) == {nz for nz, c in got.items() if c.endswith("_dried")}
    ros.spin_until(lambda: rig.diag and rig.diag[-1]["inkdiag fdi: /h"]["frames_labelled"] == "1",
                   5, "diagnostics")
    d = rig.diag[-1]["inkdiag fdi: /h"]
    assert d["model_id"] == rep.model_id and d["count.fully_blocked"].isdigit()


def _malformed(traces):
    def mut(fn):
        m = encode_traces(traces)
        fn(m)
        return m

    one_dim = mut(lambda m: m.layout.dim.pop())
    empty = Float32MultiArray()
    short = encode_traces(traces[:, :256])
    out_of_range = encode_traces(traces, first_nozzle=60)  # rows 60..91 on a 64-nozzle head
    wrong_data = mut(lambda m: setattr(m, "data", m.data[:-1]))
    return {"wrong dims": one_dim, "empty": empty, "wrong sample count": short,
            "nozzle range out of bounds": out_of_range, "data length": wrong_data}


@IN_CHILD
def test_fdi_survives_bad_frames_and_the_counts_add_up(ros, fdi_model, in_child):
    traces, _ = _frames_of({FaultClass.HEALTHY_NOZZLE: 32}, seed=3)
    rig = _Rig(ros, fdi_model, labelling_process=in_child)
    bad = _malformed(traces)
    for name, msg in bad.items():
        rig.send(msg, expect_labels=False)
    s = rig.fdi.stats
    assert s.frames_malformed == len(bad) and s.frames_labelled == 0
    assert "out of bounds" in s.last_error or "expected" in s.last_error
    # NaN rows, a flat row and a clipped row: labelled invalid with reasons, the rest classified
    x = np.array(traces)
    x[1, 7] = np.nan
    x[2, :] = np.inf
    x[3, :] = 0.25
    x[4, 100:110] = x[4].max()
    rig.send(encode_traces(x, frame_id=9), expect_labels=True)
    rep = rig.labels[-1]
    assert dict(rep.invalid) == {1: "non_finite", 2: "non_finite", 3: "flat", 4: "clipped"}
    assert rep.counts["invalid"] == 4 and sum(rep.counts.values()) == 32
    rig.send(encode_traces(traces, frame_id=10), expect_labels=True)  # still alive
    assert s.frames_received == s.frames_malformed + s.frames_labelled == len(bad) + 2
    assert s.rows_invalid == 4
    ros.spin_until(lambda: rig.diag and rig.diag[-1]["inkdiag fdi: /h"]["frames_malformed"]
                   == str(len(bad)), 5, "diagnostics with the malformed count")


@IN_CHILD
def test_fdi_under_a_burst_labels_every_frame_in_order_or_counts_it_dropped(ros, fdi_model, in_child):
    traces, _ = _frames_of({FaultClass.HEALTHY_NOZZLE: 24, FaultClass.FULLY_BLOCKED: 8}, seed=4)
    rig = _Rig(ros, fdi_model, max_queued_frames=2, labelling_process=in_child)
    msgs = [encode_traces(traces, frame_id=100 + i) for i in range(4)]
    for m in msgs:  # four frames at once: the worker batches what queued while it was busy
        rig.pub.publish(m)
    s = rig.fdi.stats
    ros.spin_until(lambda: s.frames_received >= 2 and rig.fdi.wait_idle(0.01)
                   and len(rig.labels) == s.frames_labelled, 10, "the burst labelled")
    ros.spin_for(0.3)
    assert s.frames_received == s.frames_labelled + s.frames_dropped
    ids = [r.frame_id for r in rig.labels]
    assert ids == sorted(ids) and set(ids) <= {100, 101, 102, 103} and len(ids) == s.frames_labelled
    assert all(sum(r.counts.values()) == 32 and r.counts.get("fully_blocked", 0) >= 6
               for r in rig.labels)


def test_fdi_counts_the_frames_its_killed_labelling_process_had_and_labels_on(ros, fdi_model):
    import os
    import signal

    traces, _ = _frames_of({FaultClass.HEALTHY_NOZZLE: 24, FaultClass.FULLY_BLOCKED: 8}, seed=5)
    rig = _Rig(ros, fdi_model, labelling_process=True)
    rig.send(encode_traces(traces, frame_id=1), expect_labels=True)
    first = rig.fdi._pipeline.backend.pid
    os.kill(first, signal.SIGKILL)
    s = rig.fdi.stats
    rig.send(encode_traces(traces, frame_id=2), expect_labels=False)
    ros.spin_until(lambda: rig.fdi.wait_idle(0.01) and s.frames_failed + s.frames_labelled == 2,
                   15, "frame 2 failed or labelled")
    rig.send(encode_traces(traces, frame_id=3), expect_labels=True)
    ros.spin_until(lambda: rig.fdi.wait_idle(0.01), 15, "idle")
    assert s.frames_failed == 1 and "labelling process exited" in s.last_error
    assert [r.frame_id for r in rig.labels] == [1, 3] and rig.fdi._pipeline.backend.pid not in (None, first)
    assert s.frames_received == s.frames_labelled + s.frames_failed == 3


def test_fdi_labels_on_a_thread_when_no_labelling_process_can_start(ros, fdi_model):
    traces, _ = _frames_of({FaultClass.HEALTHY_NOZZLE: 24, FaultClass.FULLY_BLOCKED: 8}, seed=6)
    rig = _Rig(ros, fdi_model, labelling_process=True)
    rig.fdi._pipeline.backend._process._fatal = "its imports failed"  # as after a child that died before it was ready
    rig.send(encode_traces(traces, frame_id=1), expect_labels=True)
    rig.send(encode_traces(traces, frame_id=2), expect_labels=True)
    s = rig.fdi.stats
    assert s.frames_labelled == 2 and s.frames_failed == 0 and "cannot start" in s.config_error
    assert rig.labels[-1].counts.get("fully_blocked", 0) >= 6


def test_fdi_refuses_a_tampered_model(ros, fdi_model, tmp_path):
    bad = tmp_path / "m.joblib"
    shutil.copy(fdi_model, bad)
    shutil.copy(str(fdi_model) + ".manifest.json", str(bad) + ".manifest.json")
    with open(bad, "ab") as f:
        f.write(b"\0")
    traces, _ = _frames_of({FaultClass.HEALTHY_NOZZLE: 8})
    rig = _Rig(ros, bad)
    assert rig.fdi.labeller is None
    rig.send(encode_traces(traces), expect_labels=False)
    ros.spin_until(lambda: rig.diag, 5, "diagnostics")
    d = rig.diag[-1]["inkdiag fdi: /h"]
    assert d["level"] == "error" and d["model_id"] == "none" and not rig.labels


def test_fe_estimates_only_the_drying_nozzles(ros):
    from inkdiag_ros.fe_node import FeNode

    fe = ros.add(FeNode(context=ros.context, namespace="/h"))
    probe = ros.node("probe", namespace="/h")
    tpub = probe.create_publisher(TRACE_MSG_TYPE, topics.TRACES, TRACES_QOS)
    dpub = probe.create_publisher(DRYING_MSG_TYPE, topics.DRYING_NOZZLES, RELIABLE_QOS)
    est = _collect(ros, probe, ESTIMATES_MSG_TYPE, topics.FM_ESTIMATES, RELIABLE_QOS, decode_estimates)
    arr = _collect(ros, probe, ESTIMATES_ARRAY_MSG_TYPE, topics.FM_ESTIMATES_ARRAY, RELIABLE_QOS,
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
    assert not res.successful and "fixed at start" in res.reason and fe.tracker.max_pending == 32
    res = fe.set_parameters([P("max_estimates_per_frame", value=0)])[0]  # outside its range
    assert not res.successful and fe.tracker.max_estimates == 1
