"""Labelling in a child process, so the fdi node's receiving and its classifier use two cores.

In one Python process taking, decoding, labelling and publishing share one
GIL, and the labelling runs many short numpy calls that hold it: the node uses
about one core (``scripts/bench graph``). A :class:`LabellingProcess` keeps the FDI model in
a child process and labels each batch there with
:meth:`inkdiag_core.FrameLabeller.label`: the parent copies the batch's traces into
shared memory (one memcpy; the child labels them in place) and gets the
:class:`inkdiag_core.FrameLabels` back over a pipe. The child is started with
``spawn``: it inherits no rclpy or DDS state, imports only the core, and is
given the model the parent has already verified. No ROS in here.

A child that dies (killed, out of memory) costs the batch it was labelling:
:meth:`LabellingProcess.label` raises :class:`LabellingProcessError`, and the
next call starts a new child.
"""

from __future__ import annotations

import multiprocessing
import os
import pickle
import signal
import threading
import time
from collections import deque
from multiprocessing import shared_memory

import numpy as np

__all__ = ["LabellingProcess", "LabellingProcessError"]

_ALIGN = 64  # bytes: each frame starts on a cache line


class LabellingProcessError(RuntimeError):
    """The labelling process exited or failed to start; the batch in hand is lost."""


class LabellingProcess:
    """A child process holding an FDI model that labels batches of frames.

    Batches are labelled in the order they are submitted. Up to ``depth`` may
    be out at a time: the caller submits the next batch while the child labels
    the previous one, and collects the results in order (a second thread may
    collect while one submits).

    Parameters
    ----------
    labeller : inkdiag_core.FrameLabeller, or a fitted scikit-learn classifier
        Pickled into the child once, at its start; the child labels each batch
        with its :meth:`~inkdiag_core.FrameLabeller.label`. A bare classifier (the
        previous interface) is labelled with :func:`inkdiag_core.label_frames_isolated`
        and ``fd_threshold``, ``baseline``, ``max_abs_v`` (ignored with a FrameLabeller).
    fd_threshold : float
        Fault-detection threshold of a bare classifier.
    baseline : inkdiag_core.BaselineModel, optional
        Per-nozzle baselines and their model, with a bare classifier.
    max_abs_v : float, optional
        Largest sample magnitude a sensor can produce, V, with a bare classifier.
    depth : int
        Batches submitted and not yet collected, at most; each has its own
        shared trace buffer.
    capacity_bytes : int
        Initial size of each shared trace buffer, bytes; a larger batch replaces
        its buffer with one twice as large (or as large as the batch).
    poll_s : float
        How often a waiting :meth:`collect` checks that the child is still alive, s.

    Notes
    -----
    The child ignores SIGINT (Ctrl-C reaches the whole process group; the
    parent decides when it ends) and exits when the parent closes its request
    pipe, including when the parent dies.
    """

    def __init__(self, labeller, *, fd_threshold: float = 0.5, baseline=None, max_abs_v=None, depth: int = 2,
                 capacity_bytes: int = 8 << 20, poll_s: float = 0.5):
        if depth < 1:
            raise ValueError(f"depth must be >= 1, got {depth}")
        from inkdiag_core import FrameLabeller

        if not isinstance(labeller, FrameLabeller):  # a bare pipeline (the previous interface)
            labeller = _PipelineLabeller(labeller, float(fd_threshold), baseline,
                                         None if max_abs_v is None else float(max_abs_v))
        self._args = (labeller,)
        self._poll_s = float(poll_s)
        self._ctx = multiprocessing.get_context("spawn")
        self._lock = threading.Lock()  # the child, its pipes, the buffers and the queue of batches out
        self._proc = self._requests = self._results = None
        self._generation = 0  # of the child: batches sent to a dead child fail
        self._out: deque = deque()  # generation of each batch submitted and not yet collected
        self._shm = []
        self._sent_names = [None] * depth  # the buffer name the child has for each slot
        self._next_slot = 0
        self._closed = False
        self.starts = 0  # children started so far (1 + restarts after a crash)
        self.busy_s = 0.0  # seconds the child spent labelling, summed over the batches collected
        self._fatal = None  # why no child can start (it died before it was ready): none is tried again
        try:
            for _ in range(depth):
                self._shm.append(_new_shm(max(int(capacity_bytes), _ALIGN)))
            self._start()
        except BaseException:
            self._release_shm()
            raise

    @property
    def pid(self):
        """The child's process id (None between a crash and the next start)."""
        return None if self._proc is None else self._proc.pid

    @property
    def broken(self):
        """Why no child can start (one died before it was ready: its imports or the model failed), or None."""
        return self._fatal

    @property
    def depth(self) -> int:
        """Batches that may be out at a time."""
        return len(self._shm)

    @property
    def in_flight(self) -> int:
        """Batches submitted and not yet collected."""
        return len(self._out)

    def _start(self) -> None:
        req_r, req_w = self._ctx.Pipe(duplex=False)
        res_r, res_w = self._ctx.Pipe(duplex=False)
        proc = self._ctx.Process(target=_child_main, args=(req_r, res_w, *self._args),
                                 name="fdi-labelling", daemon=True)
        # SIGINT blocked while the child starts: the mask is inherited through spawn's exec,
        # so a Ctrl-C while it imports does not kill it (it ignores SIGINT once running).
        mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        try:
            proc.start()
        except Exception as exc:  # pickling the model or spawning failed
            req_w.close()
            res_r.close()
            raise LabellingProcessError(f"the labelling process did not start: {exc!r}") from exc
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, mask)
            req_r.close()
            res_w.close()
        self._proc, self._requests, self._results = proc, req_w, res_r
        self._ready = False  # until the child says it has imported the core and unpickled the model
        self._generation += 1
        self._sent_names = [None] * len(self._shm)
        self.starts += 1

    def submit(self, frames, first_nozzles) -> None:
        """Hand a batch of frames to the child (returns at once).

        Parameters
        ----------
        frames : sequence of ndarray, each of shape (n_i, n_samples)
            Traces, V, one array per frame (one sample count); copied.
        first_nozzles : sequence of int
            Each frame's first nozzle id.

        Raises
        ------
        RuntimeError
            ``depth`` batches are already out (collect one first).
        LabellingProcessError
            The child could not be started or reached (nothing is out for this
            batch; the next call starts a new child), or this object is closed.
        """
        arrays = [np.asarray(f) for f in frames]
        firsts = [int(f) for f in first_nozzles]
        offsets, end = [], 0
        for a in arrays:
            offsets.append(end)
            end += -(-a.nbytes // _ALIGN) * _ALIGN
        meta = pickle.dumps(([(off, a.shape, a.dtype.str) for off, a in zip(offsets, arrays)], firsts),
                            protocol=pickle.HIGHEST_PROTOCOL)
        with self._lock:
            if self._closed:
                raise LabellingProcessError("the labelling process is closed")
            if self._fatal is not None:
                raise LabellingProcessError(f"the labelling process cannot start: {self._fatal}")
            if len(self._out) >= len(self._shm):
                raise RuntimeError(f"{len(self._out)} batches are out already: collect one first")
            if self._proc is None:
                self._start()
            slot = self._next_slot
            shm = self._buffer(slot, end + len(meta))
            for a, off in zip(arrays, offsets):
                np.copyto(np.ndarray(a.shape, a.dtype, buffer=shm.buf, offset=off), a)
            shm.buf[end:end + len(meta)] = meta
            name = None if self._sent_names[slot] == shm.name else shm.name
            try:
                # A few dozen bytes (the batch's layout is in the buffer): the pipe always has
                # room, so this never waits on the child, whatever it is doing.
                self._requests.send((slot, name, end, len(meta)))
            except OSError as exc:
                fatal = None
                if not self._out:  # nobody collecting: read what it said before it died
                    fatal = self._last_words()
                ready = self._ready
                code = self._reap()
                self._note_death(ready, code, fatal)
                raise LabellingProcessError(f"the labelling process exited (code {code}): {fatal or exc}; "
                                            + ("a new one starts with the next frames" if self._fatal is None
                                               else "none is started again")) from exc
            self._sent_names[slot] = shm.name
            self._next_slot = (slot + 1) % len(self._shm)
            self._out.append(self._generation)

    def _buffer(self, slot: int, nbytes: int):
        """The shared buffer of ``slot``, replaced by a larger one if it holds fewer than ``nbytes``."""
        shm = self._shm[slot]
        if nbytes > shm.size:
            grown = _new_shm(max(nbytes, 2 * shm.size))
            _unlink(shm)
            self._shm[slot] = shm = grown
        return shm

    def collect(self) -> list:
        """The labels of the oldest batch submitted and not yet collected (waits for them).

        Returns
        -------
        list
            Per frame of that batch, what the labeller's ``label`` gave: its
            :class:`inkdiag_core.FrameLabels`, or an :class:`inkdiag_core.FrameFailure`
            (a ``str`` with a bare classifier).

        Raises
        ------
        RuntimeError
            Nothing is out.
        LabellingProcessError
            The child exited before answering: this batch and every other one
            out are lost (each of their collects raises); the next submit starts
            a new child.
        """
        with self._lock:
            if not self._out:
                raise RuntimeError("no batch is out")
            generation, results, proc = self._out[0], self._results, self._proc
        try:
            if generation != self._generation or results is None:
                raise EOFError("it had this batch")
            while True:
                while not results.poll(self._poll_s):
                    if self._closed or not proc.is_alive():
                        raise EOFError
                kind, value = results.recv()
                if kind == "ready":
                    self._ready = True
                    continue
                if kind == "fatal":
                    with self._lock:
                        self._fatal = value
                    raise EOFError(value)
                self.busy_s += value[1]
                return value[0]
        except (EOFError, OSError) as exc:
            with self._lock:
                current = generation == self._generation
                ready = self._ready
                code = self._reap() if current else None
                if current:
                    self._note_death(ready, code, str(exc) or None)
            why = f": {exc}" if str(exc) else ""
            raise LabellingProcessError(
                f"the labelling process exited (code {code}){why}; a new one starts with the next frames"
            ) from exc
        finally:
            with self._lock:
                self._out.popleft()

    def _last_words(self):
        """(Lock held, nothing out.) Read the dead child's messages; its "fatal" reason, if any."""
        try:
            while self._results.poll(0):
                kind, value = self._results.recv()
                if kind == "ready":
                    self._ready = True
                elif kind == "fatal":
                    return value
        except (EOFError, OSError):
            pass
        return None

    def _note_death(self, ready: bool, code, fatal) -> None:
        """(Lock held.) A child that failed before it was ready, by its own hand (a "fatal"
        message, or an error exit: its model did not unpickle, its imports failed), means
        another would too: none is started again. One killed by a signal may be restarted."""
        if self._fatal is None and not ready and (fatal or (code is not None and code > 0)):
            self._fatal = fatal or f"it exited with code {code} before it was ready"

    def label(self, frames, first_nozzles) -> list:
        """:meth:`submit` a batch and :meth:`collect` its labels (nothing else may be out)."""
        self.submit(frames, first_nozzles)
        return self.collect()

    def _reap(self):
        """End the current child (lock held); its exit code."""
        proc, requests, results = self._proc, self._requests, self._results
        self._proc = self._requests = self._results = None
        self._generation += 1  # batches it had fail
        for conn in (requests, results):
            if conn is not None:
                conn.close()
        if proc is None:
            return None
        proc.join(1.0)
        if proc.is_alive():
            proc.kill()
            proc.join(1.0)
        return proc.exitcode

    def _release_shm(self) -> None:
        for shm in self._shm:
            _unlink(shm)
        self._shm = []

    def close(self, timeout: float = 5.0) -> None:
        """Ask the child to exit, wait ``timeout`` s for it, kill it if it has not, free the buffers.

        A :meth:`collect` waiting in another thread raises :class:`LabellingProcessError`.
        """
        with self._lock:
            if self._closed:
                return
            self._closed = True
            proc, requests = self._proc, self._requests
            if requests is not None:
                try:
                    requests.send(None)
                except OSError:
                    pass
        if proc is not None:
            proc.join(timeout)
        with self._lock:
            self._reap()
            self._release_shm()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def _new_shm(size: int):
    """A new shared buffer of ``size`` bytes with its pages reserved.

    A tmpfs segment is created sparse; were ``/dev/shm`` full, the first write to
    an unbacked page would kill the process with SIGBUS. Reserving the pages at
    once turns that into this error.
    """
    try:
        shm = shared_memory.SharedMemory(create=True, size=size)
    except OSError as exc:
        raise LabellingProcessError(f"no shared memory for the traces ({size} bytes): {exc}") from exc
    try:
        os.posix_fallocate(shm._fd, 0, size)  # SharedMemory keeps its descriptor in _fd
    except OSError as exc:
        _unlink(shm)
        raise LabellingProcessError(f"no room in /dev/shm for the traces ({size} bytes): {exc}") from exc
    return shm


def _unlink(shm) -> None:
    shm.close()
    try:
        shm.unlink()
    except FileNotFoundError:
        pass


def _child_main(requests, results, labeller) -> None:
    """The child: take batches from shared memory, label them, send the labels, until told to stop."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        import inkdiag_core  # noqa: F401 - imported before "ready": a broken install is fatal here

        from .allocator import PeriodicRelease, keep_freed_memory
        from .blas import limit_blas_threads

        keep_freed_memory()
        release = PeriodicRelease()  # as the nodes' spin loops: a drained backlog's heap goes back
        limit_blas_threads()  # as in every node process: no BLAS worker spinning beside the classifier
        results.send(("ready", None))
    except Exception as exc:  # noqa: BLE001 - reported to the parent, which raises it
        results.send(("fatal", f"{type(exc).__name__}: {exc}"))
        return
    buffers = {}  # slot -> SharedMemory
    while True:
        release()
        try:
            request = requests.recv()
        except (EOFError, OSError):  # the parent is gone
            break
        if request is None:
            break
        slot, name, meta_at, meta_len = request
        if name is not None:  # a new (or first) buffer for this slot
            if slot in buffers:
                buffers[slot].close()
            buffers[slot] = shared_memory.SharedMemory(name=name)
        t0 = time.perf_counter()
        specs, first_nozzles = pickle.loads(buffers[slot].buf[meta_at:meta_at + meta_len])
        out = _label_views(buffers[slot], specs, first_nozzles, labeller)
        results.send(("labels", (out, time.perf_counter() - t0)))
    for shm in buffers.values():
        shm.close()


def _label_views(shm, specs, first_nozzles, labeller) -> list:
    """Label the frames at ``specs`` in ``shm``; no view into the buffer outlives the call."""
    arrays = [np.ndarray(shape, dtype, buffer=shm.buf, offset=off) for off, shape, dtype in specs]
    return labeller.label(arrays, first_nozzles)


class _PipelineLabeller:
    """A bare classifier with its threshold, baselines and range check: the previous interface."""

    def __init__(self, pipeline, fd_threshold, baseline, max_abs_v):
        self.args = (pipeline, fd_threshold, baseline, max_abs_v)

    def label(self, frames, first_nozzles) -> list:
        from inkdiag_core import label_frames_isolated

        pipeline, fd_threshold, baseline, max_abs_v = self.args
        return label_frames_isolated(pipeline, frames, fd_threshold=fd_threshold, first_nozzles=first_nozzles,
                                     baseline=baseline, max_abs_v=max_abs_v)
