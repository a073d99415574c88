"""Batched labelling: label_frames (core) and the fdi node's BatchWorker (no ROS)."""

import threading
import time

import numpy as np
import pytest

from inkdiag_core import FaultClass, label_frames, label_frames_isolated, label_traces, load_model, simulate
from inkdiag_ros.batching import BatchWorker


def _frames(seed=0):
    r = simulate({FaultClass.HEALTHY_NOZZLE: 10, FaultClass.FULLY_BLOCKED: 5,
                  FaultClass.DEEPLY_DRIED: 5, FaultClass.EMPTY_CHANNEL_1: 4}, seed=seed)
    x = r.traces.astype(np.float32)
    x[3, 10] = np.nan  # an invalid row inside the second frame
    return [x[:3], x[3:11], x[11:12], x[12:]]


def test_label_frames_equals_each_frame_labelled_alone(fdi_model):
    model, manifest = load_model(fdi_model)
    frames = _frames()
    together = label_frames(model, frames, fd_threshold=0.3)
    assert [len(r.classes) for r in together] == [f.shape[0] for f in frames]
    for f, got in zip(frames, together):
        alone = label_traces(model, f, fd_threshold=0.3)
        assert list(got.classes) == list(alone.classes)
        np.testing.assert_allclose(got.confidence, alone.confidence, rtol=1e-12)
        assert list(got.valid) == list(alone.valid) and list(got.reasons) == list(alone.reasons)
    assert together[1].reasons[0] == "non_finite" and not together[1].valid[0]
    assert label_frames(model, []) == []


def test_label_frames_isolated_costs_a_bad_frame_only_itself(fdi_model):
    from inkdiag_core import label_frames_isolated

    model, _ = load_model(fdi_model)
    frames = _frames()
    good = label_frames_isolated(model, frames, fd_threshold=0.3, first_nozzles=[0, 3, 11, 12])
    assert [list(g.classes) for g in good] == [list(w.classes) for w in label_frames(model, frames, fd_threshold=0.3)]
    mixed = label_frames_isolated(model, [frames[1], np.zeros(512, np.float32)], fd_threshold=0.3,
                                  first_nozzles=[3, 11])
    assert list(mixed[0].classes) == list(good[1].classes)
    assert isinstance(mixed[1], str) and mixed[1].startswith("ValueError")


@pytest.mark.parametrize("max_abs_v, reason", [(10.0, "out_of_range"), (None, "non_finite_features")])
def test_an_extreme_row_costs_only_itself(fdi_model, max_abs_v, reason):
    """Rows with finite samples no sensor produces are invalid; every other row of the batch is labelled."""
    import warnings

    model, _ = load_model(fdi_model)
    frames = _frames()
    want = label_frames(model, frames, fd_threshold=0.3)
    bad = [np.array(f) for f in frames]
    big = np.finfo(np.float32).max
    bad[1][2, 100] = 1e30  # one spike
    bad[1][5, ::2], bad[1][5, 1::2] = big, -big  # alternating extremes
    bad[3][0, 7] = -big
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no numpy RuntimeWarning on this path
        got = label_frames(model, bad, fd_threshold=0.3, max_abs_v=max_abs_v)
        isolated = label_frames_isolated(model, bad, fd_threshold=0.3, first_nozzles=[0, 3, 11, 12],
                                         max_abs_v=max_abs_v)
    hit = {(1, 2), (1, 5), (3, 0)}
    for k, (g, w, iso) in enumerate(zip(got, want, isolated)):
        assert not isinstance(iso, str) and list(iso.classes) == list(g.classes)
        for i in range(len(g.classes)):
            if (k, i) in hit:
                assert (g.valid[i], g.reasons[i], g.classes[i]) == (False, reason, "")
                assert np.isnan(g.confidence[i])
            else:  # every other row as it was labelled without the extreme rows
                assert (g.valid[i], g.reasons[i], g.classes[i]) == (w.valid[i], w.reasons[i], w.classes[i])
                np.testing.assert_allclose(g.confidence[i], w.confidence[i], rtol=1e-12)
    assert got[1].reasons[0] == "non_finite"  # the NaN row keeps its reason


