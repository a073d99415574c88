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


def _frame(i, frames, firsts):
    from types import SimpleNamespace

    return SimpleNamespace(id=i, traces=frames[i % 3], first_nozzle=firsts[i % 3])


def test_inline_pipeline_labels_on_the_flushing_thread_in_bounded_batches_as_the_labeller_does(head):
    """flush() labels what is queued, in batches of at most max_batch_rows rows, each frame's result in order,
    on the calling thread; the results equal FrameLabeller.label's on the same frames."""
    import threading

    from inkdiag_ros.labelling_backend import InlinePipeline

    det, _, frames, firsts = head
    labeller = FrameLabeller(det, max_abs_v=10.0)
    seen, batches, threads = [], [], set()

    def on_result(frame, result):
        threads.add(threading.current_thread())
        seen.append((frame.id, result))

    pipe = InlinePipeline(ThreadBackend(labeller), on_result, max_batch_rows=40,
                          on_batch=lambda n, busy_s: batches.append((n, busy_s > 0)))
    for i in range(6):  # 16, 24, 24, 16, 24, 24 rows
        pipe.submit(_frame(i, frames, firsts))
    assert seen == [] and not pipe.wait_idle(0.0)  # nothing before the flush
    pipe.flush()
    assert pipe.wait_idle(0.0) and threads == {threading.current_thread()}
    assert [i for i, _ in seen] == list(range(6))
    assert batches == [(2, True), (2, True), (1, True), (1, True)]  # 16+24, 24+16, 24, 24 rows: at most 40
    want = labeller.label(frames, firsts)
    for i, got in seen:
        assert list(got.classes) == list(want[i % 3].classes) and list(got.reasons) == list(want[i % 3].reasons)
    pipe.close()


def test_inline_pipeline_drops_the_oldest_from_a_full_queue_and_outlives_a_raising_callback(head):
    from inkdiag_ros.labelling_backend import InlinePipeline

    det, _, frames, firsts = head
    seen, errors, dropped = [], [], []

    def on_result(frame, result):
        if frame.id == 3:
            raise RuntimeError("publishing failed")
        seen.append(frame.id)

    pipe = InlinePipeline(ThreadBackend(FrameLabeller(det, max_abs_v=10.0)), on_result, max_queued=3,
                          on_drop=lambda frame: dropped.append(frame.id),
                          on_error=lambda frame, exc: errors.append((frame.id, str(exc))))
    for i in range(5):
        pipe.submit(_frame(i, frames, firsts))
    pipe.flush()
    assert dropped == [0, 1] and seen == [2, 4] and errors == [(3, "publishing failed")]
    pipe.close()
    pipe.close()  # a second close is a no-op
    with pytest.raises(RuntimeError, match="closed"):
        pipe.submit(_frame(0, frames, firsts))


def test_inline_pipeline_fails_every_frame_of_a_batch_its_backend_lost_and_goes_on(head):
    from inkdiag_ros.labelling_backend import InlinePipeline

    det, _, frames, firsts = head
    backend = ThreadBackend(FrameLabeller(det, max_abs_v=10.0))
    screen = backend.screen
    calls = []

    def lose_first(traces, first_nozzles):
        calls.append(len(traces))
        if len(calls) == 1:
            raise OSError("gone")
        return screen(traces, first_nozzles)

    backend.screen = lose_first
    got = []
    pipe = InlinePipeline(backend, lambda frame, result: got.append((frame.id, type(result).__name__)),
                          max_batch_rows=40)
    for i in range(4):
        pipe.submit(_frame(i, frames, firsts))
    pipe.flush()
    assert calls == [2, 2]
    assert got == [(0, "FrameFailure"), (1, "FrameFailure"), (2, "FrameLabels"), (3, "FrameLabels")]


def test_closing_an_inline_pipeline_waits_for_the_batch_being_labelled_on_another_thread(head):
    """The node's teardown (another thread) closes the pipeline while the executor thread flushes: the batch in
    hand is handed out before the backend closes; what was still queued is not labelled."""
    import threading

    from inkdiag_ros.labelling_backend import InlinePipeline

    det, _, frames, firsts = head
    backend = ThreadBackend(FrameLabeller(det, max_abs_v=10.0))
    started, release, events = threading.Event(), threading.Event(), []
    finish = backend.labeller.finish

    def slow_finish(screened):
        started.set()
        release.wait(10.0)
        return finish(screened)

    backend.labeller.finish = slow_finish
    close = backend.close
    backend.close = lambda: events.append("backend closed") or close()
    pipe = InlinePipeline(backend, lambda frame, result: events.append(frame.id), max_batch_rows=16)
    for i in range(3):  # 16-row bound: one frame per batch
        pipe.submit(_frame(i, frames, firsts))
    flusher = threading.Thread(target=pipe.flush)
    flusher.start()
    assert started.wait(10.0)
    closer = threading.Thread(target=pipe.close)
    closer.start()
    closer.join(0.2)
    assert closer.is_alive() and events == []  # close waits for the batch in hand
    release.set()
    closer.join(10.0)
    flusher.join(10.0)
    assert events == [0, "backend closed"]


