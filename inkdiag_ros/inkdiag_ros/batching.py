"""A worker thread that processes queued items in adaptive batches (no ROS in here).

With ``labelling_process``, the fdi node's subscription callback only decodes
and validates a frame and hands it to a :class:`BatchWorker`; the worker thread
takes *everything* that queued up while it was busy and hands it to the child
as one batch. At a light load every batch is one frame (lowest latency); under
load the batches grow, which amortises the classifier's fixed per-call cost,
while the executor thread keeps receiving. (Without a child process the node
labels on its executor thread: :class:`.labelling_backend.InlinePipeline`.)

The queue is bounded: when it holds ``max_queued`` items the oldest one is
dropped and reported to ``on_drop``, so an overloaded node sheds load it
accounts for instead of growing without bound.

With ``max_in_flight``, ``handle`` only hands a batch on (to a labelling
process) and whoever finishes it calls :meth:`BatchWorker.finished`; the
worker takes the next batch as soon as fewer than ``max_in_flight`` are out,
so handing on, labelling and publishing overlap while batches still grow
under load.
"""

from __future__ import annotations

import threading
from collections import deque
from typing import Callable


def push_bounded(queue: deque, item, rows: int, max_queued: int):
    """Append ``(item, rows)`` to ``queue``; a queue already holding ``max_queued`` items
    loses its oldest first. Returns the dropped item, or None."""
    dropped = queue.popleft()[0] if len(queue) >= max_queued else None
    queue.append((item, int(rows)))
    return dropped


def take_batch(queue: deque, max_rows: int) -> list:
    """Pop the oldest items of ``queue`` (``(item, rows)`` pairs) while their rows stay within
    ``max_rows``; one larger item is taken alone. Returns the items, oldest first."""
    batch, rows = [], 0
    while queue and (not batch or rows + queue[0][1] <= max_rows):
        item, n = queue.popleft()
        batch.append(item)
        rows += n
    return batch


class BatchWorker:
    """Run ``handle(items)`` on one thread for every batch of queued items.

    Parameters
    ----------
    handle : callable(list) -> None
        Processes one batch, oldest item first. Exceptions it raises are passed
        to ``on_error`` and the worker goes on.
    max_queued : int
        Items waiting at most; submitting to a full queue drops the oldest.
    max_batch_rows : int
        Rows per batch at most (a single larger item is still taken alone).
    on_drop : callable(item) -> None
        Called (on the submitting thread) with each item dropped from a full queue.
    on_error : callable(BaseException) -> None
        Called on the worker thread when ``handle`` raises.
    name : str
        Thread name.
    max_in_flight : int, optional
        None: a batch is done when ``handle`` returns. An int: ``handle`` hands
        the batch on and returns, and the batch is done when :meth:`finished` is
        called for it (from any thread; not if ``handle`` raised); at most this
        many batches are out at a time.
    """

    def __init__(self, handle: Callable, *, max_queued: int = 64, max_batch_rows: int = 16384,
                 on_drop: Callable = lambda item: None, on_error: Callable = lambda exc: None,
                 name: str = "batch-worker", max_in_flight: int | None = None):
        if max_queued < 1 or max_batch_rows < 1:
            raise ValueError(f"max_queued and max_batch_rows must be >= 1, got {max_queued}, {max_batch_rows}")
        if max_in_flight is not None and max_in_flight < 1:
            raise ValueError(f"max_in_flight must be >= 1 or None, got {max_in_flight}")
        self._handle, self._on_drop, self._on_error = handle, on_drop, on_error
        self._max_queued, self._max_rows = int(max_queued), int(max_batch_rows)
        self._async = max_in_flight is not None
        self._max_in_flight = int(max_in_flight) if self._async else 1
        self._queue: deque = deque()  # (item, rows)
        self._cv = threading.Condition()
        self._stopping = False
        self._in_flight = 0  # batches taken and not yet done
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def submit(self, item, rows: int = 1) -> None:
        """Queue ``item`` (of ``rows`` rows) for the next batch."""
        with self._cv:
            if self._stopping:
                raise RuntimeError("BatchWorker is stopped")
            dropped = push_bounded(self._queue, item, rows, self._max_queued)
            self._cv.notify()
        if dropped is not None:
            self._on_drop(dropped)

    def pending(self) -> int:
        """Items queued plus batches being processed."""
        with self._cv:
            return len(self._queue) + self._in_flight

    def wait_idle(self, timeout: float | None = None) -> bool:
        """Block until nothing is queued or being processed; False on timeout."""
        with self._cv:
            return self._cv.wait_for(lambda: not self._queue and not self._in_flight, timeout)

    def finished(self) -> None:
        """One batch handed on by ``handle`` is done (``max_in_flight`` workers only)."""
        if not self._async:
            raise RuntimeError("finished() is for a BatchWorker with max_in_flight")
        with self._cv:
            if self._in_flight < 1:
                raise RuntimeError("finished() called more often than batches were handed on")
            self._in_flight -= 1
            self._cv.notify_all()

    def stop(self, timeout: float = 10.0) -> None:
        """Finish the batch in hand, drop the rest (unprocessed), join the thread."""
        with self._cv:
            self._stopping = True
            self._queue.clear()
            self._cv.notify_all()
        if self._thread is not threading.current_thread():
            self._thread.join(timeout)

    def _take(self) -> list:
        return take_batch(self._queue, self._max_rows)

    def _run(self) -> None:
        while True:
            with self._cv:
                self._cv.wait_for(lambda: (self._queue and self._in_flight < self._max_in_flight)
                                  or self._stopping)
                if self._stopping:
                    self._cv.notify_all()
                    return
                batch = self._take()
                self._in_flight += 1
            done = not self._async
            try:
                self._handle(batch)
            except BaseException as exc:  # noqa: BLE001 - reported, the worker goes on
                done = True  # not handed on: nobody will call finished() for it
                self._on_error(exc)
            finally:
                if done:
                    with self._cv:
                        self._in_flight -= 1
                        self._cv.notify_all()