def test_label_frames_rejects_mixed_widths_and_bad_ndim(fdi_model):
    model, _ = load_model(fdi_model)
    a = np.zeros((2, 512), np.float32)
    with pytest.raises(ValueError, match="one sample count"):
        label_frames(model, [a, np.zeros((2, 256), np.float32)])
    with pytest.raises(ValueError, match="frame 1 has shape"):
        label_frames(model, [a, np.zeros(512, np.float32)])


def test_batch_worker_batches_what_queued_while_busy_and_keeps_order():
    gate, batches = threading.Event(), []

    def handle(items):
        batches.append(list(items))
        gate.wait(5)

    w = BatchWorker(handle, max_queued=100, max_batch_rows=1000)
    try:
        w.submit(0, rows=10)
        deadline = time.monotonic() + 5
        while not batches and time.monotonic() < deadline:
            time.sleep(0.001)
        for i in range(1, 6):  # queue while the worker is busy with item 0
            w.submit(i, rows=10)
        assert w.pending() == 6
        gate.set()
        assert w.wait_idle(5)
    finally:
        w.stop()
    assert batches == [[0], [1, 2, 3, 4, 5]]


def test_batch_worker_caps_rows_drops_oldest_and_survives_errors():
    gate, batches, dropped, errors = threading.Event(), [], [], []

    def handle(items):
        batches.append(list(items))
        gate.wait(5)
        if "boom" in items:
            raise RuntimeError("boom")

    w = BatchWorker(handle, max_queued=3, max_batch_rows=25, on_drop=dropped.append,
                    on_error=errors.append)
    try:
        w.submit("first", rows=1)
        deadline = time.monotonic() + 5
        while not batches and time.monotonic() < deadline:
            time.sleep(0.001)
        for item in ("a", "b", "boom", "c"):  # queue of 3: "a" is dropped when "c" arrives
            w.submit(item, rows=10)
        gate.set()
        assert w.wait_idle(5)
        w.submit("after", rows=1)
        assert w.wait_idle(5)
    finally:
        w.stop()
    assert dropped == ["a"]
    assert batches == [["first"], ["b", "boom"], ["c"], ["after"]]  # <= 25 rows per batch
    assert len(errors) == 1 and str(errors[0]) == "boom"
    with pytest.raises(RuntimeError, match="stopped"):
        w.submit("late")
    with pytest.raises(ValueError, match="max_queued"):
        BatchWorker(lambda items: None, max_queued=0)


def _wait_for(cond, timeout=5.0):
    deadline = time.monotonic() + timeout
    while not cond() and time.monotonic() < deadline:
        time.sleep(0.001)
    return cond()


def test_batch_worker_with_batches_in_flight_takes_the_next_only_when_one_is_finished():
    handed, errors = [], []

    def handle(items):
        handed.append(list(items))
        if "bad" in items:
            raise RuntimeError("not handed on")

    w = BatchWorker(handle, max_queued=100, max_in_flight=2, on_error=errors.append)
    try:
        w.submit(0)
        assert _wait_for(lambda: handed == [[0]])
        w.submit(1)
        assert _wait_for(lambda: handed == [[0], [1]])
        for i in range(2, 6):  # both batches out: these wait, then go together
            w.submit(i)
        time.sleep(0.2)
        assert handed == [[0], [1]] and w.pending() == 6 and not w.wait_idle(0.05)
        w.finished()
        assert _wait_for(lambda: handed == [[0], [1], [2, 3, 4, 5]])
        w.finished()
        assert not w.wait_idle(0.05)
        w.finished()
        assert w.wait_idle(5) and w.pending() == 0
        with pytest.raises(RuntimeError, match="more often"):
            w.finished()
        w.submit("bad")  # handle raised: nothing is out, so it is done without finished()
        assert w.wait_idle(5) and len(errors) == 1
    finally:
        w.stop()
    sync = BatchWorker(lambda items: None)
    with pytest.raises(RuntimeError, match="max_in_flight"):
        sync.finished()
    sync.stop()
    with pytest.raises(ValueError, match="max_in_flight"):
        BatchWorker(lambda items: None, max_in_flight=0)
