"""rosbag2 bags for the tests, written by ``rosbags`` directly (no rclpy, no msg_defs encoder).

Import as ``from _bags import write_bag`` (``pythonpath = tests`` in pytest.ini).
"""

import numpy as np

from msg_defs import HEADER_LEN, SCHEMA_VERSION

FS = 10e6
NS = "/head_00"


def typestore():
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


def frame_msg(ts, traces, *, first, frame_id, stamp_s, data_offset=HEADER_LEN, fs=FS):
    """A trace frame built with rosbags' own message classes (no rclpy, no msg_defs encoder); ``fs`` Hz."""
    ma = ts.types
    n, s = traces.shape
    head = np.array([SCHEMA_VERSION, first, frame_id, 0, fs, stamp_s, 0, 0], dtype=np.float32)
    layout = ma["std_msgs/msg/MultiArrayLayout"](
        dim=[ma["std_msgs/msg/MultiArrayDimension"](label="nozzle", size=n, stride=n * s),
             ma["std_msgs/msg/MultiArrayDimension"](label="sample", size=s, stride=s)], data_offset=data_offset)
    return ma["std_msgs/msg/Float32MultiArray"](layout=layout, data=np.concatenate([head, traces.ravel()]))


def write_bag(path, frames, *, version=9, bad_frame=None, traces_type="std_msgs/msg/Float32MultiArray", stamps=None,
              writer=None, fs=FS, log_ns=None):
    """A rosbag2 MCAP bag written by rosbags directly: ``frames`` is a list of (first_nozzle, traces); frame ``k``
    has frame_id ``k`` and stamp ``stamps[k]`` s (default ``100 + k``). ``writer(path, version)``: the writer
    (default: rosbags' own). ``log_ns(k)``: the log time of frame ``k``'s traces and labels messages, ns (default:
    0.1 s apart, the labels message 1 ns after its traces)."""
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
    from rosbags.rosbag2 import StoragePlugin, Writer

    ts = typestore()
    qos = Qos(QosHistory.KEEP_LAST, 32, QosReliability.BEST_EFFORT, QosDurability.VOLATILE, QosTime(0, 0),
              QosTime(0, 0), QosLiveliness.AUTOMATIC, QosTime(0, 0), False)
    t0 = 1_700_000_000_000_000_000
    with (writer(path, version) if writer else Writer(path, version=version, storage_plugin=StoragePlugin.MCAP)) as w:
        conn = w.add_connection(f"{NS}/traces", traces_type, typestore=ts, offered_qos_profiles=[qos])
        other = w.add_connection(f"{NS}/labels", "std_msgs/msg/String", typestore=ts)
        for k, (first, x) in enumerate(frames):
            if traces_type == "std_msgs/msg/String":
                msg = ts.types["std_msgs/msg/String"](data="not traces")
            else:
                msg = frame_msg(ts, x, first=first, frame_id=k, stamp_s=100 + k if stamps is None else stamps[k],
                                data_offset=3 if k == bad_frame else HEADER_LEN, fs=fs)
            t = (t0 + k * 100_000_000, t0 + k * 100_000_000 + 1) if log_ns is None else (log_ns(k), log_ns(k))
            w.write(conn, t[0], ts.serialize_cdr(msg, traces_type))
            w.write(other, t[1], ts.serialize_cdr(ts.types["std_msgs/msg/String"](data="{}"), "std_msgs/msg/String"))
    return path


def plain(msg):
    """A decoded message as plain Python (dicts, lists, numbers, str), whichever reader decoded it.

    rosbags gives dataclasses with numpy arrays, mcap_ros2 objects with ``__slots__`` and lists:
    both become the same structure when they decoded the same fields.
    """
    if isinstance(msg, (bytes, bytearray)):
        msg = list(msg)
    if isinstance(msg, np.ndarray) or (isinstance(msg, (list, tuple)) and (
            not msg or isinstance(msg[0], (int, float, np.generic)))):  # numbers: NaN equals NaN here
        a = np.asarray(msg, dtype=np.float64)
        nan = np.isnan(a)
        return ("numbers", a.shape, np.where(nan, 0.0, a).tobytes(), np.packbits(nan).tobytes())
    if isinstance(msg, (list, tuple)):
        return [plain(m) for m in msg]
    if isinstance(msg, np.generic):
        msg = msg.item()
    if isinstance(msg, float) and msg != msg:
        return "NaN"
    fields = getattr(msg, "__dataclass_fields__", None) or getattr(type(msg), "__slots__", None)
    if fields is not None and not isinstance(msg, (str, int, float)):
        # constants (DiagnosticStatus.OK ...) are class attributes to rosbags, absent from mcap_ros2's slots
        return {k: plain(getattr(msg, k)) for k in fields if not k.startswith("_") and not k.isupper()}
    return msg


