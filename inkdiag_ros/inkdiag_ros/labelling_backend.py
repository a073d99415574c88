"""Where the fdi node's :class:`inkdiag_core.FrameLabeller` runs: two backends, two pipelines.

Both take a batch of frames with :meth:`submit` and give back, with
:meth:`collect` (batches in the order submitted), a :class:`LabelledBatch`: the
labeller's per-frame results (a :class:`inkdiag_core.FrameLabels`, or an
:class:`inkdiag_core.FrameFailure`) and the seconds spent labelling. Whatever
goes wrong inside a backend becomes a failure of every frame of the batch it
hit; neither method raises for a batch.

- :class:`ThreadBackend`: labels in :meth:`submit`, on the caller's thread; or in two
  stages, :meth:`ThreadBackend.screen` per batch and :meth:`ThreadBackend.finish` for several.
- :class:`ProcessBackend`: a child process (:class:`.labelling_process.LabellingProcess`)
  runs the same labeller (pickled across), so receiving, labelling and publishing
  overlap on two cores. A child that dies fails the frames it had and the next
  batch starts a new one; a child that cannot start at all (its imports or the
  model fail) makes the backend label on the submitting thread from then on and
  say why in :attr:`ProcessBackend.config_error`.

Two pipelines take decoded frames and hand each frame's result to the node:

- :class:`InlinePipeline` (the node's default, with a :class:`ThreadBackend`): the executor
  thread that took a burst of frames screens them, and the frames that arrive meanwhile,
  labels them in one detector pass (at most ``max_batch_rows`` rows of frames) and
  publishes their results (:meth:`InlinePipeline.flush`) before it takes more. One Python
  thread does all of the node's work, so no thread waits for another's GIL.
- :class:`LabellingPipeline` (with a :class:`ProcessBackend`): a worker thread hands batches
  to the child while the executor thread keeps receiving, and a collector thread publishes.

No ROS in here.
"""

from __future__ import annotations

import queue
import threading
import time
from collections import deque
from typing import Callable, NamedTuple, Protocol

from inkdiag_core import FrameFailure

from .batching import BatchWorker, push_bounded, take_batch
from .labelling_process import LabellingProcess, LabellingProcessError

__all__ = ["InlinePipeline", "LabelledBatch", "LabellingBackend", "LabellingPipeline", "ProcessBackend",
           "ThreadBackend", "make_backend"]


class LabelledBatch(NamedTuple):
    """One batch's results, in frame order.

    results : list -- per frame, a :class:`inkdiag_core.FrameLabels` or an :class:`inkdiag_core.FrameFailure`
    busy_s : float -- time spent labelling the batch, s
    """

    results: list
    busy_s: float


class LabellingBackend(Protocol):
    """submit / collect of batches of frames, in order; at most :attr:`depth` batches out."""

    depth: int
    config_error: str | None

    def submit(self, frames, first_nozzles) -> None: ...

    def collect(self) -> LabelledBatch: ...

    def close(self) -> None: ...


#: Rows left for the detector by the frames screened, beyond which :meth:`InlinePipeline.flush` runs it
#: without screening what arrives meanwhile first: its fixed cost per call (about 50 rows' worth,
#: reports/gate_bench.md) is small against theirs, and the answers need not wait.
DEFER_ROWS = 256


def _all_failed(n: int, exc: BaseException) -> list:
    return [FrameFailure(i, exc) for i in range(n)]


