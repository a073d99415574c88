"""Trace-frame codec: round trips, validation, and real DDS transport."""

import math
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from std_msgs.msg import Float32MultiArray, MultiArrayDimension

from msg_defs import (
    HEADER_LEN,
    TRACE_MSG_TYPE,
    TRACES_QOS,
    FrameError,
    decode_traces,
    decode_traces_serialized,
    encode_traces,
    topics,
)

PROCS = Path(__file__).resolve().parents[1] / "procs"


@pytest.mark.parametrize("shape", [(1, 1), (1, 512), (3, 7), (256, 512), (2656, 64)])
def test_round_trip_is_bit_exact(shape):
    rng = np.random.default_rng(sum(shape))
    x = rng.standard_normal(shape).astype(np.float32)
    x.flat[0] = np.nan  # samples are carried as they are; rows are judged downstream
    frame = decode_traces(encode_traces(x, first_nozzle=5, frame_id=2**30 + 3, stamp=1.7e9 + 0.25))
    assert frame.traces.shape == shape and frame.traces.dtype == np.float32
    assert np.array_equal(frame.traces, x, equal_nan=True)
    assert frame.first_nozzle == 5 and frame.frame_id == 2**30 + 3
    assert frame.stamp == pytest.approx(1.7e9 + 0.25, abs=1e-6)
    assert frame.sample_rate_hz == 10e6
    np.testing.assert_array_equal(frame.nozzle_ids, np.arange(5, 5 + shape[0]))


def test_layout_is_the_documented_one():
    msg = encode_traces(np.zeros((4, 16), np.float32), first_nozzle=32)
    assert [d.label for d in msg.layout.dim] == ["nozzle", "sample"]
    assert [(d.size, d.stride) for d in msg.layout.dim] == [(4, 64), (16, 16)]
    assert msg.layout.data_offset == HEADER_LEN
    assert len(msg.data) == HEADER_LEN + 64
    assert msg.data[0] == 1.0 and msg.data[1] == 32.0  # schema version, first nozzle


def test_decoded_view_is_zero_copy_and_read_only():
    msg = encode_traces(np.ones((2, 8), np.float32))
    frame = decode_traces(msg)
    assert not frame.traces.flags.writeable
    assert np.shares_memory(frame.traces, np.frombuffer(msg.data, dtype=np.float32))


def _msg(dims, data, offset=HEADER_LEN):
    m = Float32MultiArray()
    m.layout.dim = [MultiArrayDimension(label=l, size=s, stride=st) for l, s, st in dims]
    m.layout.data_offset = offset
    m.data = [float(v) for v in data]
    return m


def _good_header():
    return [1, 0, 0, 0, 10e6, 0, 0, 0]


_MALFORMED = [
    (Float32MultiArray(), r"expected 2 dimensions .* got 0 \(empty layout\)"),
    (_msg([("nozzle", 4, 4)], _good_header() + [0] * 4), r"expected 2 dimensions .* got 1"),
    (
        _msg([("nozzle", 1, 4), ("sample", 2, 2), ("x", 2, 2)], _good_header() + [0] * 4),
        r"expected 2 dimensions .* got 3",
    ),
    (_msg([("sample", 2, 4), ("nozzle", 2, 2)], _good_header() + [0] * 4), r"labels"),
    (_msg([("nozzle", 2, 4), ("sample", 2, 2)], _good_header() + [0] * 3), r"expected 12 .* got 11"),
    (_msg([("nozzle", 2, 4), ("sample", 2, 2)], _good_header() + [0] * 5), r"expected 12 .* got 13"),
    (_msg([("nozzle", 0, 0), ("sample", 512, 512)], _good_header()), r"empty frame: 0 nozzles"),
    (_msg([("nozzle", 2, 5), ("sample", 2, 2)], _good_header() + [0] * 4), r"strides"),
    (_msg([("nozzle", 2, 4), ("sample", 2, 2)], [0] * 4, offset=0), r"data_offset 8"),
    (_msg([("nozzle", 2, 4), ("sample", 2, 2)], [2] + _good_header()[1:] + [0] * 4), r"schema version 1, got 2"),
    (_msg([("nozzle", 2, 4), ("sample", 2, 2)], [1, 0, 0, 0, 0, 0, 0, 0] + [0] * 4), r"sample_rate_hz"),
    (_msg([("nozzle", 2, 4), ("sample", 2, 2)], [1, -3, 0, 0, 1e6, 0, 0, 0] + [0] * 4), r"non-negative integers"),
    (_msg([("nozzle", 2, 4), ("sample", 2, 2)], [1, 0, 0, 0, math.nan, 0, 0, 0] + [0] * 4),  # was: "integers"
     r"^expected a positive, finite sample_rate_hz in the header, got nan$"),
    (_msg([("nozzle", 2, 4), ("sample", 2, 2)], [1, 0, 0, 0, math.inf, 0, 0, 0] + [0] * 4), r"finite sample_rate_hz"),
    (_msg([("nozzle", 2, 4), ("sample", 2, 2)], [1, 0, math.nan, 0, 1e6, 0, 0, 0] + [0] * 4), r"non-negative integers"),
]


