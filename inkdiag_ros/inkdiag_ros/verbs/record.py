"""``inkdiag record``: a rosbag2 bag (MCAP) of a head's topics, as ``ros2 bag record`` writes."""

HELP = "record a head's topics into a rosbag2 bag (MCAP storage)"
DESCRIPTION = """\
Subscribe to a head's topics and write every message, serialized as received
(CDR, no re-serialisation), into a new rosbag2 bag directory: metadata.yaml and
one .mcap file, storage 'mcap', each topic with its type and the QoS profiles its
publishers offered (rosbag2 metadata version 8 by default, the newest that Humble's
`ros2 bag` reads; --metadata-version 9 for Jazzy's). Message timestamps are the
receive times (ns), as `ros2 bag record` stores them.

Default topics, under --namespace: traces, labels, drying_nozzles, fm_estimates,
fm_estimates/array, and /diagnostics (ground_truth on request). It stops after
--duration seconds, or on Ctrl-C / SIGTERM, and closes a valid bag either way;
it prints the messages written per topic.

example:
  inkdiag record bags/head00_run1 --namespace /head_00 --duration 10
  inkdiag record bags/truth --namespace /head_00 --topics traces ground_truth
"""


def add_arguments(parser) -> None:
    parser.add_argument("bag", metavar="BAG_DIR", help="bag directory to create (must not exist)")
    parser.add_argument("--namespace", default="/head_00", metavar="NS", help="the head's namespace (default /head_00)")
    parser.add_argument("--topics", nargs="+", metavar="TOPIC",
                        help="topics relative to the namespace (default: traces labels drying_nozzles fm_estimates "
                        "fm_estimates/array /diagnostics)")
    parser.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S seconds (default: "
                        "until Ctrl-C / SIGTERM)")
    parser.add_argument("--metadata-version", type=int, choices=(8, 9), default=8,
                        help="rosbag2 metadata version: 8 (Humble's ros2 bag reads it, default) or 9 (Jazzy)")


def run(args) -> int:
    import sys
    import time

    import rclpy
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor

    from .._spin import stop_on_signals, tear_down
    from ..bags import BagRecorder, bag_writer, check_new_bag, close_writer, head_topics, recording_summary

    if args.duration is not None and not args.duration > 0:
        raise ValueError(f"--duration must be > 0 s, got {args.duration!r}")
    wanted = head_topics(args.namespace, args.topics)
    bag = check_new_bag(args.bag)
    with stop_on_signals() as stop:
        rclpy.init()
        writer = bag_writer(bag, args.metadata_version)
        writer.open()
        node = executor = rec = None
        try:
            try:
                node = rclpy.create_node("inkdiag_record")
                stop.attach(node)
                rec = BagRecorder(node, writer, wanted)
                executor = SingleThreadedExecutor()
                executor.add_node(node)
            except Exception:  # a signal as the node was built: rclpy invalidated the context under it (RCLError)
                if not stop.explains_an_error():
                    raise
                rec = BagRecorder(None, writer, wanted)  # the bag lists its topics, with no message
            else:
                print(f"recording {', '.join(wanted)} into {bag}", file=sys.stderr, flush=True)
                end = None if args.duration is None else time.monotonic() + args.duration
                while not stop.requested and rclpy.ok() and (end is None or time.monotonic() < end):
                    try:
                        executor.spin_once(timeout_sec=0.1 if end is None else
                                           max(0.0, min(0.1, end - time.monotonic())))
                    except ExternalShutdownException:  # SIGINT/SIGTERM through rclpy's handler
                        break
        finally:  # each step whatever the one before it raised (a full disk): the error goes on up after them
            closed = False
            try:
                if rec is not None:
                    rec.finish()  # what is still queued, and the topics that had no message
            finally:
                try:
                    closed = close_writer(writer, rec)  # metadata.yaml, the MCAP summary: a valid bag, if it can
                finally:
                    try:
                        tear_down(executor, [node])
                    finally:  # what the bag holds, also before a failed write's one-line error (cli)
                        print(recording_summary(bag, rec.counts if rec else {}, rec and rec.failed, closed),
                              file=sys.stderr)
    return 0
