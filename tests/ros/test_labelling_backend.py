"""inkdiag_ros.labelling_backend: thread and process backends give the FrameLabeller's results, in order."""

import dataclasses
import os
import signal

import numpy as np
import pytest

from inkdiag_core import (
    BaselineModel,
    BaselineRecorder,
    FaultClass,
    FrameFailure,
    FrameLabeller,
    label_frames_isolated,
    load_detector,
    simulate_nozzles,
)
from inkdiag_ros.labelling_backend import ProcessBackend, ThreadBackend, make_backend
from inkdiag_ros.labelling_process import LabellingProcessError

HEAD, N = 41, 64


@pytest.fixture(scope="module")
def head(fdi_baseline_model):
    det = load_detector(fdi_baseline_model)
    rec = BaselineRecorder(n_frames=4)
    for k in range(4):
        rec.add(0, simulate_nozzles(["healthy_nozzle"] * 40, seed=HEAD, frame_seed=k).traces)  # nozzles 0..39
    classes = np.array(list(FaultClass), dtype=object)[np.arange(N) % 12]
    x = simulate_nozzles(classes, seed=HEAD, frame_seed=9).traces.astype(np.float32)
    x[5, 3] = np.inf
    frames, firsts = [x[:16], x[16:40], x[40:]], [0, 16, 40]
    # without reference traces (no healthy gate): the previous path knows no gate
    return det, dataclasses.replace(rec.baselines(), reference=None), frames, firsts


def _previous(det, frames, firsts, baselines):
    base = None if baselines is None else BaselineModel(det.baseline_pipeline_, baselines, det.baseline_fd_threshold_)
    return label_frames_isolated(det.pipeline_, frames, fd_threshold=det.fd_threshold_, first_nozzles=firsts,
                                 baseline=base, max_abs_v=10.0)


def _same(got, want):
    assert len(got) == len(want)
    for g, w in zip(got, want):
        assert list(g.classes) == list(w.classes) and list(g.reasons) == list(w.reasons)
        np.testing.assert_array_equal(g.confidence, w.confidence)
        np.testing.assert_array_equal(g.valid, w.valid)
        np.testing.assert_array_equal(g.baseline, w.baseline)


@pytest.mark.parametrize("with_baselines", [False, True])
@pytest.mark.parametrize("in_process", [False, True], ids=["thread", "process"])
def test_backends_label_bit_identically_to_the_previous_path_in_order(head, in_process, with_baselines):
    det, baselines, frames, firsts = head
    b = baselines if with_baselines else None
    backend, why = make_backend(FrameLabeller(det, b, max_abs_v=10.0), in_process=in_process)
    try:
        assert why is None and isinstance(backend, ProcessBackend if in_process else ThreadBackend)
        backend.submit(frames, firsts)
        backend.submit(frames[::-1], firsts[::-1])
        first, second = backend.collect(), backend.collect()
        _same(first.results, _previous(det, frames, firsts, b))
        _same(second.results, _previous(det, frames[::-1], firsts[::-1], b))
        assert first.busy_s > 0 and second.busy_s > 0
        assert np.concatenate([r.baseline for r in first.results]).sum() == (39 if with_baselines else 0)
    finally:
        backend.close()


@pytest.mark.parametrize("in_process", [False, True], ids=["thread", "process"])
def test_backends_carry_the_rows_the_gate_cleared(head, in_process):
    det, baselines, frames, firsts = head
    rec = BaselineRecorder(n_frames=4)
    for k in range(4):
        rec.add(0, simulate_nozzles(["healthy_nozzle"] * 40, seed=HEAD, frame_seed=k).traces)
    labeller = FrameLabeller(det, rec.baselines(), max_abs_v=10.0)
    assert labeller.uses_gate
    want = labeller.label(frames, firsts)
    backend, why = make_backend(labeller, in_process=in_process)
    try:
        backend.submit(frames, firsts)
        got = backend.collect().results
    finally:
        backend.close()
    cleared = np.concatenate([r.gate_cleared for r in got])
    assert cleared.any()
    np.testing.assert_array_equal(cleared, np.concatenate([r.gate_cleared for r in want]))
    for g, w in zip(got, want):
        assert list(g.classes) == list(w.classes)


