"""The fdi node's labelling process (no ROS): same labels as in-process, in order, survives its child."""

import os
import signal
import time

import numpy as np
import pytest

from inkdiag_core import (
    BaselineModel,
    BaselineRecorder,
    FaultClass,
    label_frames,
    load_model,
    simulate,
    simulate_nozzles,
)
from inkdiag_ros.labelling_process import LabellingProcess, LabellingProcessError


def _frames(seed=0):
    r = simulate({FaultClass.HEALTHY_NOZZLE: 10, FaultClass.FULLY_BLOCKED: 5,
                  FaultClass.DEEPLY_DRIED: 5, FaultClass.EMPTY_CHANNEL_1: 4}, seed=seed)
    x = r.traces.astype(np.float32)
    x[3, 10] = np.nan  # an invalid row inside the second frame
    x[12, :] = 0.5  # a flat one in the fourth
    return [x[:3], x[3:11], x[11:12], x[12:]]


def _same(got, want):
    assert len(got) == len(want)
    for g, w in zip(got, want):
        assert list(g.classes) == list(w.classes) and list(g.reasons) == list(w.reasons)
        np.testing.assert_array_equal(g.confidence, w.confidence)  # bit-identical, NaN where invalid
        np.testing.assert_array_equal(g.valid, w.valid)
        np.testing.assert_array_equal(g.baseline, w.baseline)


@pytest.fixture(scope="module")
def labeller(fdi_model):
    model, _ = load_model(fdi_model)
    lp = LabellingProcess(model, fd_threshold=0.3, capacity_bytes=4096)
    yield model, lp
    lp.close()


def test_child_labels_exactly_as_label_frames_in_order_with_two_batches_out(labeller):
    model, lp = labeller
    a, b = _frames(0), _frames(1)
    lp.submit(a, [0, 3, 11, 12])
    lp.submit(b, [100, 103, 111, 112])
    assert lp.in_flight == 2
    with pytest.raises(RuntimeError, match="collect one first"):
        lp.submit(a, [0, 3, 11, 12])
    _same(lp.collect(), label_frames(model, a, fd_threshold=0.3))
    _same(lp.collect(), label_frames(model, b, fd_threshold=0.3))
    assert lp.in_flight == 0 and lp.busy_s > 0
    with pytest.raises(RuntimeError, match="no batch is out"):
        lp.collect()


def test_child_grows_its_buffer_and_takes_empty_and_float64_frames(labeller):
    model, lp = labeller
    big = [np.concatenate(_frames(2)).astype(np.float64)] * 3  # > the 4 kB buffer it started with
    _same(lp.label(big, [0, 24, 48]), label_frames(model, big, fd_threshold=0.3))
    empty = lp.label([np.zeros((0, 512), np.float32)], [0])
    assert empty[0].classes.shape == (0,)


def test_a_frame_that_cannot_be_labelled_costs_only_itself(labeller):
    model, lp = labeller
    good = _frames(3)[1]
    got = lp.label([good, np.zeros(512, np.float32)], [0, 8])  # a 1-D "frame": label_frames refuses
    _same(got[:1], label_frames(model, [good], fd_threshold=0.3))
    assert isinstance(got[1], str) and "ValueError" in got[1]


def test_child_labels_against_per_nozzle_baselines(tmp_path):
    from inkdiag_core.fdi import train_default_model

    train_default_model(tmp_path / "plain.joblib", n_per_class=30)
    train_default_model(tmp_path / "base.joblib", n_per_class=30, features="kpi_y+baseline")
    plain, _ = load_model(tmp_path / "plain.joblib")
    based, _ = load_model(tmp_path / "base.joblib")
    rec = BaselineRecorder(n_frames=3)
    healthy = np.array([FaultClass.HEALTHY_NOZZLE] * 20, dtype=object)
    for k in range(3):
        rec.add(40, simulate_nozzles(healthy, seed=7, frame_seed=k).traces)
    model = BaselineModel(based, rec.baselines())
    classes = np.array(list(FaultClass), dtype=object)[np.arange(30) % 12]
    frame = simulate_nozzles(classes, seed=7, frame_seed=50).traces.astype(np.float32)
    frames, firsts = [frame[:15], frame[15:]], [30, 45]  # nozzles 40..59 have a baseline
    with LabellingProcess(plain, baseline=model) as lp:
        got = lp.label(frames, firsts)
    want = label_frames(plain, frames, first_nozzles=firsts, baseline=model)
    _same(got, want)
    assert np.concatenate([w.baseline for w in want]).sum() == 20