def read_with_rosbags(bag):
    """``[(topic, log time ns, plain message)]`` of a bag in file order, decoded by rosbags."""
    from rosbags.rosbag2 import Reader

    ts = typestore()
    with Reader(bag) as r:
        return [(c.topic, t, plain(ts.deserialize_cdr(raw, c.msgtype))) for c, t, raw in r.messages()]


def read_with_mcap_ros2(bag):
    """``[(topic, log time ns, plain message)]`` of a bag's MCAP files, decoded by mcap + mcap_ros2
    (independent of rosbags: the schemas stored in the file, its own CDR decoder)."""
    from pathlib import Path

    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    out = []
    for path in sorted(Path(bag).glob("*.mcap")):
        with open(path, "rb") as f:
            reader = make_reader(f, decoder_factories=[DecoderFactory()])
            for schema, channel, message, decoded in reader.iter_decoded_messages(log_time_order=False):
                assert schema.encoding == "ros2msg" and channel.message_encoding == "cdr"
                out.append((channel.topic, message.log_time, plain(decoded)))
    return out


def assert_two_readers_agree(bag):
    """rosbags and mcap_ros2 read the same messages, fields equal (decoded: CDR padding is never compared)."""
    a, b = read_with_rosbags(bag), read_with_mcap_ros2(bag)
    key = lambda m: (m[1], m[0])  # noqa: E731 - log time, then topic
    a, b = sorted(a, key=key), sorted(b, key=key)
    assert len(a) == len(b) > 0
    for x, y in zip(a, b):
        assert x == y, (x[:2], y[:2])
    return a


def flip_a_trace_byte(bag, chunk: int = 0):
    """Flip one bit of a trace sample in the middle of a traces message of the bag's MCAP chunk ``chunk`` (in file
    order; -1: the last) (no length or header touched: the message still decodes, as a slightly different trace);
    returns the MCAP file."""
    import struct
    from pathlib import Path

    from mcap.reader import make_reader

    path = next(Path(bag).glob("*.mcap"))
    with open(path, "rb") as f:
        starts = sorted(c.chunk_start_offset for c in make_reader(f).get_summary().chunk_indexes)
    b = bytearray(path.read_bytes())
    off = starts[chunk]
    assert b[off] == 0x06  # a Chunk record: opcode, length, start, end, uncompressed size, crc, compression, records
    comp = struct.unpack_from("<I", b, off + 37)[0]
    pos = off + 41 + comp + 8
    while not (b[pos] == 0x05 and struct.unpack_from("<Q", b, pos + 1)[0] > 1000):  # a traces Message record
        pos += 9 + struct.unpack_from("<Q", b, pos + 1)[0]
    b[pos + 9 + struct.unpack_from("<Q", b, pos + 1)[0] // 2] ^= 0x01  # a byte of a sample mid-message: one bit
    path.write_bytes(bytes(b))
    return path


def corrupt_a_record(bag):
    """Make a traces message record (the second one) of the bag's last MCAP chunk claim 10**12 bytes: the
    summary stays intact, so the bag opens and breaks off while it is read; returns the MCAP file."""
    import struct
    from pathlib import Path

    from mcap.reader import make_reader

    path = next(Path(bag).glob("*.mcap"))
    with open(path, "rb") as f:
        chunk = max(make_reader(f).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset)
    b = bytearray(path.read_bytes())
    off = chunk.chunk_start_offset
    assert b[off] == 0x06  # a Chunk record: opcode, length, start, end, uncompressed size, crc, compression, records
    comp = struct.unpack_from("<I", b, off + 37)[0]
    pos = off + 41 + comp + 8
    end = pos + struct.unpack_from("<Q", b, pos - 8)[0]
    seen = 0
    while pos < end:  # opcode (1 byte), length (8), body
        n = struct.unpack_from("<Q", b, pos + 1)[0]
        if b[pos] == 0x05 and n > 1000:  # a Message record of a trace frame
            seen += 1
            if seen == 2:
                struct.pack_into("<Q", b, pos + 1, 10**12)
                path.write_bytes(bytes(b))
                return path
        pos += 9 + n
    raise AssertionError("no second traces message in the last chunk")