class ThreadBackend:
    """Label each batch on the thread that submits it.

    Parameters
    ----------
    labeller : inkdiag_core.FrameLabeller
    """

    depth = 1
    config_error = None

    def __init__(self, labeller):
        self.labeller = labeller
        self._done: deque = deque()

    def submit(self, frames, first_nozzles) -> None:
        """Label ``frames`` (sequence of (n_i, n_samples) arrays, V) now; :meth:`collect` returns them."""
        self._done.append(self._label(frames, first_nozzles))

    def _label(self, frames, first_nozzles) -> LabelledBatch:
        t0 = time.perf_counter()
        try:
            results = self.labeller.label(frames, first_nozzles)
        except Exception as exc:  # noqa: BLE001 - the labeller's own error: every frame of the batch failed
            results = _all_failed(len(frames), exc)
        return LabelledBatch(results, time.perf_counter() - t0)

    def collect(self) -> LabelledBatch:
        """The oldest batch submitted and not collected yet."""
        return self._done.popleft()

    def screen(self, frames, first_nozzles):
        """The first stage of labelling ``frames`` now (:meth:`inkdiag_core.FrameLabeller.screen`).

        Returns
        -------
        token
            For :meth:`finish` (with the tokens of other screened batches).
        rows_left : int
            Rows the detector will take.
        busy_s : float
            Seconds spent.
        """
        t0 = time.perf_counter()
        try:
            token = self.labeller.screen(frames, first_nozzles)
            left = token.rows_left
        except Exception as exc:  # noqa: BLE001 - the labeller's own error: every frame of the batch failed
            token, left = _all_failed(len(frames), exc), 0
        return token, left, time.perf_counter() - t0

    def finish(self, tokens) -> LabelledBatch:
        """Every screened batch of ``tokens`` labelled, one detector call for them all
        (:meth:`inkdiag_core.FrameLabeller.finish`): their frames' results, in order."""
        t0 = time.perf_counter()
        screened = [t for t in tokens if not isinstance(t, list)]
        try:
            done = iter(self.labeller.finish(screened))
        except Exception as exc:  # noqa: BLE001 - as in submit; a frame's own failure from screening stays
            done = iter([[r if isinstance(r, FrameFailure) else FrameFailure(i, exc) for i, r in enumerate(t.out)]
                         for t in screened])
        results = [r for t in tokens for r in (t if isinstance(t, list) else next(done))]
        return LabelledBatch(results, time.perf_counter() - t0)

    def close(self) -> None:
        self._done.clear()


class ProcessBackend:
    """Label each batch in a child process; falls back to the submitting thread if none can start.

    Parameters
    ----------
    labeller : inkdiag_core.FrameLabeller
        Pickled into the child.
    depth : int
        Batches out at a time (submit the next while the child labels one).

    Raises
    ------
    LabellingProcessError
        No child or shared memory could be set up at all (use a :class:`ThreadBackend`).
    """

    def __init__(self, labeller, *, depth: int = 2):
        self._process = LabellingProcess(labeller, depth=depth)
        self._thread = ThreadBackend(labeller)
        self.depth = self._process.depth
        self.config_error = None
        self._lock = threading.Lock()
        self._out: deque = deque()  # per batch submitted: its n_frames (in the child) or a LabelledBatch

    @property
    def pid(self):
        """The child's process id, or None."""
        return self._process.pid

    def submit(self, frames, first_nozzles) -> None:
        """Hand the batch to the child (returns at once); see :meth:`collect`."""
        if self._process.broken is None:
            try:
                self._process.submit(frames, first_nozzles)
            except Exception as exc:  # noqa: BLE001 - this batch is lost: each of its frames fails
                if self._process.broken is None:
                    self._out.append(LabelledBatch(_all_failed(len(frames), exc), 0.0))
                    return
            else:
                self._out.append(len(frames))
                return
        self.config_error = f"the labelling process cannot start ({self._process.broken}): labelling on a thread"
        self._out.append(self._thread._label(frames, first_nozzles))

    def collect(self) -> LabelledBatch:
        """The oldest batch's results (waits for the child); a dead child fails every frame it had."""
        entry = self._out.popleft()
        if isinstance(entry, LabelledBatch):
            return entry
        busy0 = self._process.busy_s
        try:
            results = self._process.collect()
        except Exception as exc:  # noqa: BLE001 - the child died, or its results did not unpickle
            return LabelledBatch(_all_failed(entry, exc), 0.0)
        return LabelledBatch(results, self._process.busy_s - busy0)

    def close(self) -> None:
        self._process.close()


def make_backend(labeller, *, in_process: bool):
    """A :class:`ProcessBackend` when asked and possible, else a :class:`ThreadBackend`.

    Returns
    -------
    backend : ThreadBackend or ProcessBackend
    error : str or None
        Why a child process was asked for and could not be set up.
    """
    if in_process:
        try:
            return ProcessBackend(labeller), None
        except LabellingProcessError as exc:
            return ThreadBackend(labeller), f"labelling in this process: {exc}"
    return ThreadBackend(labeller), None