@pytest.mark.parametrize("msg, match", _MALFORMED)
def test_malformed_messages_raise_frame_error(msg, match):
    with pytest.raises(FrameError, match=match):
        decode_traces(msg)


@pytest.mark.parametrize("msg, match", _MALFORMED)
def test_serialized_malformed_messages_raise_the_same_frame_error(msg, match):
    from rclpy.serialization import serialize_message

    with pytest.raises(FrameError, match=match):
        decode_traces_serialized(serialize_message(msg))


@pytest.mark.parametrize("shape", [(1, 1), (3, 7), (1024, 512)])
def test_serialized_decode_is_decode_traces_of_the_message(shape):
    """fe takes its trace messages raw (issue 12: no conversion of 2 MB to a Python message)."""
    from rclpy.serialization import deserialize_message, serialize_message

    x = np.random.default_rng(sum(shape)).standard_normal(shape).astype(np.float32)
    msg = encode_traces(x, first_nozzle=17, frame_id=(1 << 30) + 5, stamp=1763798400.125, sample_rate_hz=20e6)
    buf = serialize_message(msg)
    a, b = decode_traces(deserialize_message(buf, Float32MultiArray)), decode_traces_serialized(buf)
    assert (a.first_nozzle, a.frame_id, a.sample_rate_hz, a.stamp) == (b.first_nozzle, b.frame_id,
                                                                       b.sample_rate_hz, b.stamp)
    assert b.traces.dtype == np.float32 and np.array_equal(b.traces, x) and not b.traces.flags.writeable
    assert np.shares_memory(np.frombuffer(buf, np.uint8), b.traces.view(np.uint8)), "a view, no copy"
    assert decode_traces_serialized(msg).frame_id == a.frame_id, "a message object is decoded too"
    with pytest.raises(FrameError, match="samples per trace"):
        decode_traces_serialized(buf, n_samples=shape[1] + 1)


def test_serialized_bytes_of_no_cdr_encapsulation_raise_a_frame_error():
    """rclpy's deserialiser (the fallback for another encapsulation) raised its own RMWError, which ended the fdi
    node (helper-140's QA: a bag of random bytes replayed into it)."""
    rng = np.random.default_rng(1)
    for head in (b"\xb8\x83", b"\x00\x03", b"\x00\x07"):
        with pytest.raises(FrameError, match=f"not a serialised std_msgs/msg/Float32MultiArray \\(its first bytes "
                                             f"{head.hex()}"):
            decode_traces_serialized(head + rng.bytes(998))


