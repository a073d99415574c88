"""Where the fdi node's :class:`inkdiag_core.FrameLabeller` runs: one interface, two backends.

Both take a batch of frames with :meth:`submit` and give back, with
:meth:`collect` (batches in the order submitted), a :class:`LabelledBatch`: the
labeller's per-frame results (a :class:`inkdiag_core.FrameLabels`, or an
:class:`inkdiag_core.FrameFailure`) and the seconds spent labelling. Whatever
goes wrong inside a backend becomes a failure of every frame of the batch it
hit; neither method raises for a batch.

- :class:`ThreadBackend`: labels in :meth:`submit`, on the caller's thread.
- :class:`ProcessBackend`: a child process (:class:`.labelling_process.LabellingProcess`)
  runs the same labeller (pickled across), so receiving, labelling and publishing
  overlap on two cores. A child that dies fails the frames it had and the next
  batch starts a new one; a child that cannot start at all (its imports or the
  model fail) makes the backend label on the submitting thread from then on and
  say why in :attr:`ProcessBackend.config_error`.

No ROS in here.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from typing import NamedTuple, Protocol

from inkdiag_core import FrameFailure

from .labelling_process import LabellingProcess, LabellingProcessError

__all__ = ["LabelledBatch", "LabellingBackend", "ProcessBackend", "ThreadBackend", "make_backend"]


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