class LabellingPipeline:
    """Frames in from any thread; each frame's result out, in order, on one collector thread.

    A :class:`.batching.BatchWorker` takes every frame queued while the backend was
    busy and submits them as one batch (at most ``backend.depth`` batches out); a
    collector thread collects each batch in order and calls ``on_result(frame,
    result)`` for every frame of it (``result``: a :class:`inkdiag_core.FrameLabels`
    or an :class:`inkdiag_core.FrameFailure`; a batch the backend lost fails every
    frame of it), then ``on_batch(n_frames, busy_s)``. This is the whole
    concurrency of the fdi node; the node only decodes, submits and publishes.

    Parameters
    ----------
    backend : ThreadBackend or ProcessBackend
    on_result : callable(frame, result) -> None
        Runs on the collector thread. If it raises, ``on_error(frame, exc)`` is called
        and the pipeline goes on with the next frame.
    on_batch : callable(n_frames: int, busy_s: float) -> None, optional
    on_drop : callable(frame) -> None, optional
        A frame dropped unlabelled from a full queue (``max_queued``).
    on_error : callable(frame, exc) -> None, optional
        ``on_result`` raised ``exc`` for ``frame`` (default: ignore).
    max_queued, max_batch_rows : int
        As for :class:`.batching.BatchWorker`.
    """

    def __init__(self, backend, on_result: Callable, *, on_batch: Callable | None = None,
                 on_drop: Callable | None = None, on_error: Callable | None = None, max_queued: int = 64,
                 max_batch_rows: int = 16384, name: str = "labeller"):
        self.backend = backend
        self._on_result, self._on_batch = on_result, on_batch or (lambda n, busy_s: None)
        self._on_error = on_error or (lambda frame, exc: None)
        self._handed_on = queue.SimpleQueue()  # (frames, error or None) per batch submitted, in order
        self._worker = BatchWorker(self._submit, max_queued=max_queued, max_batch_rows=max_batch_rows,
                                   on_drop=on_drop or (lambda frame: None), name=name,
                                   max_in_flight=backend.depth)
        self._collector = threading.Thread(target=self._collect, name=f"{name}-collector", daemon=True)
        self._collector.start()
        self._closed = False

    def submit(self, frame) -> None:
        """Queue one decoded frame (``.traces`` (n, n_samples), ``.first_nozzle``)."""
        self._worker.submit(frame, rows=frame.traces.shape[0])

    def flush(self, keep_going: Callable | None = None, refill: Callable | None = None) -> None:
        """Nothing to do: the pipeline's own threads label and hand out every frame submitted."""

    def wait_idle(self, timeout: float | None = None) -> bool:
        """Block until every submitted frame's result was handed to ``on_result``."""
        return self._worker.wait_idle(timeout)

    def close(self) -> None:
        """Stop taking frames, hand out the results of the batches out, close the backend (once; again: no-op)."""
        if self._closed:
            return
        self._closed = True
        self._worker.stop()
        self._handed_on.put(None)  # after the batches out: their results are handed out first
        self._collector.join(10.0)
        self.backend.close()

    def _submit(self, frames) -> None:
        try:
            self.backend.submit([f.traces for f in frames], [f.first_nozzle for f in frames])
        except Exception as exc:  # noqa: BLE001 - not out in the backend: every frame of it fails
            self._handed_on.put((frames, exc))
        else:
            self._handed_on.put((frames, None))

    def _collect(self) -> None:
        while (item := self._handed_on.get()) is not None:
            frames, error = item
            try:
                if error is not None:
                    raise error
                results, busy_s = self.backend.collect()
            except Exception as exc:  # noqa: BLE001 - the batch is lost: each of its frames fails
                results, busy_s = _all_failed(len(frames), exc), 0.0
            for frame, result in zip(frames, results):
                self._call(self._on_result, frame, result)
            try:
                self._on_batch(len(frames), busy_s)
            except Exception:  # noqa: BLE001 - statistics only; the collector goes on
                pass
            self._worker.finished()

    def _call(self, callback, frame, arg) -> None:
        _hand_out(callback, self._on_error, frame, arg)


def _hand_out(callback, on_error, frame, arg) -> None:
    """``callback(frame, arg)``; what it raises goes to ``on_error``, never out of the pipeline."""
    try:
        callback(frame, arg)
    except Exception as exc:  # noqa: BLE001 - the pipeline must outlive any one frame
        try:
            on_error(frame, exc)
        except Exception:  # noqa: BLE001 - nothing more to do for this frame
            pass