def test_serialized_decode_reads_big_endian_cdr_and_refuses_truncated_bytes():
    import struct

    from rclpy.serialization import serialize_message

    x = np.arange(6, dtype=np.float32).reshape(2, 3)
    buf = serialize_message(encode_traces(x, first_nozzle=3, frame_id=9, stamp=2.5))
    assert buf[:2] == b"\x00\x01"  # little-endian plain CDR
    # the same message in big-endian CDR: every 4-byte field swapped, labels kept
    le = bytearray(buf)
    be = bytearray(b"\x00\x00" + bytes(le[2:4]))
    pos, n_dims = 4, struct.unpack_from("<I", le, 4)[0]
    be += struct.pack(">I", n_dims)
    pos = 8
    for _ in range(n_dims):
        n = struct.unpack_from("<I", le, pos)[0]
        be += struct.pack(">I", n) + le[pos + 4:pos + 4 + n]
        pos += 4 + n
        pad = -(pos - 4) % 4
        be += le[pos:pos + pad]
        pos += pad
        be += struct.pack(">II", *struct.unpack_from("<II", le, pos))
        pos += 8
    be += struct.pack(">II", *struct.unpack_from("<II", le, pos))
    pos += 8
    be += np.frombuffer(bytes(le[pos:]), "<f4").astype(">f4").tobytes()
    f = decode_traces_serialized(bytes(be))
    assert (f.first_nozzle, f.frame_id, f.stamp) == (3, 9, 2.5) and np.array_equal(f.traces, x)
    for cut in (3, 10, len(buf) - 4):
        with pytest.raises(FrameError):
            decode_traces_serialized(bytes(buf[:cut]))
    with pytest.raises(FrameError, match="serialized"):
        decode_traces_serialized(12)


def test_frame_error_is_a_value_error():
    assert issubclass(FrameError, ValueError)
    with pytest.raises(ValueError, match="Float32MultiArray"):
        decode_traces("not a message")


def test_nozzle_range_is_checked_against_the_head():
    msg = encode_traces(np.zeros((10, 4), np.float32), first_nozzle=2650)
    assert decode_traces(msg, max_nozzle_id=2659).first_nozzle == 2650
    with pytest.raises(FrameError, match=r"nozzle range 2650..2659 out of bounds.*0..2655"):
        decode_traces(msg, max_nozzle_id=2655)
    # a hand-made header claiming ids beyond the format's 2**24 is refused without a bound too
    bad = encode_traces(np.zeros((10, 4), np.float32), first_nozzle=0)
    for first in (2**24 - 5, 1e30):
        data = list(bad.data)
        data[1] = first
        bad.data = data
        with pytest.raises(FrameError, match=r"below 2\*\*24"):
            decode_traces(bad)


@pytest.mark.parametrize("field, index", [("frame_lo", 2), ("frame_hi", 3), ("stamp_s_lo", 5),
                                          ("stamp_s_hi", 6)])
@pytest.mark.parametrize("value", [2**24, 2**25, 3.4e38])
def test_header_fields_beyond_2_24_are_refused(field, index, value):
    """Each of frame_lo/hi, stamp_s_lo/hi < 2**24: else two frames collide on one id, and ids or
    stamps of 39+ digits overflow an int64 or a double downstream."""
    msg = encode_traces(np.zeros((2, 4), np.float32), frame_id=7, stamp=12.5)
    data = list(msg.data)
    data[index] = value
    msg.data = data
    want = rf"header {field} must be < 2\*\*24 \(16777216\), got " + re.escape(f"{float(np.float32(value)):.10g}")
    with pytest.raises(FrameError, match=want):
        decode_traces(msg)
    data[index] = 2**24 - 1  # the largest value allowed
    msg.data = data
    decode_traces(msg)


def test_stamp_microseconds_bound_is_enforced():
    msg = encode_traces(np.zeros((2, 4), np.float32), stamp=3.999999)
    assert decode_traces(msg).stamp == pytest.approx(3.999999, abs=1e-9)
    data = list(msg.data)
    data[7] = 1e6
    msg.data = data
    with pytest.raises(FrameError, match=r"stamp_us \(microseconds\) must be < 1e6, got 1000000"):
        decode_traces(msg)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(traces=np.zeros(5)), r"2-D array"),
        (dict(traces=np.zeros((0, 5))), r"non-empty"),
        (dict(traces=np.zeros((2, 2)), first_nozzle=-1), r"first_nozzle"),
        (dict(traces=np.zeros((2, 2)), first_nozzle=2**24 - 1), r"below 2\*\*24"),
        (dict(traces=np.zeros((2, 2)), sample_rate_hz=0.1), r"float32-exact"),
        (dict(traces=np.zeros((2, 2)), stamp=float("nan")), r"stamp"),
    ],
)
def test_encoder_rejects_bad_arguments(kwargs, match):
    traces = kwargs.pop("traces")
    with pytest.raises(FrameError, match=match):
        encode_traces(traces, **kwargs)