def test_an_inline_flush_stops_between_batches_when_told_and_the_rest_waits(head):
    """fdi flushes with ``keep_going=context.ok``: a signal in the middle of a burst stops it after the batch in
    hand; the frames left stay queued (the next flush takes them, or close drops them)."""
    from inkdiag_ros.labelling_backend import InlinePipeline

    det, _, frames, firsts = head
    seen = []
    pipe = InlinePipeline(ThreadBackend(FrameLabeller(det, max_abs_v=10.0)), lambda f, r: seen.append(f.id),
                          max_batch_rows=16)
    for i in range(3):  # one frame per batch
        pipe.submit(_frame(i, frames, firsts))
    pipe.flush(lambda: len(seen) < 1)
    assert seen == [0] and not pipe.wait_idle(0.0)
    pipe.flush()
    assert seen == [0, 1, 2] and pipe.wait_idle(0.0)


def test_an_inline_flush_screens_what_arrives_meanwhile_and_runs_the_detector_once(head):
    """fdi's flush asks ``refill`` for the messages that arrived while a burst was screened: they are
    screened too, and the detector runs once for all of them (its fixed cost once per burst, not per
    executor wake-up); the labels are FrameLabeller.label's, frame by frame, in order."""
    from inkdiag_ros.labelling_backend import InlinePipeline

    det, base, frames, firsts = head
    labeller = FrameLabeller(det, base, max_abs_v=10.0)
    backend = ThreadBackend(labeller)
    detector_calls, finish = [], labeller.finish
    labeller.finish = lambda screened: detector_calls.append(len(screened)) or finish(screened)
    seen, batches = [], []
    pipe = InlinePipeline(backend, lambda f, r: seen.append((f.id, r)), max_batch_rows=1000,
                          on_batch=lambda n, busy_s: batches.append(n))
    arrivals = [[3, 4], [5], []]  # what each refill finds

    def refill():
        new = arrivals.pop(0)
        for i in new:
            pipe.submit(_frame(i, frames, firsts))
        return bool(new)

    for i in range(3):
        pipe.submit(_frame(i, frames, firsts))
    pipe.flush(refill=refill)
    assert arrivals == [] and detector_calls == [3] and batches == [6]  # screened 3 times, finished once
    assert [i for i, _ in seen] == list(range(6))
    want = labeller.label(frames, firsts)
    for i, got in seen:
        w = want[i % 3]
        for name in ("classes", "valid", "reasons", "baseline", "gate_cleared"):
            assert np.array_equal(getattr(got, name), getattr(w, name)), name
        assert np.array_equal(got.confidence, w.confidence, equal_nan=True)
    assert pipe.wait_idle(0.0)


def test_an_inline_flush_bounds_a_detector_pass_by_max_batch_rows_and_returns_under_sustained_load(head):
    """Frames keep arriving (``refill`` always finds one): the detector runs once the next frame would take its
    pass beyond ``max_batch_rows`` rows, refill is not asked again, and the flush returns once the queue is empty (the
    node's callback gets its thread back: /diagnostics, the timer)."""
    from inkdiag_ros.labelling_backend import InlinePipeline

    det, _, frames, firsts = head
    seen, batches, asked = [], [], []
    pipe = InlinePipeline(ThreadBackend(FrameLabeller(det, max_abs_v=10.0)), lambda f, r: seen.append(f.id),
                          max_batch_rows=48, on_batch=lambda n, busy_s: batches.append(n))
    k = iter(range(3, 100))

    def refill():  # a frame (16, 24 or 24 rows) always waiting
        asked.append(1)
        pipe.submit(_frame(next(k), frames, firsts))
        return True

    pipe.submit(_frame(0, frames, firsts))  # 16 rows
    pipe.flush(refill=refill)
    # frame 0 (16 rows) and refilled 3 (16): one pass; refilled 4 (24 rows) does not fit the 48 - 32 left:
    # a pass of its own after, without asking refill again
    assert asked == [1, 1] and batches == [2, 1] and seen == [0, 3, 4] and pipe.wait_idle(0.0)
    pipe.close()