def test_a_killed_child_fails_its_batches_and_the_next_one_starts_afresh(fdi_model):
    model, _ = load_model(fdi_model)
    frames = _frames(4)
    lp = LabellingProcess(model)
    try:
        assert lp.label(frames[:1], [0])[0].classes.shape == (3,)
        os.kill(lp.pid, signal.SIGKILL)
        time.sleep(0.2)
        with pytest.raises(LabellingProcessError, match=r"exited \(code -9\)"):
            lp.label(frames, [0, 3, 11, 12])
        assert lp.pid is None and lp.in_flight == 0
        _same(lp.label(frames, [0, 3, 11, 12]), label_frames(model, frames))
        assert lp.starts == 2
    finally:
        pid, names = lp.pid, [s.name for s in lp._shm]
        lp.close()
    with pytest.raises(ProcessLookupError):
        os.kill(pid, 0)  # the child is gone (reaped)
    assert not any(os.path.exists(f"/dev/shm/{n.lstrip('/')}") for n in names)
    with pytest.raises(LabellingProcessError, match="closed"):
        lp.submit(frames, [0, 3, 11, 12])
    lp.close()  # twice is fine


def test_refuses_a_bad_depth(fdi_model):
    model, _ = load_model(fdi_model)
    with pytest.raises(ValueError, match="depth must be >= 1"):
        LabellingProcess(model, depth=0)


def test_two_large_batches_out_do_not_deadlock_the_pipes(labeller):
    """Thousands of frames per batch: their layout goes through shared memory, not the request pipe."""
    import threading

    model, lp = labeller
    x = np.concatenate(_frames(5))
    frames = [x[i % len(x)][None] for i in range(3000)]  # 3000 one-row frames per batch
    got = {}

    def run():
        lp.submit(frames, range(3000))
        lp.submit(frames[::-1], range(3000))
        got["a"], got["b"] = lp.collect(), lp.collect()

    t = threading.Thread(target=run, daemon=True)
    t.start()
    t.join(120)
    assert not t.is_alive(), "submit/collect of two large batches hung"
    want = label_frames(model, frames, fd_threshold=0.3)
    _same(got["a"], want)
    _same(got["b"], want[::-1])


class _FailsToUnpickle:
    """Pickles in the parent; unpickling it in the child raises."""

    def __reduce__(self):
        import operator

        return operator.truediv, (1, 0)


def test_a_child_that_cannot_start_is_not_restarted_for_every_batch():
    lp = LabellingProcess(_FailsToUnpickle())
    try:
        with pytest.raises(LabellingProcessError, match="exited"):
            lp.label(_frames(6), [0, 3, 11, 12])
        assert lp.broken and lp.starts == 1
        with pytest.raises(LabellingProcessError, match="cannot start"):
            lp.submit(_frames(6), [0, 3, 11, 12])
        assert lp.starts == 1 and lp.in_flight == 0
    finally:
        lp.close()


def test_a_child_found_dead_at_submit_before_it_was_ready_is_not_restarted_either():
    lp = LabellingProcess(_FailsToUnpickle())
    try:
        deadline = time.monotonic() + 30
        while lp._proc.is_alive() and time.monotonic() < deadline:  # dies unpickling the model
            time.sleep(0.05)
        with pytest.raises(LabellingProcessError):
            for _ in range(3):  # the pipe may take a request or two before it reports the death
                lp.label(_frames(6), [0, 3, 11, 12])
        assert lp.broken and lp.starts == 1
    finally:
        lp.close()


def test_a_child_killed_by_a_signal_while_starting_is_restarted(fdi_model):
    model, _ = load_model(fdi_model)
    lp = LabellingProcess(model)
    try:
        os.kill(lp.pid, signal.SIGKILL)  # still importing: not ready yet
        with pytest.raises(LabellingProcessError, match=r"code -9"):
            lp.label(_frames(7), [0, 3, 11, 12])
        assert lp.broken is None
        _same(lp.label(_frames(7), [0, 3, 11, 12]), label_frames(model, _frames(7)))
        assert lp.starts == 2
    finally:
        lp.close()


def test_no_room_for_the_shared_buffers_is_an_error_not_a_crash(fdi_model):
    import glob

    model, _ = load_model(fdi_model)
    before = set(glob.glob("/dev/shm/psm_*"))
    with pytest.raises(LabellingProcessError, match="shared memory|/dev/shm"):
        LabellingProcess(model, capacity_bytes=1 << 46)  # 64 TiB: more than any /dev/shm holds
    assert set(glob.glob("/dev/shm/psm_*")) <= before