class _Broken(FrameLabeller):
    def label(self, frames, first_nozzles):
        raise RuntimeError("the labeller itself failed")


def test_a_batch_the_labeller_fails_fails_every_frame(head):
    det, _, frames, firsts = head
    backend = ThreadBackend(_Broken(det))
    backend.submit(frames, firsts)
    got = backend.collect().results
    assert [g.frame_index for g in got] == [0, 1, 2]
    assert all(isinstance(g, FrameFailure) and "the labeller itself failed" in g.why for g in got)


def test_a_dead_child_fails_every_frame_it_had_and_the_next_batch_starts_a_new_one(head):
    det, _, frames, firsts = head
    backend = ProcessBackend(FrameLabeller(det, max_abs_v=10.0))
    try:
        backend.submit(frames[:1], firsts[:1])
        backend.collect()  # the child is up
        pid = backend.pid
        os.kill(pid, signal.SIGKILL)
        backend.submit(frames, firsts)
        got = backend.collect().results
        assert len(got) == 3 and all(isinstance(g, FrameFailure) and isinstance(g.error, LabellingProcessError)
                                     for g in got)
        backend.submit(frames, firsts)
        _same(backend.collect().results, _previous(det, frames, firsts, None))
        assert backend.pid not in (None, pid) and backend.config_error is None
    finally:
        backend.close()


def test_a_child_that_cannot_start_falls_back_to_the_thread_and_says_why(head):
    det, _, frames, firsts = head
    backend = ProcessBackend(FrameLabeller(det, max_abs_v=10.0))
    try:
        backend._process._fatal = "its imports failed"  # as after a child that died before it was ready
        backend.submit(frames, firsts)
        _same(backend.collect().results, _previous(det, frames, firsts, None))
        assert "cannot start" in backend.config_error and "its imports failed" in backend.config_error
    finally:
        backend.close()


def test_pipeline_outlives_a_result_callback_that_raises(head):
    """A frame whose on_result raises goes to on_error; the collector goes on with every later frame."""
    from types import SimpleNamespace

    from inkdiag_ros.labelling_backend import LabellingPipeline

    det, _, frames, firsts = head
    seen, errors = [], []

    def on_result(frame, result):
        if frame.id == 1:
            raise RuntimeError("publishing failed")
        seen.append(frame.id)

    pipe = LabellingPipeline(ThreadBackend(FrameLabeller(det, max_abs_v=10.0)), on_result,
                             on_error=lambda frame, exc: errors.append((frame.id, str(exc))))
    try:
        for i in range(6):
            pipe.submit(SimpleNamespace(id=i, traces=frames[i % 3], first_nozzle=firsts[i % 3]))
        assert pipe.wait_idle(30.0)
    finally:
        pipe.close()
    assert seen == [0, 2, 3, 4, 5] and errors == [(1, "publishing failed")]


def test_closing_a_pipeline_twice_closes_its_backend_once(head):
    """tear_down closes fdi's outputs, then destroy_node closes them again: the second close is a no-op."""
    from types import SimpleNamespace

    from inkdiag_ros.labelling_backend import LabellingPipeline

    det, _, frames, firsts = head
    backend, seen, closes = ThreadBackend(FrameLabeller(det, max_abs_v=10.0)), [], []
    close = backend.close
    backend.close = lambda: closes.append(1) or close()
    pipe = LabellingPipeline(backend, lambda frame, result: seen.append(frame.id))
    pipe.submit(SimpleNamespace(id=0, traces=frames[0], first_nozzle=firsts[0]))
    assert pipe.wait_idle(30.0)
    pipe.close()
    pipe.close()
    assert seen == [0] and closes == [1]