def test_in_process_round_trip_through_dds(ros):
    x = np.random.default_rng(0).standard_normal((256, 512)).astype(np.float32)
    pub_node = ros.node("test_pub")
    sub_node = ros.node("test_sub")
    got = []
    sub_node.create_subscription(TRACE_MSG_TYPE, topics.TRACES, got.append, TRACES_QOS)
    pub = pub_node.create_publisher(TRACE_MSG_TYPE, topics.TRACES, TRACES_QOS)
    ros.spin_until(lambda: pub.get_subscription_count() > 0, what="subscription match")
    msg = encode_traces(x, first_nozzle=256, frame_id=1)

    def published_and_received():
        if not got:
            pub.publish(msg)  # best effort: publish again until one arrives
        return bool(got)

    ros.spin_until(published_and_received, timeout=10, what="a 256 x 512 frame")
    frame = decode_traces(got[0])
    assert frame.traces.tobytes() == x.tobytes()
    assert (frame.first_nozzle, frame.frame_id) == (256, 1)


def test_two_process_round_trip(ros):
    n, s, seed = 64, 512, 3
    env = dict(os.environ, ROS_DOMAIN_ID=str(ros.domain_id))
    proc = subprocess.Popen(
        [sys.executable, str(PROCS / "publish_frames.py"), str(n), str(s), str(seed), "30"],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
    )
    try:
        got = []
        node = ros.node("test_sub_remote")
        node.create_subscription(TRACE_MSG_TYPE, topics.TRACES, got.append, TRACES_QOS)
        ros.spin_until(lambda: bool(got), timeout=25, what="a frame from the publisher process")
    finally:
        proc.terminate()
        out, _ = proc.communicate(timeout=10)
    frame = decode_traces(got[0])
    expected = np.random.default_rng(seed).standard_normal((n, s)).astype(np.float32)
    assert np.array_equal(frame.traces, expected)
    assert (frame.first_nozzle, frame.frame_id, frame.stamp) == (100, 7, 1.5)


def test_labels_carry_the_rows_the_gate_cleared():
    import json

    from std_msgs.msg import String

    from msg_defs import GATE_CLEARED_KEY, LabelsReport, MessageError, build_diagnostics, decode_labels, \
        diagnostics_values, encode_labels

    classes = np.array(["healthy_nozzle", "ok_signal", "deeply_dried", ""], dtype=object)
    valid = np.array([True, True, True, False])
    rep = LabelsReport.from_arrays(frame_id=1, stamp=2.0, first_nozzle=10, classes=classes,
                                   confidence=np.array([1.0, 1.0, 0.9, np.nan]), valid=valid,
                                   reasons=np.array(["", "", "", "flat"], dtype=object), model_id="m",
                                   gate_cleared=np.array([True, True, False, True]))
    assert rep.gate_cleared == 2  # an invalid row is never counted
    msg = encode_labels(rep)
    assert json.loads(msg.data)["gate_cleared"] == 2
    assert decode_labels(msg) == rep
    old = json.loads(msg.data)
    del old["gate_cleared"]  # an older publisher: 0
    assert decode_labels(String(data=json.dumps(old))).gate_cleared == 0
    for bad in (-1, 4, "2", True):
        old["gate_cleared"] = bad
        with pytest.raises(MessageError, match="gate_cleared"):
            decode_labels(String(data=json.dumps(old)))
    with pytest.raises(MessageError, match="gate_cleared"):
        LabelsReport.from_arrays(frame_id=1, stamp=2.0, first_nozzle=10, classes=classes, confidence=np.ones(4),
                                 valid=valid, reasons=np.array([""] * 4, dtype=object), model_id="m",
                                 gate_cleared=np.ones(3, bool))
    arr = build_diagnostics(namespace="/h", level="ok", message="", values={}, counts={"healthy_nozzle": 5},
                            gate_cleared=7)
    d = diagnostics_values(arr)["inkdiag fdi: /h"]
    assert d["count." + GATE_CLEARED_KEY] == "7" and d["count.healthy_nozzle"] == "5"
