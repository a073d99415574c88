"""rosbag2 bags (MCAP) of a head's topics: what they hold, and reading trace frames out of them.

A bag is a rosbag2 directory (``metadata.yaml`` plus ``*.mcap``), as
``ros2 bag record`` writes, read and written through ``rosbags`` (a pure-Python
rosbag2 reader and writer): ``inkdiag record`` writes one, ``inkdiag replay``
publishes one, and :func:`load_recording` reads the trace frames of one into the
same :class:`inkdiag_core.Recording` an ``.npz`` recording gives, so the offline
verbs take either.

Why here and not in ``inkdiag_core``: a trace frame's layout (the header in the
MultiArray's leading padding) is the wire contract, decoded only by
:func:`msg_defs.decode_traces`, and the core imports neither msg_defs nor ROS.
Each stored message (CDR, as received) is decoded by
:func:`msg_defs.decode_traces_serialized`, exactly as the fdi node decodes a live message.

Topic names in a bag are absolute (``/head_00/traces``); :data:`HEAD_TOPICS` are
the relative names :func:`head_topics` resolves under a namespace.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import importlib
import sys
from pathlib import Path

import numpy as np

from inkdiag_core.head_profile import same_sample_rate
from inkdiag_core.recording import Recording, RecordingError, refuse_an_unclosed_bag
from inkdiag_core.recording import load_recording as load_npz_recording

from msg_defs import topics
from msg_defs.qos import DIAGNOSTICS_QOS, RELIABLE_QOS, TRACES_QOS

from ._fatal import FatalNodeError

__all__ = ["TRACES_TYPE", "HEAD_TOPICS", "BagFrames", "is_bag", "head_topics", "ros_type_name",
           "msg_class", "qos_to_rosbags", "qos_from_rosbags", "iter_bag_frames", "iter_bag_chunks",
           "read_bag_recording", "load_recording", "stream_recording", "report_stats", "BagRecorder",
           "InProcessRecording", "recording_node", "pop_record_arg", "check_new_bag", "bag_writer", "first_line",
           "check_topic_names", "is_unclosed_bag", "SalvageReader"]

#: The rosbag2 type name of a trace frame.
TRACES_TYPE = "std_msgs/msg/Float32MultiArray"

#: The head's topics ``inkdiag record`` records by default: relative name -> (type, QoS it subscribes with).
HEAD_TOPICS = {
    topics.TRACES: (TRACES_TYPE, TRACES_QOS),
    topics.LABELS: ("std_msgs/msg/String", RELIABLE_QOS),
    topics.DRYING_NOZZLES: ("std_msgs/msg/String", RELIABLE_QOS),
    topics.FM_ESTIMATES: ("std_msgs/msg/String", RELIABLE_QOS),
    topics.FM_ESTIMATES_ARRAY: ("std_msgs/msg/Float64MultiArray", RELIABLE_QOS),
    topics.DIAGNOSTICS: ("diagnostic_msgs/msg/DiagnosticArray", DIAGNOSTICS_QOS),
}
#: Topics that may be asked for by name but are not recorded by default.
EXTRA_TOPICS = {topics.GROUND_TRUTH: ("std_msgs/msg/String", RELIABLE_QOS)}


def head_topics(namespace: str, names=None) -> dict:
    """Absolute topic name -> (type, QoS) of a head's topics under ``namespace``.

    Parameters
    ----------
    namespace : str
        E.g. ``/head_00``.
    names : iterable of str, optional
        Relative names (``traces``, ``fm_estimates/array``, ``/diagnostics``,
        ``ground_truth``); default: all of :data:`HEAD_TOPICS`.

    Raises
    ------
    ValueError
        An unknown topic name.
    """
    ns = "/" + namespace.strip("/") if namespace.strip("/") else ""
    known = {**HEAD_TOPICS, **EXTRA_TOPICS}
    out = {}
    for name in (names if names else HEAD_TOPICS):
        rel = name.strip()
        if rel not in known and rel.lstrip("/") in known:
            rel = rel.lstrip("/")
        if rel not in known:
            raise ValueError(f"unknown topic {name!r}: expected one of {', '.join(known)}")
        full = rel if rel.startswith("/") else f"{ns}/{rel}"
        out[full] = known[rel]
    check_topic_names(out, f"--namespace {namespace}")
    return out


def check_topic_names(names, what: str) -> None:
    """Refuse a topic name ROS would refuse (a token starting with a digit, a '-', '//'), before any node or file.

    Raises
    ------
    ValueError
        One line naming ``what`` (e.g. ``--namespace /2head``), the topic and why.
    """
    from rclpy.exceptions import InvalidTopicNameException
    from rclpy.validate_full_topic_name import validate_full_topic_name

    for name in names:
        try:
            validate_full_topic_name(name)
        except InvalidTopicNameException as exc:
            why = str(exc).splitlines()[0].removeprefix("Invalid topic name: ").rstrip(":")
            raise ValueError(f"{what}: {name} is not a ROS topic name ({why})") from None


def is_bag(path) -> bool:
    """Whether ``path`` is a rosbag2 directory: it has a ``metadata.yaml``, or MCAP storage files without one
    (:func:`is_unclosed_bag`: the offline verbs read what they hold, :class:`SalvageReader`)."""
    p = Path(path)
    return p.is_dir() and ((p / "metadata.yaml").is_file() or is_unclosed_bag(p))


def ros_type_name(msg_type) -> str:
    """``std_msgs/msg/String`` for the rclpy class ``std_msgs.msg.String``."""
    pkg = msg_type.__module__.split(".")[0]
    return f"{pkg}/msg/{msg_type.__name__}"


def msg_class(type_name: str):
    """The rclpy message class of a rosbag2 type name (``std_msgs/msg/String``).

    Raises
    ------
    ValueError
        A type whose Python package is not installed.
    """
    parts = type_name.split("/")
    if len(parts) != 3 or parts[1] != "msg":
        raise ValueError(f"not a ROS 2 message type name: {type_name!r}")
    try:
        return getattr(importlib.import_module(f"{parts[0]}.msg"), parts[2])
    except (ImportError, AttributeError):
        raise ValueError(f"message type {type_name} is not installed here") from None


def qos_to_rosbags(profile):
    """A ``rosbags.interfaces.Qos`` (what rosbag2's metadata stores) from an rclpy ``QoSProfile``."""
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

    def t(d):
        ns = int(getattr(d, "nanoseconds", 0))
        return QosTime(ns // 1_000_000_000, ns % 1_000_000_000)

    return Qos(history=QosHistory(int(profile.history)), depth=int(profile.depth),
               reliability=QosReliability(int(profile.reliability)),
               durability=QosDurability(int(profile.durability)),
               deadline=t(profile.deadline), lifespan=t(profile.lifespan),
               liveliness=QosLiveliness(int(profile.liveliness)),
               liveliness_lease_duration=t(profile.liveliness_lease_duration),
               avoid_ros_namespace_conventions=bool(profile.avoid_ros_namespace_conventions))


def qos_from_rosbags(qos, default):
    """An rclpy ``QoSProfile`` for publishing what a bag offered: reliability, durability, history, depth.

    Deadline, lifespan and liveliness stay rclpy's defaults (rosbag2's player does
    the same: a recorded "infinite" duration is not a valid value to set). ``qos``
    None: ``default``.
    """
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    if qos is None:
        return default
    rel = qos.reliability.value if qos.reliability.value in (1, 2) else int(default.reliability)
    dur = qos.durability.value if qos.durability.value in (1, 2) else int(default.durability)
    hist = qos.history.value if qos.history.value in (1, 2) else int(default.history)
    depth = int(qos.depth) if qos.depth > 0 else int(default.depth)
    return QoSProfile(reliability=ReliabilityPolicy(rel), durability=DurabilityPolicy(dur),
                      history=HistoryPolicy(hist), depth=depth)


#: Skipped messages :class:`BagFrames` keeps with their reasons (the others are only counted).
MAX_SKIPS_KEPT = 1000


@dataclasses.dataclass
class BagFrames:
    """What :func:`iter_bag_frames` read: counts and the frames it skipped.

    Attributes
    ----------
    topic : str
        The traces topic read.
    n_messages : int
        Messages read on it.
    skipped : list of (int, str)
        ``(message index, reason)`` of the first :data:`MAX_SKIPS_KEPT` messages that are
        not a valid trace frame (or of another sampling than the reader's, :func:`iter_bag_chunks`).
    n_skipped : int
        All skipped messages.
    report : callable, optional
        ``report(message_index, reason, frame_id)`` called for each skipped message
        as it is met (``frame_id`` None when the message did not decode).
    """

    topic: str = ""
    n_messages: int = 0
    skipped: list = dataclasses.field(default_factory=list)
    n_skipped: int = 0
    report: object = None
    salvaged: list | None = None  # read by a SalvageReader (a bag that did not open, or past a damaged chunk)
    n_listed: int | None = None  # messages on the topic metadata.yaml lists (None: it does not say)

    def skip(self, index: int, why: str, frame_id=None) -> None:
        """Count message ``index`` as skipped for ``why`` (and report it)."""
        self.n_skipped += 1
        if len(self.skipped) < MAX_SKIPS_KEPT:
            self.skipped.append((index, why))
        if self.report is not None:
            self.report(index, why, frame_id)

    def summary(self) -> str:
        """One line: frames read, and the skipped ones with their first reasons."""
        n_skip = max(self.n_skipped, len(self.skipped))
        s = f"{self.n_messages - n_skip} of {self.n_messages} messages on {self.topic} decoded"
        if n_skip:
            s += f"; skipped {n_skip}: " + "; ".join(
                f"message {i}: {why}" for i, why in self.skipped[:3]) + (" ..." if n_skip > 3 else "")
        if self.salvaged is not None:
            s += "; " + salvage_note(self.salvaged)
        return s + listed_note(self.n_listed, self.n_messages, f" on {self.topic}")


def listed_note(n_listed, n_found: int, where: str = "") -> str:
    """``; metadata.yaml lists N messages{where}: M of them not found in its files`` (or ``M more found than it
    lists``) when a bag's files hold another count than its metadata says; "" when they agree or it does not say."""
    if n_listed is None or n_listed == n_found:
        return ""
    return (f"; metadata.yaml lists {n_listed} messages{where}: " + (
        f"{n_listed - n_found} of them not found in its files" if n_listed > n_found
        else f"{n_found - n_listed} more found than it lists"))


def listed_count(bag: Path, topic: str):
    """Messages on ``topic`` that ``metadata.yaml`` lists (summed over its connections), or None when it does not
    say (no metadata.yaml, another layout)."""
    try:  # an entry listed twice (metadata.yaml edited by hand) counts once, as rosbags reads it once
        entries = {repr(t): t for t in _bag_info(bag)["topics_with_message_count"]}.values()
        counts = [int(t["message_count"]) for t in entries if t["topic_metadata"]["name"] == topic]
    except Exception:  # noqa: BLE001 - missing, unreadable or another layout: nothing to compare with
        return None
    return sum(counts) if counts else None


def salvage_note(damage) -> str:
    """What a :class:`SalvageReader` says of a bag, ``damage`` its :attr:`SalvageReader.damage` lines."""
    return ("read from its MCAP files as they are (a bag its recorder did not close, a file cut short, or a damaged "
            "chunk): " + ("; ".join(damage) if damage else "no damage found"))


def open_reader(bag_dir, *, salvage: bool = False):
    """An open ``rosbags`` Reader of ``bag_dir``; RecordingError (one line, naming it) if it is none or does not open.

    ``salvage``: a bag that does not open (an MCAP file without its summary: a recorder that died, a
    copy cut short) or has no ``metadata.yaml`` (its recorder stopped before it closed the bag) is read
    by a :class:`SalvageReader` instead, if it has MCAP files.
    """
    from rosbags.rosbag2 import Reader

    src = str(bag_dir)
    p = Path(bag_dir)
    if not p.exists():
        raise RecordingError(f"{src}: no such bag")
    if not (p / "metadata.yaml").is_file():
        if salvage and is_unclosed_bag(p):
            return SalvageReader(p)
        refuse_an_unclosed_bag(p)
        raise RecordingError(f"{src}: not a rosbag2 bag (a directory with a metadata.yaml)")
    try:
        reader = Reader(p)
        reader.open()
    except Exception as exc:  # rosbags' ReaderError, or a storage error of a damaged file
        if salvage and any(p.glob("*.mcap")):
            salvaged = SalvageReader(p)
            if not _bag_info(p):  # its metadata.yaml is what did not read (not a file cut short): say so
                salvaged.damage.insert(0, f"its metadata.yaml could not be read ({first_line(exc)})")
            return salvaged
        raise RecordingError(f"{src}: cannot open the bag{_listed(p)}: {first_line(exc)}") from None
    return reader


def is_unclosed_bag(path) -> bool:
    """Whether ``path`` is a directory of MCAP storage files without a ``metadata.yaml`` (a bag whose recorder
    stopped, or has not yet stopped, before it closed the bag)."""
    p = Path(path)
    return p.is_dir() and not (p / "metadata.yaml").is_file() and any(p.glob("*.mcap"))


def _bag_info(bag: Path) -> dict:
    """``metadata.yaml``'s ``rosbag2_bagfile_information``, or {} when there is none or it cannot be read."""
    try:
        import yaml

        info = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
        return info if isinstance(info, dict) else {}
    except Exception:  # noqa: BLE001 - missing, unreadable, not YAML, another layout: nothing to say
        return {}


def _storage_order(bag: Path) -> list:
    """The bag's MCAP files in recording order: ``metadata.yaml``'s list where it names them all, else by name
    with a numbered suffix in numeric order (rosbag2's ``run_2.mcap`` before ``run_10.mcap``)."""
    import re

    files = list(bag.glob("*.mcap"))
    try:
        listed = [bag / f for f in _bag_info(bag).get("relative_file_paths", [])]
        if listed and sorted(listed) == sorted(files):
            return listed
    except TypeError:  # not a list of names
        pass
    return sorted(files, key=lambda f: [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", f.name)])


def _missing_files(bag: Path) -> list:
    """The storage files ``metadata.yaml`` lists that are not in ``bag`` (none when it does not list any)."""
    try:
        listed = [bag / f for f in _bag_info(bag).get("relative_file_paths", [])]
    except TypeError:  # not a list of names
        return []
    return [f for f in listed if not f.is_file()]


def _summary_channels(path):
    """An MCAP file's channels from its summary section, ``{id: (channel, schema name)}``; None when it has none or
    it does not read (a file cut off before its end: its records are scanned instead)."""
    from mcap.reader import make_reader

    try:
        with open(path, "rb") as f:
            summary = make_reader(f).get_summary()
    except Exception:  # noqa: BLE001 - no footer, a damaged summary: scanned from the start
        return None
    if summary is None or not summary.channels:
        return None
    return {i: (ch, summary.schemas[ch.schema_id].name if ch.schema_id in summary.schemas else "")
            for i, ch in summary.channels.items()}


@dataclasses.dataclass(frozen=True)
class _Connection:
    """A topic of a :class:`SalvageReader`: as much of a ``rosbags`` Connection as the readers here use."""

    topic: str
    msgtype: str
    offered_qos_profiles: tuple = ()  # rosbags.interfaces.Qos, from the MCAP channel record's metadata

    @property
    def ext(self):  # rosbags' ``connection.ext.offered_qos_profiles``
        return self


def _channel_qos(channel) -> tuple:
    """The QoS profiles an MCAP channel record says its publishers offered (rosbag2 writes them into each
    channel's metadata); () when it says none or they do not parse."""
    from rosbags.rosbag2.metadata import parse_qos

    try:
        return tuple(parse_qos((channel.metadata or {}).get("offered_qos_profiles", "")))
    except Exception:  # noqa: BLE001 - not YAML, another layout: msg_defs' profile for its kind of topic instead
        return ()


class SalvageReader:
    """The messages a bag's MCAP storage files still hold when ``rosbags`` cannot open the bag, or
    cannot read on past a damaged chunk.

    A recorder that died (power lost, SIGKILL) leaves its last file without the MCAP summary
    that ``rosbags`` needs to open it, and no ``metadata.yaml``; a copy cut short does the same.
    This reads each file from its start with the ``mcap`` library's stream reader (no summary
    needed), the files in recording order (:func:`_storage_order`), chunk by chunk, each chunk's CRC
    checked: a damaged chunk costs only its own messages (how many: the message index records that
    follow it, where the file has them), and a file stops where it is cut off. A file's channels are
    those its summary section lists, or, in a file without one (cut off), those of a first pass over
    its records (a chunk after a damaged one may use a channel the damaged one declared).
    Same interface as the part of ``rosbags``' Reader that :func:`iter_bag_frames` uses:
    :attr:`connections` and :meth:`messages`, in file order. :attr:`damage` says what was lost.
    """

    def __init__(self, bag: Path):
        self.files = _storage_order(Path(bag))
        self.damage: list = []  # one line per file that is missing, cut off, per damaged chunk
        self._said = set()  # what the files say of their damage is said once (both passes meet it)
        for f in _missing_files(Path(bag)):
            self._say(f"{f}: listed in metadata.yaml, not in the bag: its messages lost")
        self._channels = [_summary_channels(f) for f in self.files]  # per file: channel id -> (channel, schema name)
        for k, ch, schema_name in self._records(messages=False, files=[k for k, c in enumerate(self._channels)
                                                                      if c is None]):
            self._channels[k] = self._channels[k] or {}
            self._channels[k].setdefault(ch.id, (ch, schema_name))
        conns = {}
        for chans in self._channels:
            for ch, schema_name in (chans or {}).values():
                if (ch.topic, schema_name) not in conns:
                    conns[ch.topic, schema_name] = _Connection(ch.topic, schema_name, _channel_qos(ch))
        self.connections = list(conns.values())

    def _records(self, messages: bool, files=None):
        """``(file_index, channel, schema_name)`` per Channel record met (``messages`` False; the files of
        index in ``files``, default all), or ``(channel, schema_name, message)`` per Message record
        (``messages`` True)."""
        from mcap.records import Channel, Chunk, Message, MessageIndex, Schema
        from mcap.stream_reader import StreamReader, breakup_chunk

        for k, path in enumerate(self.files):
            if files is not None and k not in files:
                continue
            schemas, n_msgs = {}, 0
            known = (self._channels[k] or {}) if messages else {}
            channels = {i: ch for i, (ch, _) in known.items()}
            names = {i: name for i, (_, name) in known.items()}
            chunk = None  # the last chunk: [why it is damaged or None, messages read from it, messages its index lists]
            with open(path, "rb") as f:
                records = StreamReader(f, emit_chunks=True, record_size_limit=1 << 30).records
                while True:
                    try:
                        rec = next(records)
                    except StopIteration:
                        break
                    except Exception as exc:  # noqa: BLE001 - cut off here, or garbage from here: the file ends
                        self._say(f"{path}: cut off after {n_msgs} messages of all its topics ({first_line(exc)})")
                        break
                    if chunk is not None:
                        if isinstance(rec, MessageIndex):  # the chunk's own: how many messages it held
                            chunk[2] += len(rec.records)
                            continue
                        self._check_chunk(path, *chunk)
                        chunk = None
                    inner = [rec]
                    if isinstance(rec, Chunk):
                        try:
                            inner = breakup_chunk(rec, validate_crc=True)
                        except Exception as exc:  # noqa: BLE001 - a damaged chunk: its messages are lost, not the rest
                            chunk = [first_line(exc), 0, 0]
                            continue
                        chunk = [None, sum(isinstance(r, Message) for r in inner), 0]
                    for r in inner:
                        if isinstance(r, Schema):
                            schemas[r.id] = r.name
                        elif isinstance(r, Channel):
                            channels[r.id] = r
                            if not messages:
                                yield k, r, schemas.get(r.schema_id, "")
                        elif isinstance(r, Message) and r.channel_id in channels:
                            n_msgs += 1
                            if messages:
                                ch = channels[r.channel_id]
                                yield ch, schemas.get(ch.schema_id, names.get(r.channel_id, "")), r
            if chunk is not None:
                self._check_chunk(path, *chunk)

    def _check_chunk(self, path, why, n_read: int, n_listed: int) -> None:
        """Say a chunk that did not read (``why``), or gave fewer messages than its message index lists (its
        records end early: a record that claims a wrong length)."""
        if why is not None:
            lost = f"its {n_listed} messages of all topics lost" if n_listed else "its messages lost"
            self._say(f"{path}: a damaged chunk skipped ({why}): {lost}")
        elif n_read < n_listed:
            self._say(f"{path}: a damaged chunk: {n_read} of the {n_listed} messages of all topics its index lists "
                      "read (its records end early)")

    def _say(self, line: str) -> None:
        if line not in self._said:
            self._said.add(line)
            self.damage.append(line)

    def messages(self, connections=()):
        """``(connection, log_time_ns, rawdata)`` of each message on ``connections``' topics, in file order."""
        wanted = {(c.topic, c.msgtype): c for c in connections}
        for ch, schema_name, msg in self._records(messages=True):
            conn = wanted.get((ch.topic, schema_name))
            if conn is not None:
                yield conn, msg.log_time, msg.data

    def close(self) -> None:
        pass


def _listed(bag: Path) -> str:
    """`` (FILE, 0 of the N messages metadata.yaml lists readable: truncated or corrupt)`` where it says so."""
    try:
        info = _bag_info(bag)
        files = ", ".join(str(bag / f) for f in info.get("relative_file_paths", []))
        return f" ({files}: 0 of the {int(info['message_count'])} messages metadata.yaml lists readable)"
    except Exception:  # noqa: BLE001 - metadata.yaml does not say
        return ""


def storage_files(bag: Path) -> str:
    """`` (FILE, ...)``: the bag's storage files metadata.yaml lists, or nothing if it cannot be read."""
    try:
        return " (" + ", ".join(str(bag / f) for f in _bag_info(bag)["relative_file_paths"]) + ")"
    except Exception:  # noqa: BLE001 - metadata.yaml does not say
        return ""


def first_line(exc) -> str:
    """The first line of an exception's message, or its type's name when the message is empty (for one-line errors)."""
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def _unlisted_topics(reader, src) -> list:
    """Topics the MCAP files of a bag ``rosbags`` opened hold in their summaries that ``metadata.yaml`` does not list
    (it lists what a reader sees: a file edited by hand); [] for a :class:`SalvageReader` (it reads the files)."""
    if isinstance(reader, SalvageReader):
        return []
    listed = {c.topic for c in reader.connections}
    bag, stored = Path(src), set()
    try:  # the files metadata.yaml names (not a stray .mcap beside them), else every one
        files = [f for f in (bag / n for n in _bag_info(bag).get("relative_file_paths", [])) if f.is_file()]
    except TypeError:  # not a list of names
        files = []
    for f in files or sorted(bag.glob("*.mcap")):
        stored |= {ch.topic for ch, _ in (_summary_channels(f) or {}).values()}
    return sorted(stored - listed)


def _not_listed(reader, src, wanted) -> str:
    """``; its storage files hold T, which metadata.yaml does not list ...`` for the ``wanted(topic)`` topics
    :func:`_unlisted_topics` finds, or ``""``."""
    hidden = [t for t in _unlisted_topics(reader, src) if wanted(t)]
    return (f"; its storage files hold {', '.join(hidden)}, which metadata.yaml does not list (edited by hand? "
            "rosbag2 lists every topic it recorded)" if hidden else "")


def _traces_connections(reader, topic, src):
    conns = reader.connections
    if topic is None:
        named = sorted({c.topic for c in conns if c.topic.endswith("/" + topics.TRACES)})
        cands = sorted({c.topic for c in conns if c.msgtype == TRACES_TYPE and c.topic in named})
        if len(cands) > 1:
            raise RecordingError(f"{src}: {len(cands)} traces topics ({', '.join(cands)}): choose one with --topic")
        if not cands and len(named) != 1:
            have = ", ".join(f"{c.topic} ({c.msgtype})" for c in conns) or "no topics"
            hidden = _not_listed(reader, src, lambda t: t.endswith("/" + topics.TRACES))
            raise RecordingError(f"{src}: no {TRACES_TYPE} traces topic (it has {have})"
                                 + (hidden or "; choose one with --topic"))
        topic = cands[0] if cands else named[0]  # one traces topic of another type: refused below
    sel = [c for c in conns if c.topic == topic]
    if not sel:
        raise RecordingError(f"{src}: no topic {topic} in the bag (it has "
                             f"{', '.join(sorted({c.topic for c in conns})) or 'no topics'})"
                             + _not_listed(reader, src, lambda t: t == topic))
    other = sorted({c.msgtype for c in sel if c.msgtype != TRACES_TYPE})
    if other:
        raise RecordingError(f"{src}: topic {topic} is {other[0]}, not {TRACES_TYPE} trace frames")
    return topic, sel


def _unread(messages, last_ns, n_at_last: int):
    """``messages`` but those ``rosbags`` gave already: it gives a bag's messages in log-time order, so those before
    ``last_ns`` (the log time of the last it gave; None: none) and the first ``n_at_last`` at it."""
    for conn, t_ns, raw in messages:
        if last_ns is not None and t_ns <= last_ns:
            if t_ns < last_ns or n_at_last > 0:
                n_at_last -= t_ns == last_ns
                continue
        yield conn, t_ns, raw


def check_salvage_has_topics(reader, src) -> None:
    """RecordingError if ``reader`` is a :class:`SalvageReader` that found no complete channel record (none to read)."""
    if isinstance(reader, SalvageReader) and not reader.connections:
        what = "not a closed rosbag2 bag" if not (Path(src) / "metadata.yaml").is_file() else "cannot open the bag"
        raise RecordingError(f"{src}: {what}{_listed(Path(src))}, and its MCAP files hold no complete message "
                             f"either: {'; '.join(reader.damage) or 'no topics'}")


def read_on(reader, conns, bag: Path, reselect, broken_off, on_salvage=None):
    """Yield ``(connection, log_time_ns, raw)`` of ``reader.messages(connections=conns)``, read on past damage.

    Where ``rosbags`` cannot read on (a damaged chunk of an MCAP bag it opened), the rest is read by a
    :class:`SalvageReader` of ``bag`` (its connections: ``reselect(salvage_reader)``; ``on_salvage(salvage_reader)``
    is called at the switch), skipping what was read already (:func:`_unread`): each message once. Where
    it cannot read on (a SalvageReader's own file, a bag without MCAP files), ``broken_off(exc)`` is raised
    (an exception, one line). The caller closes ``reader``.
    """
    it = reader.messages(connections=conns)
    last = (None, 0)  # the log time of the last message read, and how many were read at it
    while True:
        try:
            item = next(it)
        except StopIteration:
            return
        except Exception as exc:  # a truncated or damaged storage file
            if isinstance(reader, SalvageReader) or not any(bag.glob("*.mcap")):
                raise broken_off(exc) from None
            try:  # a damaged chunk of a bag that opened: on past it, as a bag that does not open
                reader = SalvageReader(bag)
                conns = reselect(reader)
            except Exception:  # noqa: BLE001 - its files do not read either (permissions...): as before
                raise broken_off(exc) from None
            if on_salvage is not None:
                on_salvage(reader)
            it = _unread(reader.messages(connections=conns), *last)
            continue
        last = (item[1], last[1] + 1 if item[1] == last[0] else 1)
        yield item


def iter_bag_frames(bag_dir, *, topic: str | None = None, stats: BagFrames | None = None):
    """Stream the trace frames of a bag, one decoded frame per message, in bag order.

    Parameters
    ----------
    bag_dir : str or os.PathLike
        A rosbag2 directory.
    topic : str, optional
        The traces topic (absolute, e.g. ``/head_00/traces``); default: the
        bag's one ``Float32MultiArray`` topic whose name ends in ``/traces``.
    stats : BagFrames, optional
        Filled as the frames are read: message count and skipped messages with reasons.

    Yields
    ------
    msg_defs.TraceFrame
        Traces (n_nozzles, n_samples) float32, V, first nozzle, frame id, sample rate
        (Hz) and stamp (s). A message that is not a valid trace frame is skipped
        and recorded in ``stats`` (it never costs the other frames). An MCAP bag that
        ``rosbags`` cannot open, or cannot read on past a damaged chunk, is read by a
        :class:`SalvageReader` (from there on: a frame is yielded once); ``stats.salvaged``
        says what was lost.

    Raises
    ------
    RecordingError
        Not a bag, a bag that cannot be opened, no such traces topic, a topic of
        another type, or a bag without MCAP files that breaks off (says how many
        messages were read).
    """
    from msg_defs import FrameError, decode_traces_serialized

    src = str(bag_dir)
    stats = stats if stats is not None else BagFrames()

    def broken_off(exc):
        return RecordingError(f"{src}: truncated or corrupt bag{storage_files(Path(src))}: {stats.n_messages} "
                              f"messages on {stats.topic} readable, then: {first_line(exc)}")

    def on_salvage(salvage_reader):
        stats.salvaged = salvage_reader.damage  # filled as the files are read

    reader = open_reader(bag_dir, salvage=True)
    with contextlib.closing(reader):
        check_salvage_has_topics(reader, src)
        if isinstance(reader, SalvageReader):
            on_salvage(reader)
        stats.topic, conns = _traces_connections(reader, topic, src)
        stats.n_listed = listed_count(Path(src), stats.topic)
        for _, _, raw in read_on(reader, conns, Path(src), lambda r: _traces_connections(r, stats.topic, src)[1],
                                 broken_off, on_salvage):
            i = stats.n_messages
            stats.n_messages += 1
            try:  # a copy: the frame's traces view it (no buffer of the reader's, which it may reuse)
                frame = decode_traces_serialized(bytes(raw), cdr_only=True)  # a bag's messages are CDR
            except FrameError as exc:
                stats.skip(i, first_line(exc))
                continue
            except Exception as exc:  # noqa: BLE001 - CDR that does not decode as a Float32MultiArray
                stats.skip(i, f"not a serialised {TRACES_TYPE}: {first_line(exc)}")
                continue
            yield frame


#: Rows per chunk :func:`iter_bag_chunks` yields at most by default (whole frames; 32 MB of 512-sample traces).
CHUNK_ROWS = 16384
#: Trace frames of another sampling than the reader's, before any of its own, after which a bag is refused.
MAX_OFF_SAMPLING = 100


def iter_bag_chunks(bag_dir, *, topic: str | None = None, stats: BagFrames | None = None,
                    max_rows: int = CHUNK_ROWS, sampling=None):
    """Stream a bag's trace frames in chunks of whole frames, each a :class:`inkdiag_core.Recording`.

    Memory stays bounded by one chunk whatever the length of the bag: the offline
    verbs label, estimate and calibrate chunk by chunk. Rows are the frames' nozzles
    in bag order: ``nozzle`` from each frame's header, ``frame_id`` and ``stamp`` (s)
    from its header. Frames of another sample rate or samples per trace than ``sampling``
    (without it: than the first decoded frame) are skipped (``stats.skip``, with the
    reason and the frame id): a bad frame first in the bag costs only itself.

    Parameters
    ----------
    bag_dir, topic, stats
        As :func:`iter_bag_frames`.
    max_rows : int
        Rows per chunk at most; a frame is never split (a frame larger than this is a chunk alone).
    sampling : (float, int, str), optional
        The sample rate (Hz, compared as :func:`inkdiag_core.head_profile.same_sample_rate` does), the
        samples per trace and whose they are (for the reason, e.g. ``"the model's head 'default',"``)
        of the head the caller reads the bag for. A bag whose first :data:`MAX_OFF_SAMPLING` trace
        frames are all of another sampling is refused there, before the rest is read: a recording of
        another head, not a few bad frames.

    Yields
    ------
    first_row : int
        Index (in the bag's rows, bag order) of the chunk's first row.
    chunk : Recording
        Its rows, traces (n, n_samples) float32, V.

    Raises
    ------
    RecordingError
        As :func:`iter_bag_frames` (a bag that breaks off: after the chunk of the frames
        read before it); a bag whose first :data:`MAX_OFF_SAMPLING` trace frames are all of
        another sampling than ``sampling``; and, once the bag is read, a bag with no decodable
        trace frame (empty, or every frame skipped: the first reasons are given).
    """
    stats = stats if stats is not None else BagFrames()
    blocks, n_rows, first_row = [], 0, 0
    fs = None  # the chunks' sample rate: the first frame kept's
    want = None if sampling is None else (float(sampling[0]), int(sampling[1]), str(sampling[2]))
    n_off = 0
    held = []  # frames of another sampling before the first kept one: reported once one is (else one error says it)
    refused = None

    def another_head():
        kinds = len({h[1] for h in held})
        how = held[0][1] if kinds == 1 else f"of {kinds} other samplings (the first {held[0][1]})"
        return RecordingError(f"{bag_dir}: {'its first' if n_off >= MAX_OFF_SAMPLING else 'all its'} {n_off} trace "
                              f"frames on {stats.topic} are {how}: a recording of another head?")

    def chunk():
        return Recording.from_arrays(np.concatenate([b[0] for b in blocks]), fs,
                                     nozzle=np.concatenate([b[1] for b in blocks]),
                                     frame_id=np.concatenate([np.full(b[0].shape[0], b[2], np.int64) for b in blocks]),
                                     stamp=np.concatenate([np.full(b[0].shape[0], b[3]) for b in blocks]),
                                     source=str(bag_dir))

    try:
        for frame in iter_bag_frames(bag_dir, topic=topic, stats=stats):
            if want is None:  # no sampling given: the first decoded frame's
                want = (frame.sample_rate_hz, frame.n_samples, "the bag's first frame,")
            want_fs, want_n, whose = want
            if not (same_sample_rate(frame.sample_rate_hz, want_fs) and frame.n_samples == want_n):
                off = (f"sampled at {frame.sample_rate_hz:.10g} Hz x {frame.n_samples}, not at {whose} "
                       f"{want_fs:.10g} Hz x {want_n}")
                n_off += 1
                if fs is not None:
                    stats.skip(stats.n_messages - 1, off, frame.frame_id)
                    continue
                held.append((stats.n_messages - 1, off, frame.frame_id))
                if n_off >= MAX_OFF_SAMPLING:  # not one good frame yet: another head's bag
                    refused = another_head()
                    raise refused
                continue
            if fs is None:
                fs = frame.sample_rate_hz
                for h in held:
                    stats.skip(*h)
                held.clear()
            if blocks and n_rows + frame.n_nozzles > max_rows:
                yield first_row, chunk()
                first_row += n_rows
                blocks, n_rows = [], 0
            # a copy: the frame is a view into its message
            blocks.append((np.array(frame.traces), np.asarray(frame.nozzle_ids, np.int64), frame.frame_id, frame.stamp))
            n_rows += frame.n_nozzles
    except RecordingError as exc:  # the bag broke off (or is another head's): the frames read before it are given
        if blocks:
            yield first_row, chunk()
        if exc is not refused:  # broke off: the frames held back are reported, as skipped
            for h in held:
                stats.skip(*h)
        raise
    if blocks:
        yield first_row, chunk()
    elif first_row == 0 and fs is None and held:
        raise another_head()
    elif first_row == 0:
        what = "no messages" if stats.n_messages == 0 else f"no valid trace frame ({stats.summary()})"
        hint = ""
        if stats.n_messages == 0 and stats.salvaged is not None:  # read past damage: that is why (helper-132)
            hint = "; " + salvage_note(stats.salvaged)
        elif stats.n_messages == 0 and stats.n_listed:  # listed, none read, no damage: a metadata.yaml not its files'
            hint = (f", though its metadata.yaml lists {stats.n_listed} messages on it (the topic's type and QoS text "
                    "there must be those stored in its files: edited by hand?)")
        raise RecordingError(f"{bag_dir}: {what} on {stats.topic}{hint}")


def read_bag_recording(bag_dir, *, topic: str | None = None, stats: BagFrames | None = None,
                       sampling=None) -> Recording:
    """Read a bag's trace frames into one :class:`inkdiag_core.Recording` (as ``load_recording`` gives).

    The whole bag in memory: the offline verbs stream it with :func:`iter_bag_chunks`
    instead. Rows, skipped frames (``sampling``) and errors as :func:`iter_bag_chunks`.
    """
    chunks = [c for _, c in iter_bag_chunks(bag_dir, topic=topic, stats=stats, sampling=sampling)]
    if len(chunks) == 1:
        return chunks[0]
    return Recording.from_arrays(np.concatenate([c.traces for c in chunks]), chunks[0].sample_rate_hz,
                                 nozzle=np.concatenate([c.nozzle for c in chunks]),
                                 frame_id=np.concatenate([c.frame_id for c in chunks]),
                                 stamp=np.concatenate([c.stamp for c in chunks]), source=str(bag_dir))


def load_recording(path, *, topic: str | None = None, stats: BagFrames | None = None, sampling=None) -> Recording:
    """A recording from an ``.npz`` file or a rosbag2 bag directory (dispatch on what ``path`` is).

    ``topic``, ``stats`` and ``sampling``: for a bag, as :func:`read_bag_recording`; an ``.npz``
    has no topics (``topic`` given for one is an error).
    """
    if is_bag(path):
        return read_bag_recording(path, topic=topic, stats=stats, sampling=sampling)
    if topic is not None:
        raise RecordingError(f"{path}: --topic is for a bag directory; this is not one")
    return load_npz_recording(path)


class BagRecorder:
    """Raw subscriptions of one node, each writing what it receives into a rosbags rosbag2 writer.

    Used by ``inkdiag record`` (a node of its own) and :class:`InProcessRecording`.

    Parameters
    ----------
    node : rclpy.node.Node
    writer : rosbags.rosbag2.Writer
        Open.
    wanted : dict
        Absolute topic -> (type name, subscription QoS), from :func:`inkdiag_ros.bags.head_topics`.

    ``node`` None: no subscriptions, the topics listed at :meth:`finish` with no message (a recording stopped by
    a signal as its node was built: its bag lists the same topics as one stopped a moment later, helper-140).
    """

    def __init__(self, node, writer, wanted):
        from rosbags.typesys import Stores, get_typestore

        self.node, self.writer, self.wanted = node, writer, wanted
        self.typestore = get_typestore(Stores.ROS2_JAZZY)
        self.connections = {}
        self.counts = dict.fromkeys(wanted, 0)
        self.failed = None  # the BagWriteError of the first write that failed: nothing is written after it
        self._last_ns = 0  # the log time of the last message written
        self._subs = {topic: node.create_subscription(msg_class(t), topic, self._callback(topic), qos, raw=True)
                      for topic, (t, qos) in wanted.items()} if node is not None else {}

    def _offered(self, topic):
        """The QoS profiles the topic's publishers offer (the subscription's own when none is seen)."""
        try:
            infos = self.node.get_publishers_info_by_topic(topic)
        except Exception:  # the context went down (a signal): no graph to ask any more
            infos = []
        profiles = [qos_to_rosbags(i.qos_profile) for i in infos]
        return profiles or [qos_to_rosbags(self.wanted[topic][1])]

    def connection(self, topic):
        """The bag connection of ``topic``, added (with its offered QoS) at its first message."""
        conn = self.connections.get(topic)
        if conn is None:
            conn = self.writer.add_connection(topic, self.wanted[topic][0], typestore=self.typestore,
                                              offered_qos_profiles=self._offered(topic))
            self.connections[topic] = conn
        return conn

    def _callback(self, topic):
        def on_message(raw):
            self._write(topic, self.node.get_clock().now().nanoseconds, raw)
        return on_message

    def _write(self, topic, stamp: int, raw) -> None:
        """Write ``raw`` at log time ``stamp`` (ns), or at the last one written if that is later: the bag's log
        times never go backwards in its files (a reader of the files as they are reads them in that order)."""
        if self.failed is not None:
            return
        stamp = max(stamp, self._last_ns)
        try:
            self.writer.write(self.connection(topic), stamp, raw)
        except OSError as exc:  # a full disk: the messages written so far stay readable (close_writer)
            self.failed = BagWriteError.of(self.writer, exc)
            raise self.failed from exc
        self._last_ns = stamp
        self.counts[topic] += 1

    def drain(self) -> int:
        """Write the messages received but not yet handed to a callback; returns how many.

        A stop (SIGINT/SIGTERM) ends the spin loop between two callbacks: a frame's trace message
        could be in the bag and its ground truth, received a moment later, still queued on its
        subscription. Call it once the executor is down. They are written in the order they were
        received, each stamped with its receive time, or with the last log time written if that is
        later (a callback stamps a message when it runs, after its receipt). At most a queue's depth
        per topic (a publisher in another process goes on publishing meanwhile).
        """
        from ._spin import take_queued

        if self.failed is not None:
            return 0
        queued = []
        for topic, sub in self._subs.items():
            try:
                for raw, info in take_queued(sub, max(self.wanted[topic][1].depth, 1), with_info=True):
                    stamp = info.get("received_timestamp") or self.node.get_clock().now().nanoseconds
                    queued.append((stamp, len(queued), topic, raw))
            except Exception:  # the node or its context is gone already: nothing more to take
                pass
        for stamp, _, topic, raw in sorted(queued):
            self._write(topic, stamp, raw)
        return len(queued)

    def finish(self):
        """Write what is still queued (:meth:`drain`) and add the topics that had no message (so the metadata
        lists every recorded topic)."""
        self.drain()
        if self.failed is None:
            for topic in self.wanted:
                self.connection(topic)

    def destroy(self):
        """Drop the subscriptions (no message is written after this)."""
        for sub in self._subs.values():
            try:
                self.node.destroy_subscription(sub)
            except Exception:  # the node or its context is gone already
                pass
        self._subs = {}


class BagWriteError(FatalNodeError, OSError):
    """A recording's write failed (a full disk): the recording stops there, the process with one line
    (``inkdiag record``, ``--record``: exit status 2)."""

    @classmethod
    def of(cls, writer, exc: OSError) -> "BagWriteError":
        """``recording into BAG failed: <exc>`` for ``writer``'s bag."""
        return cls(f"recording into {getattr(writer, 'path', 'the bag')} failed: {exc}")


def close_writer(writer, recorder) -> bool:
    """Close ``writer`` (its last chunk, the MCAP summary, metadata.yaml); True if it closed.

    After ``recorder``'s write failed (:attr:`BagRecorder.failed`), closing writes to the same full disk and
    may fail too: that second error is not raised (the first says what happened) and False comes back, the
    bag left as its files are (the offline verbs and ``inkdiag replay`` read on past the damage). A close
    that is the first to fail (the writer holds a chunk, up to 1 MiB, until then: a short recording meets a
    full disk only here) raises a :class:`BagWriteError`, which ``recorder`` keeps as its failure too."""
    try:
        writer.close()
    except OSError as exc:
        if recorder is not None and recorder.failed is not None:
            return False
        failed = BagWriteError.of(writer, exc)
        if recorder is not None:
            recorder.failed = failed
        raise failed from exc
    return True


def recording_summary(bag, counts: dict, failed, closed: bool) -> str:
    """The last line of a recording: ``wrote N messages to BAG: topic n, ...``; after a failed write (``failed``),
    what was left of the bag (``closed``: its writer closed all the same)."""
    per_topic = ", ".join(f"{t} {n}" for t, n in counts.items())
    if failed is None:
        return f"wrote {sum(counts.values())} messages to {bag}: {per_topic}"
    return (f"{bag}: a write failed after {sum(counts.values())} messages ({per_topic}); "
            + ("the bag is closed" if closed else "the bag could not be closed and the messages of its last chunk "
               "are lost: inkdiag replay and the offline verbs read the others"))


def pop_record_arg(argv):
    """``(argv without --record BAG_DIR, BAG_DIR or None)``: a node's own ``--record`` option.

    Only the arguments before ``--ros-args`` are looked at (ROS arguments pass through).

    Raises
    ------
    ValueError
        ``--record`` without a directory.
    """
    argv = list(argv)
    end = argv.index("--ros-args") if "--ros-args" in argv else len(argv)
    for i, a in enumerate(argv[:end]):
        if a == "--record" or a.startswith("--record="):
            if "=" in a:
                return argv[:i] + argv[i + 1:], a.split("=", 1)[1]
            if i + 1 >= end:
                raise ValueError("--record needs a bag directory: --record BAG_DIR")
            return argv[:i] + argv[i + 2:], argv[i + 1]
    return argv, None


def bag_writer(bag_dir, version: int = 8):
    """A rosbag2 MCAP writer (``rosbags.rosbag2.Writer``, not opened) for a new bag, whose chunks carry their
    CRC-32: ``inkdiag record`` and ``--record`` write with it.

    rosbags' own MCAP writer leaves every chunk's ``uncompressed_crc`` at 0 ("not computed"): a byte
    flipped inside a trace of such a bag reads as a plausible trace and is labelled without a word. With
    the CRC, readers that check it (rosbags; the ``mcap`` library with ``validate_crcs``) refuse the damaged
    chunk: the offline verbs leave its messages out and say so (:func:`iter_bag_frames`).
    """
    from rosbags.rosbag2 import StoragePlugin

    return _crc_writer_class()(bag_dir, version=version, storage_plugin=StoragePlugin.MCAP)


@functools.cache
def _crc_writer_class():  # built on first use: rosbags is imported only then, as everywhere here
    from binascii import crc32

    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.rosbag2.storage_mcap import McapWriter

    class CrcMcapWriter(McapWriter):
        def close_chunk(self) -> None:
            crc = crc32(self.chunk.bio.getbuffer())  # of the chunk's uncompressed records, as MCAP defines it
            start = self.bio.tell()  # the Chunk record is the first thing close_chunk writes
            super().close_chunk()
            end = self.bio.tell()
            self.bio.seek(start + _CHUNK_CRC_OFFSET)
            self.bio.write(crc.to_bytes(4, "little"))
            self.bio.seek(end)

    class CrcWriter(Writer):
        STORAGE_PLUGINS = {**Writer.STORAGE_PLUGINS, StoragePlugin.MCAP: CrcMcapWriter}

    return CrcWriter


#: Where a Chunk record's ``uncompressed_crc`` sits: opcode (1 byte), record length (8), message start and end
#: times and uncompressed size (8 each).
_CHUNK_CRC_OFFSET = 1 + 8 + 3 * 8


def check_new_bag(bag_dir) -> Path:
    """``bag_dir`` as a Path, refused if it exists, its parent does not, or it lies inside another bag (a bag goes
    into a new directory of its own)."""
    bag = Path(bag_dir)
    if bag.exists():
        raise ValueError(f"{bag}: exists already; a bag is written into a new directory")
    if not bag.parent.is_dir():
        raise ValueError(f"{bag.parent}: no such directory")
    for up in bag.absolute().parents:  # helper-123: a bag written into another was taken (a folder that only holds
        if (up / "metadata.yaml").is_file():  # .mcap files, perhaps other tools' recordings, is no bag to refuse)
            raise ValueError(f"{bag}: inside the bag {up}; write the new bag beside it, not in it")
    return bag


class InProcessRecording:
    """A rosbag2 bag (MCAP) written from a node's own subscriptions: ``--record`` of printhead_sim and graph.

    Subscribes ``node`` (raw) to the topics and writes every message as received, as
    ``inkdiag record`` does, in the process that publishes them: nothing is lost to
    discovery or to a second process starting late. :meth:`close` (idempotent) closes
    a valid bag; call it before the node is destroyed.

    Parameters
    ----------
    node : rclpy.node.Node
        Its namespace resolves relative names.
    bag_dir : str or os.PathLike
        New directory (:func:`check_new_bag`).
    names : iterable of str, optional
        Relative topic names as :func:`head_topics` takes them (default: :data:`HEAD_TOPICS`).
    metadata_version : int
        8 (default, Humble's ``ros2 bag`` reads it) or 9.
    """

    def __init__(self, node, bag_dir, names=None, *, metadata_version: int = 8):
        self.bag = check_new_bag(bag_dir)
        self.writer = bag_writer(self.bag, metadata_version)
        self.writer.open()
        try:
            self.recorder = BagRecorder(node, self.writer, head_topics(node.get_namespace(), names))
        except Exception:
            self.writer.close()
            raise
        self._closed = False
        self.unclosed = False  # its writer did not close after a failed write (close_writer)

    def close(self) -> dict:
        """Stop recording and close the bag; returns the messages written per topic."""
        if not self._closed:
            self._closed = True
            try:
                self.recorder.finish()
            finally:
                self.recorder.destroy()
                self.unclosed = True  # until the writer says otherwise (its close may raise)
                self.unclosed = not close_writer(self.writer, self.recorder)
        return dict(self.recorder.counts)

    def summary(self) -> str:
        """:func:`recording_summary` of this recording."""
        return recording_summary(self.bag, self.recorder.counts, self.recorder.failed, not self.unclosed)


def recording_node(node_cls, bag_dir, names=None):
    """A factory for :func:`inkdiag_ros._spin.spin_node`: ``node_cls()`` recording ``names`` into ``bag_dir``.

    The bag is closed (and its summary logged) by the node's ``close_outputs()``, which
    ``spin_node`` calls after Ctrl-C / SIGTERM as after a normal stop, before the node is
    destroyed (or by ``destroy_node`` itself).
    """
    check_new_bag(bag_dir)

    def make(**kwargs):
        node = node_cls(**kwargs)
        try:
            rec = InProcessRecording(node, bag_dir, names)
        except Exception:
            node.destroy_node()
            raise
        destroy = node.destroy_node
        inner = getattr(node, "close_outputs", None)
        closed = []

        def close_outputs():  # tear_down calls it before any node is destroyed (and its deadline starts)
            if not closed:
                closed.append(True)
                try:
                    if inner is not None:  # the node's own last outputs first: the bag may record them
                        inner()
                finally:
                    try:
                        rec.close()
                    finally:  # what the bag holds, also after a failed write
                        print(rec.summary(), file=sys.stderr, flush=True)

        def destroy_node():
            close_outputs()
            return destroy()

        node.close_outputs = close_outputs
        node.destroy_node = destroy_node
        node.get_logger().info(f"recording {', '.join(rec.recorder.wanted)} into {rec.bag}")
        return node

    return make



#: Skipped messages an offline verb reports one by one on stderr (the rest are counted in its summary).
MAX_SKIPS_REPORTED = 100


def skip_reporter(path, file=None, limit: int = MAX_SKIPS_REPORTED):
    """A :attr:`BagFrames.report` for the offline verbs: one stderr line per skipped message, up to ``limit``."""
    import sys

    seen = [0]

    def report(index, why, frame_id=None):
        seen[0] += 1
        out = file or sys.stderr
        if seen[0] <= limit:
            fid = f" (frame {frame_id})" if frame_id is not None else ""
            print(f"{path}: message {index}{fid} skipped: {why}", file=out, flush=True)
        elif seen[0] == limit + 1:
            print(f"{path}: more messages skipped: counted in the summary only", file=out, flush=True)

    return report


def stream_recording(path, topic: str | None = None, *, max_rows: int = CHUNK_ROWS, file=None, sampling=None):
    """The offline verbs' reader: a recording (``.npz`` or bag) as chunks of whole frames.

    ``sampling``: a bag's frames of another sampling are skipped (:func:`iter_bag_chunks`); an
    ``.npz`` has one sample rate, which the caller checks.

    Returns
    -------
    stats : BagFrames
        Filled while the chunks are read (``stats.topic`` empty for an ``.npz``); each
        skipped message is reported on ``file`` (stderr) as it is met (:func:`skip_reporter`).
    chunks : iterator of (int, Recording)
        ``(first_row, chunk)``: an ``.npz`` is one chunk (it is read whole), a bag is
        streamed by :func:`iter_bag_chunks` (``max_rows`` rows a chunk at most).
    """
    stats = BagFrames(report=skip_reporter(path, file))
    if is_bag(path):
        return stats, iter_bag_chunks(path, topic=topic, stats=stats, max_rows=max_rows, sampling=sampling)
    if topic is not None:
        raise RecordingError(f"{path}: --topic is for a bag directory; this is not one")
    return stats, iter([(0, load_npz_recording(path))])


def report_stats(path, stats: BagFrames, file=None) -> None:
    """The bag's summary line on ``file`` (stderr), if ``path`` was a bag."""
    import sys

    if stats.topic:
        print(f"{path}: {stats.summary()}", file=file or sys.stderr)


def load_and_report(path, topic: str | None = None, *, file=None, sampling=None) -> Recording:
    """:func:`load_recording` for the offline verbs: a bag's frame counts and skipped frames go to ``file`` (stderr)."""
    import sys

    stats = BagFrames(report=skip_reporter(path, file))
    rec = load_recording(path, topic=topic, stats=stats, sampling=sampling)
    report_stats(path, stats, file or sys.stderr)
    return rec