def test_a_stopped_inline_flush_still_hands_out_the_screened_and_each_frame_once(head):
    """A stop (``keep_going`` False) between batches labels and hands out what was screened, what is queued
    waits; an exception that is not an Exception (KeyboardInterrupt) from ``on_result`` leaves the flush
    without handing any frame out twice; one from ``refill`` ends it after the screened frames."""
    from inkdiag_ros.labelling_backend import InlinePipeline

    det, _, frames, firsts = head
    seen, batches = [], []
    pipe = InlinePipeline(ThreadBackend(FrameLabeller(det, max_abs_v=10.0)), lambda f, r: seen.append(f.id),
                          max_batch_rows=1000, on_batch=lambda n, busy_s: batches.append(n))
    for i in range(2):
        pipe.submit(_frame(i, frames, firsts))
    calls = []
    pipe.flush(lambda: not calls.append(1) and len(calls) < 2,
               refill=lambda: pipe.submit(_frame(2, frames, firsts)) is None)  # stopped after one refill
    assert seen == [0, 1] and batches == [2]  # the screened frames labelled at the stop, not lost
    assert not pipe.wait_idle(0.0)  # the refilled one waits
    pipe.close()

    handed = []

    def on_result(frame, result):
        handed.append(frame.id)
        if frame.id == 1:
            raise KeyboardInterrupt

    failed = []
    pipe = InlinePipeline(ThreadBackend(FrameLabeller(det, max_abs_v=10.0)), on_result, max_batch_rows=1000,
                          on_error=lambda frame, exc: failed.append((frame.id, type(exc).__name__)))
    for i in range(3):
        pipe.submit(_frame(i, frames, firsts))
    with pytest.raises(KeyboardInterrupt):
        pipe.flush()
    assert handed == [0, 1] and pipe.wait_idle(0.0)  # frame 2 is not handed out; none twice
    assert failed == [(2, "KeyboardInterrupt")]  # but reported: not silently lost
    pipe.close()

    for stage in ("screen", "finish"):  # interrupted inside the backend: every frame taken is reported failed
        backend = ThreadBackend(FrameLabeller(det, max_abs_v=10.0))

        def interrupted(*args, **kwargs):
            raise KeyboardInterrupt

        setattr(backend, stage, interrupted)
        handed.clear()
        failed.clear()
        pipe = InlinePipeline(backend, lambda f, r: handed.append(f.id), max_batch_rows=1000,
                              on_error=lambda frame, exc: failed.append((frame.id, type(exc).__name__)))
        for i in range(2):
            pipe.submit(_frame(i, frames, firsts))
        with pytest.raises(KeyboardInterrupt):
            pipe.flush()
        assert handed == [] and failed == [(0, "KeyboardInterrupt"), (1, "KeyboardInterrupt")], stage
        assert pipe.wait_idle(0.0)
        pipe.close()

    seen.clear()
    pipe = InlinePipeline(ThreadBackend(FrameLabeller(det, max_abs_v=10.0)), lambda f, r: seen.append(f.id),
                          max_batch_rows=1000)
    pipe.submit(_frame(0, frames, firsts))

    def broken_refill():
        raise RuntimeError("take failed")

    with pytest.raises(RuntimeError, match="take failed"):
        pipe.flush(refill=broken_refill)
    assert seen == [0] and pipe.wait_idle(0.0)
    pipe.close()


def test_an_inline_flush_does_not_wait_for_more_once_the_screened_frames_left_many_rows(head, monkeypatch):
    """Frames of faulty nozzles leave most rows to the detector: past DEFER_ROWS of them the detector runs
    without asking for more (its fixed cost is already small against theirs)."""
    from inkdiag_ros import labelling_backend
    from inkdiag_ros.labelling_backend import InlinePipeline

    det, _, frames, firsts = head  # no gate: every valid row is left to the detector
    monkeypatch.setattr(labelling_backend, "DEFER_ROWS", 30)
    batches, asked = [], []
    pipe = InlinePipeline(ThreadBackend(FrameLabeller(det, max_abs_v=10.0)), lambda f, r: None,
                          max_batch_rows=1000, on_batch=lambda n, busy_s: batches.append(n))
    pipe.submit(_frame(0, frames, firsts))  # 16 rows left: below 30, more is asked for
    pipe.flush(refill=lambda: asked.append(1) or (len(asked) == 1 and pipe.submit(_frame(1, frames, firsts)) is None))
    assert asked == [1] and batches == [2]  # 16 + 24 rows left: 40 >= 30, the detector ran at once