class InlinePipeline:
    """Frames labelled and handed out on the thread that queued them, when it calls :meth:`flush`.

    The fdi node's subscription callback submits every frame it took in one executor
    wake-up, then flushes: the queued frames are screened as they are taken, and what
    arrives meanwhile too (``refill``), then labelled in one detector pass (at most
    ``max_batch_rows`` rows of frames each; one larger frame alone); each frame's result goes to
    ``on_result(frame, result)`` in order, then ``on_batch(n_frames, busy_s)``. No thread of
    its own: taking, labelling and publishing take turns on one thread instead of three
    threads contending for the GIL (the fdi node's throughput, reports/gate_bench.md). While
    a batch is labelled, new messages wait in the subscription's DDS history (the traces
    QoS's depth), not here. Same interface and arguments as :class:`LabellingPipeline`.

    Parameters
    ----------
    backend : ThreadBackend
    on_result, on_batch, on_drop, on_error
        As for :class:`LabellingPipeline` (``on_result`` runs on the flushing thread).
    max_queued : int
        Frames queued at most between two flushes; submitting to a full queue drops the oldest.
    max_batch_rows : int
        Rows per labelling pass at most.
    name : str
        Unused (no thread to name); accepted as :class:`LabellingPipeline` takes it.
    """

    def __init__(self, backend, on_result: Callable, *, on_batch: Callable | None = None,
                 on_drop: Callable | None = None, on_error: Callable | None = None, max_queued: int = 64,
                 max_batch_rows: int = 16384, name: str = "labeller"):
        if max_queued < 1 or max_batch_rows < 1:
            raise ValueError(f"max_queued and max_batch_rows must be >= 1, got {max_queued}, {max_batch_rows}")
        self.backend = backend
        self._on_result, self._on_batch = on_result, on_batch or (lambda n, busy_s: None)
        self._on_drop = on_drop or (lambda frame: None)
        self._on_error = on_error or (lambda frame, exc: None)
        self._max_queued, self._max_rows = int(max_queued), int(max_batch_rows)
        self._queue: deque = deque()  # (frame, rows)
        self._cv = threading.Condition()  # close() and wait_idle() may come from another thread
        self._flushing = None  # the thread in flush(), or None
        self._closed = False

    def submit(self, frame) -> None:
        """Queue one decoded frame (``.traces`` (n, n_samples), ``.first_nozzle``) for the next flush."""
        with self._cv:
            if self._closed:
                raise RuntimeError("the labelling pipeline is closed")
            dropped = push_bounded(self._queue, frame, frame.traces.shape[0], self._max_queued)
        if dropped is not None:
            self._on_drop(dropped)

    def flush(self, keep_going: Callable | None = None, refill: Callable | None = None) -> None:
        """Label every queued frame and hand out its result, on this thread; returns when none is left.

        Each batch taken from the queue is screened at once (the healthy gate); the detector
        runs on the rows they left once nothing more is queued, ``max_batch_rows`` rows of
        frames are screened, or they left :data:`DEFER_ROWS` rows: one detector pass for a
        burst of messages that arrive while the first of them are screened, not one per
        executor wake-up (the pass's fixed cost, reports/gate_bench.md). ``refill()``
        (optional) is asked for more before the first detector pass of the flush: it submits
        what has arrived meanwhile and returns whether it did; what it raises ends the flush
        (after the frames screened are labelled and handed out). After that pass the flush
        labels what is still queued and returns, so a caller under sustained load gets its
        thread back. Frames of one dtype get the same labels however they are grouped.

        ``keep_going()`` (optional) is asked before each batch: False stops the flush (the frames
        screened are labelled and handed out first), and what is still queued waits for the
        next one (or is dropped by :meth:`close`), as when the node's context is shut down by a
        signal in the middle of a burst.
        """
        me = threading.current_thread()
        with self._cv:
            if self._flushing is not None:  # re-entered from a callback: the running flush takes them
                return
            self._flushing = me
        staged = hasattr(self.backend, "screen")
        pending: list = []  # (frames, token) screened, waiting for the detector
        n_rows, n_left, busy_s = 0, 0, 0.0
        try:
            while keep_going is None or keep_going():
                batch = self._take(self._max_rows - n_rows if pending else None)
                if batch and staged:
                    try:
                        token, left, dt = self.backend.screen([f.traces for f in batch],
                                                              [f.first_nozzle for f in batch])
                    except Exception as exc:  # noqa: BLE001 - the batch is lost: each of its frames fails
                        token, left, dt = _all_failed(len(batch), exc), 0, 0.0
                    except BaseException as exc:  # KeyboardInterrupt, SystemExit: taken, so reported failed
                        self._fail(batch, exc)
                        raise
                    pending.append((batch, token))
                    n_rows += sum(f.traces.shape[0] for f in batch)
                    n_left += left
                    busy_s += dt
                    if (n_rows < self._max_rows and n_left < DEFER_ROWS
                            and (self._queue or (refill is not None and refill()))):
                        continue  # more arrived: screened too before the detector's one pass
                elif batch:
                    self._label_and_hand_out(batch)
                    continue
                if not pending:
                    break  # _take ended the flush
                done, pending = pending, []  # handed out once, whatever on_result raises
                refill = None  # one refill chain per flush: the caller's callback returns under sustained load
                self._finish(done, busy_s)
                n_rows, n_left, busy_s = 0, 0, 0.0
        finally:
            try:
                if pending:  # stopped early, or raised: what was screened is still labelled and handed out
                    done, pending = pending, []
                    self._finish(done, busy_s)
            finally:
                with self._cv:
                    if self._flushing is me:  # stopped early, or raised
                        self._flushing = None
                        self._cv.notify_all()

    def _label_and_hand_out(self, batch) -> None:  # a backend without stages: each batch in one call
        try:
            self.backend.submit([f.traces for f in batch], [f.first_nozzle for f in batch])
            results, busy_s = self.backend.collect()
        except Exception as exc:  # noqa: BLE001 - the batch is lost: each of its frames fails
            results, busy_s = _all_failed(len(batch), exc), 0.0
        except BaseException as exc:  # KeyboardInterrupt, SystemExit: none handed out, each reported failed
            self._fail(batch, exc)
            raise
        self._hand_out(batch, results, busy_s)

    def _finish(self, pending, screen_s: float) -> None:
        frames = [f for batch, _ in pending for f in batch]
        try:
            results, busy_s = self.backend.finish([token for _, token in pending])
        except Exception as exc:  # noqa: BLE001 - the batches are lost: each of their frames fails
            results, busy_s = _all_failed(len(frames), exc), 0.0
        except BaseException as exc:  # KeyboardInterrupt, SystemExit: none handed out, each reported failed
            self._fail(frames, exc)
            raise
        self._hand_out(frames, results, screen_s + busy_s)

    def _hand_out(self, frames, results, busy_s: float) -> None:
        n = 0
        try:
            for frame, result in zip(frames, results):
                n += 1
                _hand_out(self._on_result, self._on_error, frame, result)
        except BaseException as exc:  # from on_result/on_error (KeyboardInterrupt, SystemExit): the rest failed
            self._fail(frames[n:], exc)
            raise
        try:
            self._on_batch(len(frames), busy_s)
        except Exception:  # noqa: BLE001 - statistics only; the pipeline goes on
            pass

    def _fail(self, frames, exc: BaseException) -> None:
        """``on_error(frame, exc)`` for frames taken and never handed out (a flush left by ``exc``)."""
        for frame in frames:
            try:
                self._on_error(frame, exc)
            except Exception:  # noqa: BLE001 - nothing more to do for this frame
                pass

    def _take(self, room: int | None = None) -> list:
        """The next batch; none left: the flush ends in the same lock (a frame submitted after it finds
        none). With ``room`` (rows, frames screened and not finished yet): frames within it only,
        and the flush goes on."""
        with self._cv:
            if room is None:
                batch = take_batch(self._queue, self._max_rows)
            else:
                batch = take_batch(self._queue, room) if self._queue and self._queue[0][1] <= room else []
            if not batch and room is None:
                self._flushing = None
                self._cv.notify_all()
            return batch

    def wait_idle(self, timeout: float | None = None) -> bool:
        """Block until nothing is queued or being labelled; False on timeout (frames submitted
        and never flushed stay queued; from ``on_result`` on the flushing thread: never idle)."""
        with self._cv:
            return self._cv.wait_for(lambda: not self._queue and self._flushing is None, timeout)

    def close(self) -> None:
        """Stop taking frames; a flush running on another thread hands out its batch first; close the backend."""
        with self._cv:
            if self._closed:
                return
            self._closed = True
            self._queue.clear()  # unlabelled, as a LabellingPipeline's queue on close
            self._cv.notify_all()  # a wait_idle elsewhere: nothing queued now
            if self._flushing not in (None, threading.current_thread()):
                self._cv.wait_for(lambda: self._flushing is None, 10.0)
        self.backend.close()
