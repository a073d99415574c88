"""``inkdiag replay``: publish a rosbag2 bag's messages again, with their recorded QoS and timing."""

HELP = "publish a rosbag2 bag's messages again (recorded QoS and timing)"
DESCRIPTION = """\
Publish every message of a rosbag2 bag (from `inkdiag record`, `ros2 bag record`
or any rosbag2 writer; MCAP or SQLite 3 storage), serialized as stored, on its
recorded topic with the QoS its publishers offered (reliability, durability,
history, depth; the first offered profile), spaced as recorded (--rate scales the
time: 2 is twice as fast), or back to back with --as-fast-as-possible.

Before the first message it waits (up to --wait-s) until its publishers are
matched by subscribers, and 1 s more for their side of the match: a replay
that published at once would lose its first messages to discovery. Reliable
topics are waited on to be acknowledged at the end.

A bag its recorder did not close, a file cut short or a damaged chunk (MCAP) is
read on past, as `inkdiag label` reads it: the last line says what was lost.

--namespace NS moves the head's topics: the first name component of every topic
that has more than one (/head_00/traces -> NS/traces; /diagnostics stays).
--topics keeps only those topics (relative names as in `inkdiag record`, or the
absolute recorded names).

example:
  inkdiag replay bags/head00_run1 --namespace /head_07 --rate 1
"""


def add_arguments(parser) -> None:
    parser.add_argument("bag", metavar="BAG_DIR", help="rosbag2 bag directory")
    speed = parser.add_mutually_exclusive_group()
    speed.add_argument("--rate", type=float, default=1.0, metavar="R", help="time scale (default 1: as recorded)")
    speed.add_argument("--as-fast-as-possible", action="store_true", help="publish back to back, no recorded timing")
    parser.add_argument("--namespace", default=None, metavar="NS", help="publish the head's topics under NS instead")
    parser.add_argument("--topics", nargs="+", metavar="TOPIC", help="replay only these topics")
    parser.add_argument("--loop", action="store_true", help="start again at the end (until Ctrl-C / SIGTERM)")
    parser.add_argument("--wait-s", type=float, default=10.0, metavar="S",
                        help="wait at most S seconds for subscribers before the first message (default 10)")


def remap(topic: str, namespace) -> str:
    """``topic`` under ``namespace``: its first component replaced when it has more than one."""
    if not namespace:
        return topic
    parts = topic.strip("/").split("/")
    if len(parts) < 2:
        return topic
    ns = namespace.strip("/")
    return "/" + "/".join(([ns] if ns else []) + parts[1:])


def _targets(conns, namespace) -> dict:
    """Each recorded topic of ``conns`` -> the topic it is published on (:func:`remap`).

    Raises
    ------
    ValueError
        A name ROS refuses (``--namespace /2head``), or two recorded topics published as one
        (two heads' traces under one ``--namespace``: a node would take them for one head's).
    """
    from ..bags import check_topic_names

    targets = {c.topic: remap(c.topic, namespace) for c in conns}
    check_topic_names(sorted(set(targets.values())), f"--namespace {namespace}" if namespace else "the bag")
    by_target = {}
    for topic, target in sorted(targets.items()):
        by_target.setdefault(target, []).append(topic)
    for target, topics in by_target.items():
        if len(topics) > 1:
            raise ValueError(f"--namespace {namespace}: {' and '.join(topics)} would both be published as {target}, "
                             "one head's messages mixed with another's: replay one head at a time "
                             f"(--topics {topics[0]} ...)")
    return targets


def _selected(topic: str, wanted) -> bool:
    if not wanted:
        return True
    return any(topic == w or (not w.startswith("/") and topic.endswith("/" + w)) for w in wanted)