def test_an_unknown_nozzle_is_a_fault_with_its_score_and_counted():
    # issue 16: `unknown` entries in faults with their score, counts["unknown"], not drying
    from msg_defs import DRIED_CLASSES, UNKNOWN_CLASS, LabelsReport, decode_labels, encode_labels

    classes = np.array(["healthy_nozzle", UNKNOWN_CLASS, "slightly_dried", "ok_signal"], dtype=object)
    rep = LabelsReport.from_arrays(frame_id=3, stamp=1.5, first_nozzle=10, classes=classes,
                                   confidence=np.array([0.9, 0.995, 0.8, 0.7]),
                                   valid=np.ones(4, dtype=bool), reasons=np.array([""] * 4, dtype=object),
                                   model_id="m")
    back = decode_labels(encode_labels(rep))
    assert back.counts[UNKNOWN_CLASS] == 1
    assert (11, UNKNOWN_CLASS, 0.995) in back.faults
    assert back.nozzles_of(DRIED_CLASSES) == [12]


def test_serialized_fast_prefix_reads_what_the_field_reader_reads(monkeypatch):
    """The usual layout's bytes in one unpack (the fdi node decodes every message so): the same dims, offset
    and data as the field-by-field reader, or the same error, for every byte of the prefix changed,
    every truncation around it and trailing bytes, as bytes, bytearray or memoryview."""
    from rclpy.serialization import serialize_message

    from msg_defs import codec

    def read(fn, buf):
        try:
            got = fn(buf)
        except FrameError as exc:
            return "error", str(exc)
        if got is None:  # another encapsulation
            return None
        dims, off, data = got
        return [tuple(d) for d in dims], off, data.dtype.str, data.flags.writeable, data.tolist()

    x = np.arange(12, dtype=np.float32).reshape(3, 4)
    buf = serialize_message(encode_traces(x, first_nozzle=5, frame_id=2, stamp=1.5))
    n = codec._TRACES_PREFIX.size
    assert len(buf) == n + 4 * (8 + x.size), "encode_traces' bytes end with the data"
    cases = [buf, buf + b"\x00" * 5] + [buf[:cut] for cut in range(n - 2, n + 6)] + [buf[:-1], buf[:-4]]
    for i in range(n):  # each byte of the prefix changed
        for v in (0, 1, 0x41, 0xFF):
            b = bytearray(buf)
            b[i] = v
            cases.append(bytes(b))
    read_ok = 0
    for b in cases:
        for given in (b, bytearray(b), memoryview(b)):
            got = read(codec._read_cdr_traces, given)
            assert got == read(codec._read_cdr_fields, given)
            read_ok += got is not None and got[0] != "error"
    assert read_ok > 30
    # the usual frame, as it is and with trailing bytes, takes the one-unpack way: never the field reader
    monkeypatch.setattr(codec, "_read_cdr_fields", lambda b: pytest.fail("the field reader read a usual frame"))
    for b in (buf, bytearray(buf), memoryview(buf), buf + b"\x00"):
        dims, off, data = codec._read_cdr_traces(b)
        assert [tuple(d) for d in dims] == [("nozzle", 3, 12), ("sample", 4, 4)] and off == 8
        assert np.array_equal(data[8:].reshape(3, 4), x)


def _random_frame(rng, n, names, p_invalid, gate):
    codes = rng.integers(0, len(names), n).astype(np.uint8)
    codes[rng.random(n) < 0.8] = names.index("healthy_nozzle")  # mostly healthy, as a working head
    valid = rng.random(n) >= p_invalid
    reasons = np.where(valid, "", rng.choice(["non_finite", "flat", "clipped"], n)).astype(object)
    classes = np.array(names, dtype=object)[codes]
    confidence = rng.random(n)
    cleared = (rng.random(n) < 0.5) & (classes == "healthy_nozzle") if gate else None  # invalid rows too
    return codes, classes, confidence, valid, reasons, cleared


