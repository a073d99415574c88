"""The fdi node's BatchWorker (no ROS)."""

import threading
import time

import pytest

from inkdiag_ros.batching import BatchWorker


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