def run(args) -> int:
    import math
    import sys
    import time
    from pathlib import Path

    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import ReliabilityPolicy

    from msg_defs.qos import RELIABLE_QOS, TRACES_QOS
    from inkdiag_core.recording import RecordingError

    from .._spin import stop_on_signals, tear_down
    from ..bags import (TRACES_TYPE, SalvageReader, check_salvage_has_topics, first_line, listed_count, listed_note,
                        msg_class, open_reader, qos_from_rosbags, read_on, salvage_note, storage_files)

    if not args.as_fast_as_possible and not (math.isfinite(args.rate) and args.rate > 0):
        raise ValueError(f"--rate must be a number > 0, got {args.rate!r}")
    if not (math.isfinite(args.wait_s) and args.wait_s >= 0):
        raise ValueError(f"--wait-s must be a number of seconds >= 0, got {args.wait_s!r}")
    bag = Path(args.bag)
    # no such bag, not a bag, one that opens neither with rosbags nor from its MCAP files: RecordingError, one line
    reader = open_reader(bag, salvage=True)
    # read from its MCAP files as they are (a bag that did not open, or past a damaged chunk): the SalvageReaders
    # of this pass over the bag, and what they found (lines, in order; None: rosbags read it all)
    salvage, damage = [], None

    def selected(r):
        if isinstance(r, SalvageReader):
            salvage.append(r)
        return [c for c in r.connections if _selected(c.topic, args.topics)]

    try:
        check_salvage_has_topics(reader, bag)
        conns = selected(reader)
        if not conns:
            has = ", ".join(sorted({c.topic for c in reader.connections})) or "none"
            raise RecordingError(f"{bag}: no topic to replay (it has {has})")
        # salvaged: not known before it is read; else metadata.yaml's counts as the offline verbs read them (an
        # entry listed twice, two rosbags connections, counts once)
        listed = [listed_count(bag, t) for t in sorted({c.topic for c in conns})]
        n_listed = None if salvage else sum(listed) if None not in listed else sum(c.msgcount for c in conns)
        if n_listed == 0:
            raise RecordingError(f"{bag}: no messages on {', '.join(sorted({c.topic for c in conns}))} to replay")
        targets = _targets(conns, args.namespace)  # bad or colliding names: ValueError, before any node
        classes = {}
        for c in conns:  # before any node: a topic of a type not installed here is named, with the way round it
            try:
                classes[c.topic, c.msgtype] = msg_class(c.msgtype)
            except ValueError as exc:
                raise RecordingError(f"{bag}: topic {c.topic}: {exc}; leave it out with --topics") from None
    except BaseException:
        reader.close()
        raise
    n_sent, no_pub = 0, {}  # messages published; (topic, type) -> messages of a topic it has no publisher for

    def broken_off(exc):
        return RecordingError(f"{bag}: truncated or corrupt bag{storage_files(bag)}: {n_sent} messages replayed, "
                              f"then: {first_line(exc)}")

    with stop_on_signals() as stop:
        node = executor = None
        try:
            try:
                rclpy.init()
                node = rclpy.create_node("inkdiag_replay")
                stop.attach(node)
                executor = SingleThreadedExecutor()
                executor.add_node(node)
                pubs = {}
                for c in conns:
                    default = TRACES_QOS if c.msgtype == TRACES_TYPE else RELIABLE_QOS
                    offered = c.ext.offered_qos_profiles
                    qos = qos_from_rosbags(offered[0] if offered else None, default)
                    pubs[c.topic, c.msgtype] = node.create_publisher(classes[c.topic, c.msgtype], targets[c.topic], qos)
            except Exception:  # a signal as the node was built: rclpy invalidated the context under it (RCLError)
                if not stop.explains_an_error():
                    raise
            else:
                _wait_for_subscribers(executor, node, list(pubs.values()), args.wait_s, stop)
                if not stop.requested:
                    print(f"replaying {'the' if n_listed is None else n_listed} messages of "
                          + ", ".join(t if targets[t] == t else f"{t} as {targets[t]}" for t in sorted(targets))
                          + f" from {bag}", file=sys.stderr, flush=True)
                    try:
                        alone = sorted({targets[topic] for (topic, msgtype), pub in pubs.items()  # the traces: what
                                        if msgtype == TRACES_TYPE and not pub.get_subscription_count()})  # it is for
                    except Exception:  # a signal took the context down meanwhile (RCLError)
                        if not stop.explains_an_error():
                            raise
                        alone, stop.requested = [], True
                    if alone:  # said, not silent: those messages go to nobody
                        try:  # a subscription the graph has but the publisher did not match: another QoS
                            unmatched = [t for t in alone if node.count_subscribers(t)]
                        except Exception:  # noqa: BLE001 - a signal took the context down meanwhile: said as before
                            unmatched = []
                        why = ("a subscription is there, not matched: of another QoS than the recording's (a reliable "
                               "reader of a best-effort topic; rclpy's warning names the policy), of another type, or "
                               "not matched yet" if unmatched else
                               "is the node's namespace the one the topic is under?")
                        print(f"inkdiag replay: warning: no subscriber on {', '.join(alone)} after {args.wait_s:g} s: "
                              f"its messages go to no node ({why})", file=sys.stderr, flush=True)
                while not stop.requested and rclpy.ok():
                    t_bag0 = t_wall0 = None
                    n_before = n_sent
                    for c, ts, raw in read_on(reader, conns, bag, selected, broken_off):
                        if stop.requested:
                            break
                        pub = pubs.get((c.topic, c.msgtype))
                        if pub is None:  # a topic only the MCAP files past a damaged chunk list: said at the end
                            no_pub[c.topic, c.msgtype] = no_pub.get((c.topic, c.msgtype), 0) + 1
                            continue
                        if t_bag0 is None:
                            t_bag0, t_wall0 = ts, time.monotonic()
                        if not args.as_fast_as_possible:
                            due = t_wall0 + (ts - t_bag0) * 1e-9 / args.rate
                            while not stop.requested and time.monotonic() < due:
                                try:
                                    executor.spin_once(timeout_sec=min(0.05, max(0.0, due - time.monotonic())))
                                except Exception:  # ExternalShutdownException, or RCLError: the context went down
                                    if not stop.explains_an_error():
                                        raise
                                    stop.requested = True
                            if stop.requested:
                                break
                        try:
                            pub.publish(bytes(raw))
                        except Exception:
                            if not stop.explains_an_error():  # else a signal took the context down meanwhile
                                raise
                            stop.requested = True
                            break
                        n_sent += 1
                    damage = _found(salvage, damage)
                    if n_sent == n_before and not stop.requested:  # none read (a --loop would spin re-reading)
                        raise RecordingError(_none_read(bag, conns, damage, no_pub))
                    if not args.loop:
                        break
                try:
                    for pub in pubs.values() if rclpy.ok() else ():  # reliable topics: the subscribers have them first
                        if pub.qos_profile.reliability == ReliabilityPolicy.RELIABLE and pub.get_subscription_count():
                            pub.wait_for_all_acked(rclpy.duration.Duration(seconds=5.0))
                except Exception:  # a signal took the context down meanwhile (RCLError)
                    if not stop.explains_an_error():
                        raise
        finally:
            reader.close()
            tear_down(executor, [node])
    damage = _found(salvage, damage)
    whole = not (args.loop or stop.requested or damage)  # one pass read to its end: as many as metadata.yaml lists?
    print(f"replayed {n_sent} messages from {bag}"
          + (listed_note(n_listed, n_sent + sum(no_pub.values())) if whole else "")
          + (f"; {_not_replayed(no_pub)}" if no_pub else "")
          + (f"; {salvage_note(list(damage))}" if damage is not None else ""), file=sys.stderr)
    return 0


