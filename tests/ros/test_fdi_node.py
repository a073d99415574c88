"""The fdi node alone, real rclpy on a per-test Context: one FaultDetector model file, a failed batch
counts every frame; labels, drying nozzles and diagnostics against test publishers/subscribers."""

import shutil
import time

import numpy as np
import pytest
from rclpy.parameter import Parameter as P
from std_msgs.msg import Float32MultiArray

from _helpers import collect
from inkdiag_core import FaultClass, simulate
from msg_defs import (
    DIAGNOSTICS_MSG_TYPE,
    DIAGNOSTICS_QOS,
    DRYING_MSG_TYPE,
    LABELS_MSG_TYPE,
    RELIABLE_QOS,
    TRACE_MSG_TYPE,
    TRACES_QOS,
    decode_drying,
    decode_labels,
    diagnostics_values,
    encode_traces,
    topics,
)


def _fdi(ros, model_path, **over):
    from inkdiag_ros.fdi_node import FdiNode

    params = {"model_path": str(model_path), "diagnostics_period_s": 0.2, **over}
    return ros.add(FdiNode(context=ros.context, namespace="/h",
                           parameter_overrides=[P(k, value=v) for k, v in params.items()]))


def test_a_failed_batch_counts_every_frame_it_held(ros, fdi_model, monkeypatch):
    import inkdiag_core

    calls = []

    def fail(self, frames, *args, **kwargs):
        calls.append(len(frames))
        raise RuntimeError("unexpected labelling error")

    monkeypatch.setattr(inkdiag_core.FrameLabeller, "screen", fail)  # the first stage of each pass
    fdi = _fdi(ros, fdi_model)
    x = simulate({FaultClass.HEALTHY_NOZZLE: 4}, seed=1).traces.astype(np.float32)
    for k in range(5):  # taken in one executor wake-up: labelled together when the callback flushes
        fdi._on_trace_msg(encode_traces(x, first_nozzle=0, frame_id=k))
    fdi._on_traces(encode_traces(x, first_nozzle=0, frame_id=5))
    assert fdi.wait_idle(10)
    s = fdi.stats
    assert calls == [6]  # one labelling pass for the six frames
    assert s.frames_failed == 6 and s.frames_labelled == 0, (s.frames_failed, calls)
    assert "unexpected labelling error" in s.last_error


def test_fdi_publishes_diagnostics_from_its_trace_callback_when_the_timer_cannot_run(ros, fdi_model):
    """Under load the executor runs trace callbacks back to back (fdi labels in them) and the diagnostics
    timer waits behind them: the callback itself publishes /diagnostics once a period has passed."""
    fdi = _fdi(ros, fdi_model)  # diagnostics_period_s 0.2
    x = simulate({FaultClass.HEALTHY_NOZZLE: 4}, seed=1).traces.astype(np.float32)
    published, publish = [], fdi._diag_pub.publish
    fdi._diag_pub.publish = lambda msg: published.append(time.monotonic()) or publish(msg)
    t0, k = time.monotonic(), 0
    while time.monotonic() - t0 < 0.9:  # never spun: only the trace callback can publish
        fdi._on_traces(encode_traces(x, first_nozzle=0, frame_id=k))
        k += 1
        time.sleep(0.01)
    assert fdi.stats.frames_labelled == k
    assert 3 <= len(published) <= 5 and all(b - a >= 0.19 for a, b in zip(published, published[1:])), published


def test_a_model_file_that_is_not_a_fault_detector_is_refused(ros, tmp_path):
    from inkdiag_core.fdi import train_default_model

    old = tmp_path / "old_pipeline.joblib"
    train_default_model(old, n_per_class=30, features="kpi_y+baseline")  # a plain pipeline file (save_model)
    fdi = _fdi(ros, old)
    assert fdi.labeller is None and fdi.model_id == "none"