@pytest.mark.parametrize("seed", range(6))
def test_labels_from_class_codes_are_the_labels_from_strings(seed):
    """LabelsReport.from_arrays with class codes (the fdi node's reports) gives the report the per-row strings give:
    random frames with invalid rows or none, the gate's rows or none, unknown and "" classes, a class named like the
    invalid count, empty frames; arguments it does not take (another dtype, names not distinct, a code past the
    names) go the strings' way, errors included."""
    from msg_defs import LabelsReport, MessageError, serialize_labels

    rng = np.random.default_rng(seed)
    names = ("", "healthy_nozzle", "ok_signal", "deeply_dried", "fully_blocked", "unknown", "invalid", "a")
    for n, p_invalid, gate in [(200, 0.0, True), (200, 0.05, True), (64, 0.0, False), (64, 0.3, False), (0, 0.0, True),
                               (1, 1.0, True), (5, 0.0, True)]:
        codes, classes, confidence, valid, reasons, cleared = _random_frame(rng, n, names, p_invalid, gate)
        kw = dict(frame_id=7, stamp=12.5, first_nozzle=400, classes=classes, confidence=confidence, valid=valid,
                  reasons=reasons, model_id="m", gate_cleared=cleared)
        want = LabelsReport.from_arrays(**kw)
        got = LabelsReport.from_arrays(**kw, class_codes=codes, class_names=names)
        assert got == want
        assert serialize_labels(got) == serialize_labels(want)
        assert list(got.counts) == list(want.counts)  # the same order: by class name, then "invalid"
        blind = np.full(n, None, dtype=object)  # the codes are what is read, not the strings
        assert LabelsReport.from_arrays(**{**kw, "classes": blind}, class_codes=codes, class_names=names) == want
    codes, classes, confidence, valid, reasons, cleared = _random_frame(rng, 50, names, 0.1, True)
    kw = dict(frame_id=7, stamp=12.5, first_nozzle=400, classes=classes, confidence=confidence, valid=valid,
              reasons=reasons, model_id="m", gate_cleared=cleared)
    want = LabelsReport.from_arrays(**kw)
    for other in [dict(class_codes=codes.astype(np.int64), class_names=names),
                  dict(class_codes=codes, class_names=list(names)),
                  dict(class_codes=np.where(codes == 1, 9, codes).astype(np.uint8), class_names=names[:-1] + ("z",)),
                  dict(class_codes=codes, class_names=names[:-1] + ("ok_signal",))]:
        assert LabelsReport.from_arrays(**kw, **other) == want  # not taken: the strings build it
    with pytest.raises(MessageError, match="must all have shape"):
        LabelsReport.from_arrays(**{**kw, "reasons": reasons[:-1]}, class_codes=codes, class_names=names)
    # helper-144: a code past the names on an invalid row only; names of str subclasses (after the plain ones were
    # cached: equal tuples); a name that is not hashable; ragged classes (the strings' own error)
    past = np.where(valid, codes, 200).astype(np.uint8)
    assert (~valid).any() and LabelsReport.from_arrays(**kw, class_codes=past, class_names=names) == want
    sub = tuple(np.str_(c) for c in names)
    got = LabelsReport.from_arrays(**kw, class_codes=codes, class_names=sub)
    assert got == want and all(type(c) is str for c in got.counts) and all(type(f[1]) is str for f in got.faults)
    assert LabelsReport.from_arrays(**kw, class_codes=codes, class_names=names[:-1] + (["a"],)) == want
    huge = codes.astype(np.uint64)
    huge[3] = 2**63  # on a valid row (helper-147: bincount raised)
    assert LabelsReport.from_arrays(**{**kw, "valid": np.ones(codes.size, bool)}, class_codes=huge,
                                    class_names=names) == LabelsReport.from_arrays(**{**kw, "valid": np.ones(codes.size,
                                                                                                           bool)})
    ragged = dict(kw, classes=[["x"], "healthy_nozzle", "y"], confidence=np.ones(3), valid=np.ones(3, bool),
                  reasons=np.array(["", "", ""], dtype=object), gate_cleared=None)
    with pytest.raises(TypeError, match="unhashable"):
        LabelsReport.from_arrays(**ragged)
    with pytest.raises(TypeError, match="unhashable"):
        LabelsReport.from_arrays(**ragged, class_codes=np.array([1, 1, 1], np.uint8), class_names=names)