def _not_replayed(no_pub: dict) -> str:
    """What ``no_pub`` ((topic, type) -> messages) says: messages read past a damaged chunk, of a topic and type
    the bag's summary (so no publisher) has not."""
    return "; ".join(f"{n} messages of {topic} ({msgtype or 'no type'}) not replayed: that topic and type are not "
                     "in the bag's summary" for (topic, msgtype), n in sorted(no_pub.items()))


def _none_read(bag, conns, damage, no_pub) -> str:
    """The error of a pass over the bag that replayed no message: what was read instead, or lost."""
    from ..bags import salvage_note

    why = f"{bag}: no messages on {', '.join(sorted({c.topic for c in conns}))} to replay"
    if no_pub:
        why += f"; {_not_replayed(no_pub)}"
    if damage is not None:
        return f"{why}; {salvage_note(list(damage))}"
    return (f"{why}: none of the messages its metadata.yaml lists was read from its storage (the topic's type and QoS "
            "text there must be those stored in its files: edited by hand?)")


def _found(salvage: list, damage):
    """``damage`` (a dict of lines, or None) with the lines of the SalvageReaders in ``salvage``, which is emptied."""
    for r in salvage:
        damage = {} if damage is None else damage
        damage.update(dict.fromkeys(r.damage))
    salvage.clear()
    return damage


# A publisher counts a subscriber as soon as its own side has matched it; the subscriber's side
# matches the publisher a little later, and a best-effort reader drops what comes before. 0.2 s
# was once too short for an fdi node on a loaded CI machine (2 of 8 frames taken); probe
# (a writer publishing at once on its match, two CPU burners): 5 of 8 taken in 1 run of 6.
READER_MATCH_GRACE_S = 1.0


def _wait_for_subscribers(executor, node, pubs, wait_s, stop):
    """Spin until every publisher is matched, or some are and 1 s more passed, or ``wait_s`` ran out; then,
    if any is matched, ``READER_MATCH_GRACE_S`` more for the subscribers' side of the match."""
    import time

    deadline = time.monotonic() + wait_s
    first_match = None

    def waiting() -> bool:
        nonlocal first_match
        matched = _matched(pubs)
        if matched is None or all(matched):
            return False
        if any(matched):
            first_match = first_match or time.monotonic()
            if time.monotonic() - first_match > 1.0:
                return False
        return time.monotonic() < deadline

    if _spin_while(executor, stop, waiting) and not stop.requested and any(_matched(pubs) or ()):
        # the readers' side matches after the writers': best-effort samples before it are dropped unseen
        grace = time.monotonic() + READER_MATCH_GRACE_S
        _spin_while(executor, stop, lambda: time.monotonic() < grace)


def _matched(pubs) -> list | None:
    """Whether each publisher has a subscriber; None once the context went down (a signal)."""
    try:
        return [p.get_subscription_count() > 0 for p in pubs]
    except Exception:  # noqa: BLE001 - the context went down
        return None


def _spin_while(executor, stop, keep_going) -> bool:
    """Spin in 50 ms steps while no stop is requested and ``keep_going()``; False if the context went down."""
    while not stop.requested and keep_going():
        try:
            executor.spin_once(timeout_sec=0.05)
        except Exception:  # noqa: BLE001 - the context went down (a signal)
            return False
    return True