def test_baseline_model_path_is_gone(ros, fdi_baseline_model):
    fdi = _fdi(ros, fdi_baseline_model)
    assert not fdi.has_parameter("baseline_model_path") and fdi.has_parameter("baseline_path")
    assert fdi.model_id.startswith("fdi-rf-kpi_y+baseline-") and not fdi.labeller.uses_baselines


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
        self.labels = collect(ros, probe, LABELS_MSG_TYPE, topics.LABELS, RELIABLE_QOS, decode_labels)
        self.drying = collect(ros, probe, DRYING_MSG_TYPE, topics.DRYING_NOZZLES, RELIABLE_QOS,
                               decode_drying)
        self.diag = collect(ros, probe, DIAGNOSTICS_MSG_TYPE, topics.DIAGNOSTICS, DIAGNOSTICS_QOS,
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
    # bytes of no CDR encapsulation, published serialized: rclpy's deserialiser raised and ended the node (helper-140)
    noise = b"\xb8\x83" + np.random.default_rng(5).bytes(2000)
    return {"wrong dims": one_dim, "empty": empty, "wrong sample count": short,
            "nozzle range out of bounds": out_of_range, "data length": wrong_data, "not CDR": noise}


@IN_CHILD
def test_fdi_survives_bad_frames_and_the_counts_add_up(ros, fdi_model, in_child):
    traces, _ = _frames_of({FaultClass.HEALTHY_NOZZLE: 32}, seed=3)
    rig = _Rig(ros, fdi_model, labelling_process=in_child)
    bad = _malformed(traces)
    for name, msg in bad.items():
        rig.send(msg, expect_labels=False)
    s = rig.fdi.stats
    assert s.frames_malformed == len(bad) and s.frames_labelled == 0
    assert s.last_error.startswith("not a serialised std_msgs/msg/Float32MultiArray (its first bytes b883")  # the last
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
    # and why, for an operator who sees /diagnostics only (not the node's log)
    assert d["config_error"].startswith("FDI model not loaded: ") and "tampered" in d["config_error"]
    assert d["message"] == d["config_error"] + ": frames are not labelled"


def test_fdi_labels_a_trace_unlike_every_class_unknown_and_counts_it(ros, tmp_path):
    # issue 16: a foreign-body trace comes back `unknown` in the labels JSON (a fault, with its
    # score) and is counted as count.unknown on /diagnostics
    from inkdiag_core import extract_kpis
    from inkdiag_core.fdi import train_default_model

    model = tmp_path / "open.joblib"
    train_default_model(model, n_per_class=320, seed=0)  # >= 230 calibration rows per class
    x = simulate({FaultClass.HEALTHY_NOZZLE: 8}, seed=31).traces.astype(np.float64)
    k = extract_kpis(x, 10e6)
    t = np.arange(x.shape[1]) / 10e6
    f = np.linspace(600e3, 1200e3, 8)[:, None]  # a lightly damped foreign-body mode, 30 % of the amplitude
    x += 0.3 * k[:, [3]] * np.exp(-0.01 * 2 * np.pi * f * t) * np.cos(2 * np.pi * f * t)
    rig = _Rig(ros, model, labelling_process=False)
    rig.send(encode_traces(x.astype(np.float32), first_nozzle=0, frame_id=1, stamp=1.0), expect_labels=True)
    rep = rig.labels[-1]
    unknown = [(nz, p) for nz, c, p in rep.faults if c == "unknown"]
    assert len(unknown) >= 7 and all(p >= 0.99 for _, p in unknown)
    assert rep.counts["unknown"] == len(unknown)
    ros.spin_until(lambda: rig.diag and rig.diag[-1]["inkdiag fdi: /h"]["frames_labelled"] == "1",
                   5, "diagnostics")
    assert rig.diag[-1]["inkdiag fdi: /h"]["count.unknown"] == str(len(unknown))


def test_diagnostics_counts_invalid_from_the_start():
    """``count.invalid`` (= ``rows_invalid``) is in /diagnostics before the first labelled frame too."""
    from inkdiag_ros.stats import FdiStats

    stats = FdiStats()
    assert stats.period(True)[3] == {"invalid": 0}
    stats.labelled({"healthy_nozzle": 3, "invalid": 1}, 4)
    counts = stats.period(True)[3]
    assert counts == {"healthy_nozzle": 3, "invalid": 1} and stats.rows_invalid == 1


def test_diagnostics_warn_when_the_healthy_gate_clears_few_healthy_rows():
    """helper-88: another head's baselines on /head_01 cleared 14 of 64 rows a frame and made a quarter of them faults
    or unknown, under the half that warns: /diagnostics said OK. On a head whose baselines are its own the gate clears
    about 99 % of its healthy rows; under half is a warning. Not without a gate, nor for rows without a baseline."""
    from inkdiag_ros.stats import FdiStats

    def run(gate, cleared, n_baseline=64, n=20):
        stats = FdiStats()
        stats.gate_in_use = gate
        stats.period(True)
        for _ in range(n):  # 64 rows a frame, 50 healthy
            stats.received()
            stats.labelled({"healthy_nozzle": 50, "unknown": 7, "deeply_dried": 7}, 64, n_baseline, cleared)
        return stats.period(True)[:2]

    assert run(True, 49)[0] == "ok"  # 49 of 50 cleared
    level, message = run(True, 14)
    assert level == "warn" and message.startswith("the healthy gate cleared 280 of the last 1000 healthy rows with a "
                                                  "baseline (about 99 % on a head whose baselines are its own)"), message
    assert run(False, 0)[0] == "ok"  # no gate (baselines without reference traces): nothing to judge
    assert run(True, 0, n_baseline=10)[0] == "ok"  # 10 rows with a baseline, 14 not healthy: none surely healthy
    assert run(True, 14, n=15)[0] == "ok"  # 750 rows: not judged yet


def test_diagnostics_warn_when_most_rows_are_faults():
    """Rows mostly faults or unknown (baselines of another head make every nozzle look unlike its own) are WARN,
    judged on the rows since the last judgement (a small head's over several periods) and held until the next;
    a working head's few faults are not; the warning joins the others of the period."""
    from inkdiag_ros.stats import FdiStats

    stats = FdiStats()
    stats.period(True)

    def frames(n, counts):
        for _ in range(n):
            stats.received()
            stats.labelled(counts, sum(counts.values()))

    frames(10, {"healthy_nozzle": 196, "deeply_dried": 2, "unknown": 2})  # 2,000 rows, 2 % faulty
    level, message, values, _, _ = stats.period(True)
    assert level == "ok" and values["rows_faulty"] == 40, message
    for k in range(4):  # a 64-nozzle head, all unknown: 320 rows a period, judged once 1,000 are in
        frames(5, {"unknown": 64})
        level, message = stats.period(True)[:2]
        assert (level == "warn") == (k >= 3), (k, message)
    assert message.startswith("100 % of the last 1280 rows were faults or unknown") and "baselines" in message
    frames(5, {"healthy_nozzle": 64})  # not judged yet: the warning holds
    assert stats.period(True)[0] == "warn"
    frames(1, {"unknown": 60, "invalid": 4})  # with invalid rows: both said
    message = stats.period(True)[1]
    assert "invalid row(s)" in message and "were faults or unknown" in message
    frames(20, {"healthy_nozzle": 64})  # judged again on healthy rows: OK
    assert stats.period(True)[0] == "ok"


def test_a_misspelt_parameter_is_named_with_the_one_meant(ros, fdi_model):
    """rclpy ignores a parameter the node does not declare: fdi says so, with the nearest name it has."""
    fdi = _fdi(ros, fdi_model, max_queue_frames=5, bogus_thing=1)
    assert fdi.ignored_parameters == ["bogus_thing", "max_queue_frames"]
    assert fdi.config["max_queued_frames"] == 64  # left at its default, hence the warning
    assert _fdi(ros, fdi_model).ignored_parameters == []
