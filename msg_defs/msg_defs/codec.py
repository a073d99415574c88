"""Trace frames to and from ``std_msgs/Float32MultiArray``.

One message carries one *frame*: the traces of a contiguous range of nozzles
of one printhead, measured at once. The layout is the standard row-major
MultiArray layout plus a short header in the leading padding that
``layout.data_offset`` reserves for exactly that purpose:

=========================  ==================================================
field                      value
=========================  ==================================================
``layout.dim[0]``          ``label="nozzle"``, ``size=n_nozzles``, ``stride=n_nozzles*n_samples``
``layout.dim[1]``          ``label="sample"``, ``size=n_samples``, ``stride=n_samples``
``layout.data_offset``     ``HEADER_LEN`` (8)
``data[0:8]``              header, float32 holding exact integers (< 2**24):
                           ``[schema_version, first_nozzle, frame_lo, frame_hi,
                           sample_rate_hz, stamp_s_lo, stamp_s_hi, stamp_us]``;
                           ``first_nozzle + n_nozzles <= 2**24``, each of
                           ``frame_lo, frame_hi, stamp_s_lo, stamp_s_hi``
                           ``< 2**24``, ``stamp_us < 10**6``
``data[8:]``               traces, row-major: ``data[8 + i*n_samples + k]`` is
                           sample ``k`` of nozzle ``first_nozzle + i``
=========================  ==================================================

``frame_id = frame_hi * 2**24 + frame_lo``; ``stamp`` (the measurement time,
s since the epoch) ``= (stamp_s_hi * 2**24 + stamp_s_lo) + stamp_us * 1e-6``.
A decoded ``frame_id`` and the stamp's seconds are thus below ``2**48``
(exact in an int64 and in a double). The rows are the nozzles ``first_nozzle .. first_nozzle + n_nozzles - 1``.
Trace samples are in the sensor's unit (V); ``sample_rate_hz`` says how they
were sampled (float32-exact values only, e.g. 10e6).

Encoding and decoding take the buffer fast path: ``array.array.frombytes``
into ``msg.data`` (a memcpy in rclpy), ``np.frombuffer`` on receipt
(zero-copy: the decoded traces are a read-only view into the message).

Every check on receipt raises :class:`FrameError` (a ``ValueError``) saying
what was expected and what arrived. Non-finite *samples* are not a frame
error: rows are judged one by one downstream (the FDI node labels them
invalid); only the frame's structure is validated here.
"""

from __future__ import annotations

import array
import math
import struct
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from std_msgs.msg import Float32MultiArray, MultiArrayDimension

from .errors import MessageError

__all__ = [
    "SCHEMA_VERSION",
    "HEADER_LEN",
    "NOZZLE_LABEL",
    "SAMPLE_LABEL",
    "TRACE_MSG_TYPE",
    "FrameError",
    "TraceFrame",
    "encode_traces",
    "decode_traces",
    "decode_traces_serialized",
    "restamp_traces",
]

#: Version of this trace layout; bumped on any incompatible change.
SCHEMA_VERSION = 1
#: Number of float32 header values in the leading padding.
HEADER_LEN = 8
NOZZLE_LABEL = "nozzle"
SAMPLE_LABEL = "sample"

#: The ROS message type of a trace frame.
TRACE_MSG_TYPE = Float32MultiArray

_EXACT = 1 << 24  # float32 holds every integer below 2**24 exactly


class FrameError(MessageError):
    """A trace message that does not follow the layout; says what was expected and found."""


@dataclass(frozen=True)
class TraceFrame:
    """A decoded trace frame.

    Attributes
    ----------
    traces : ndarray, shape (n_nozzles, n_samples), float32
        Read-only view into the message buffer (copy it to modify).
    first_nozzle : int
        Id of the nozzle in row 0; row ``i`` is nozzle ``first_nozzle + i``.
    frame_id : int
        The publisher's frame counter.
    sample_rate_hz : float
        Sample rate of the traces, Hz.
    stamp : float
        Measurement time, s since the epoch (microsecond resolution).
    """

    traces: np.ndarray
    first_nozzle: int = 0
    frame_id: int = 0
    sample_rate_hz: float = 10e6
    stamp: float = 0.0

    @property
    def n_nozzles(self) -> int:
        return int(self.traces.shape[0])

    @property
    def n_samples(self) -> int:
        return int(self.traces.shape[1])

    @property
    def nozzle_ids(self) -> np.ndarray:
        """Nozzle id of each row, int64 (n_nozzles,)."""
        return np.arange(self.first_nozzle, self.first_nozzle + self.n_nozzles, dtype=np.int64)

    def rows_of(self, nozzle_ids):
        """The rows of the given nozzles that this frame holds.

        Returns ``(ids, traces)``: the ids (int64, sorted, only those in this
        frame's range) and their traces (a float32 copy, (len(ids), n_samples)).
        """
        ids = np.unique(np.asarray(list(nozzle_ids), dtype=np.int64))
        ids = ids[(ids >= self.first_nozzle) & (ids < self.first_nozzle + self.n_nozzles)]
        return ids, np.array(self.traces[ids - self.first_nozzle])


def _check_uint(name: str, value, limit: int) -> int:
    if isinstance(value, bool) or not float(value).is_integer() or not 0 <= int(value) < limit:
        raise FrameError(f"{name} must be an integer in [0, {limit}), got {value!r}")
    return int(value)


def encode_traces(
    traces,
    *,
    first_nozzle: int = 0,
    frame_id: int = 0,
    sample_rate_hz: float = 10e6,
    stamp: float = 0.0,
) -> Float32MultiArray:
    """Encode a (n_nozzles, n_samples) array as a ``Float32MultiArray`` frame.

    Parameters
    ----------
    traces : array_like, shape (n_nozzles, n_samples)
        Sensor samples (V); cast to float32.
    first_nozzle : int
        Id of the nozzle in row 0, ``0 <= first_nozzle < 2**24``.
    frame_id : int
        Frame counter, ``0 <= frame_id < 2**48``.
    sample_rate_hz : float
        Sample rate, Hz; must be exactly representable in float32.
    stamp : float
        Measurement time, s since the epoch (kept to the microsecond).

    Raises
    ------
    FrameError
        On a wrong shape or out-of-range header value.
    """
    x = np.asarray(traces)
    if x.ndim != 2 or x.shape[0] == 0 or x.shape[1] == 0:
        raise FrameError(
            f"traces must be a non-empty 2-D array (n_nozzles, n_samples), got shape {x.shape}"
        )
    n, s = x.shape
    first = _check_uint("first_nozzle", first_nozzle, _EXACT)
    if first + n > _EXACT:
        raise FrameError(f"nozzle ids must stay below 2**24, got first_nozzle={first} with {n} rows")
    fid = _check_uint("frame_id", frame_id, _EXACT * _EXACT)
    fs = float(sample_rate_hz)
    if not (math.isfinite(fs) and fs > 0 and float(np.float32(fs)) == fs):
        raise FrameError(f"sample_rate_hz must be positive and float32-exact, got {sample_rate_hz!r}")
    st = float(stamp)
    if not (math.isfinite(st) and st >= 0):
        raise FrameError(f"stamp must be a finite time >= 0 s, got {stamp!r}")
    sec = int(st)
    usec = min(int(round((st - sec) * 1e6)), 999_999)
    sec = _check_uint("stamp seconds", sec, _EXACT * _EXACT)

    buf = np.empty(HEADER_LEN + n * s, dtype=np.float32)
    buf[:HEADER_LEN] = (
        SCHEMA_VERSION, first, fid % _EXACT, fid // _EXACT, fs, sec % _EXACT, sec // _EXACT, usec,
    )
    buf[HEADER_LEN:].reshape(n, s)[...] = x

    msg = Float32MultiArray()
    msg.layout.dim = [
        MultiArrayDimension(label=NOZZLE_LABEL, size=n, stride=n * s),
        MultiArrayDimension(label=SAMPLE_LABEL, size=s, stride=s),
    ]
    msg.layout.data_offset = HEADER_LEN
    data = array.array("f")
    data.frombytes(buf.tobytes())
    msg.data = data  # array.array: rclpy copies it with one memcpy
    return msg


def decode_traces(msg, *, max_nozzle_id: int | None = None, n_samples: int | None = None,
                  sample_rate_hz: float | None = None) -> TraceFrame:
    """Decode and validate a trace frame.

    Parameters
    ----------
    msg : std_msgs.msg.Float32MultiArray
    max_nozzle_id : int, optional
        When given, every row's nozzle id must be ``<= max_nozzle_id``
        (the receiving head's last nozzle).
    n_samples : int, optional
        When given, the frame must have exactly this many samples per trace
        (what the receiver's model was built for).
    sample_rate_hz : float, optional
        When given, the header's sample rate must equal it.

    Returns
    -------
    TraceFrame

    Raises
    ------
    FrameError
        Wrong message type, number of dimensions, labels, sizes, strides,
        data offset, data length, schema version or header values.
    """
    if not isinstance(msg, Float32MultiArray):
        raise FrameError(f"expected a std_msgs/Float32MultiArray, got {type(msg).__name__}")
    try:  # received messages hold an array.array: zero-copy view
        data = np.frombuffer(msg.data, dtype=np.float32)
    except TypeError:  # a hand-built message may hold a list
        data = np.asarray(msg.data, dtype=np.float32)
    return _decode(msg.layout.dim, msg.layout.data_offset, data, max_nozzle_id=max_nozzle_id,
                   n_samples=n_samples, sample_rate_hz=sample_rate_hz)


def _decode(dims, data_offset, data, *, max_nozzle_id, n_samples, sample_rate_hz) -> TraceFrame:
    """The checks of :func:`decode_traces` on a message's layout dimensions (objects with
    ``label``, ``size`` and ``stride``), ``data_offset`` and float32 data (1-D)."""
    if len(dims) != 2:
        raise FrameError(
            f"expected 2 dimensions ('{NOZZLE_LABEL}', '{SAMPLE_LABEL}'), got {len(dims)}"
            + (f": {[d.label for d in dims]}" if dims else " (empty layout)")
        )
    labels = (dims[0].label, dims[1].label)
    if labels != (NOZZLE_LABEL, SAMPLE_LABEL):
        raise FrameError(f"expected dimension labels ('{NOZZLE_LABEL}', '{SAMPLE_LABEL}'), got {labels}")
    n, s = int(dims[0].size), int(dims[1].size)
    if n == 0 or s == 0:
        raise FrameError(f"empty frame: {n} nozzles x {s} samples")
    if int(dims[1].stride) != s or int(dims[0].stride) != n * s:
        raise FrameError(
            f"expected row-major strides ({n * s}, {s}) for {n} x {s}, "
            f"got ({dims[0].stride}, {dims[1].stride})"
        )
    if int(data_offset) != HEADER_LEN:
        raise FrameError(
            f"expected layout.data_offset {HEADER_LEN} (the header), got {data_offset}"
        )
    want = HEADER_LEN + n * s
    if data.size != want:
        raise FrameError(
            f"expected {want} data values ({HEADER_LEN} header + {n} x {s}), got {data.size}"
        )
    head = data[:HEADER_LEN].tolist()  # 8 Python floats: checked without numpy's per-call cost
    if head[0] != SCHEMA_VERSION:
        raise FrameError(f"expected trace schema version {SCHEMA_VERSION}, got {head[0]:.10g}")
    counts = [head[k] for k in (1, 2, 3, 5, 6, 7)]
    if not all(map(math.isfinite, counts)) or any(v < 0 or v != math.floor(v) for v in counts):
        raise FrameError(f"header values must be non-negative integers, got {head}")
    if not (head[4] > 0 and math.isfinite(head[4])):  # NaN was said to be a count that is not an integer
        raise FrameError(f"expected a positive, finite sample_rate_hz in the header, got {head[4]:.10g}")
    for k, name in ((2, "frame_lo"), (3, "frame_hi"), (5, "stamp_s_lo"), (6, "stamp_s_hi")):
        if head[k] >= _EXACT:
            raise FrameError(f"header {name} must be < 2**24 ({_EXACT}), got {head[k]:.10g}")
    if head[7] > 999_999:
        raise FrameError(f"header stamp_us (microseconds) must be < 1e6, got {head[7]:.10g}")
    first = int(head[1])
    if first + n > _EXACT:
        raise FrameError(f"nozzle ids must stay below 2**24, got first_nozzle={first} with {n} rows")
    if max_nozzle_id is not None and first + n - 1 > max_nozzle_id:
        raise FrameError(
            f"nozzle range {first}..{first + n - 1} out of bounds: this head's nozzles are "
            f"0..{max_nozzle_id}"
        )
    if n_samples is not None and s != n_samples:
        raise FrameError(f"expected {n_samples} samples per trace, got {s}")
    if sample_rate_hz is not None and float(head[4]) != float(np.float32(sample_rate_hz)):
        raise FrameError(f"expected sample_rate_hz {sample_rate_hz:.10g}, got {head[4]:.10g}")
    traces = data[HEADER_LEN:].reshape(n, s)
    traces.flags.writeable = False  # a view into the message: never write through it
    return TraceFrame(
        traces=traces,
        first_nozzle=first,
        frame_id=int(head[3]) * _EXACT + int(head[2]),
        sample_rate_hz=float(head[4]),
        stamp=(int(head[6]) * _EXACT + int(head[5])) + int(head[7]) * 1e-6,
    )


class _Dim(NamedTuple):  # a NamedTuple: built twice per received frame, ~10x cheaper than a dataclass
    label: str
    size: int
    stride: int


# CDR encapsulation identifiers (first two bytes of a serialized message): plain CDR, big/little endian
_CDR_BYTE_ORDER = {b"\x00\x00": ">", b"\x00\x01": "<"}
_FLOAT32 = {order: np.dtype(np.float32).newbyteorder(order) for order in "<>"}


# A trace frame's bytes up to its data in little-endian CDR, as every frame encode_traces makes is laid out:
# encapsulation, 2 dimensions ("nozzle", "sample"), data_offset, count.
_DIM = "I{0}s{1}xII"  # a dimension: label length, label and NUL, padding to 4 bytes, size, stride
_TRACES_PREFIX = struct.Struct("<4sI" + "".join(_DIM.format(len(lab) + 1, -(len(lab) + 1) % 4)
                                                for lab in (NOZZLE_LABEL, SAMPLE_LABEL)) + "II")
_PREFIX_CONST = (b"\x00\x01\x00\x00", 2, len(NOZZLE_LABEL) + 1, NOZZLE_LABEL.encode() + b"\0",
                 len(SAMPLE_LABEL) + 1, SAMPLE_LABEL.encode() + b"\0")


def _read_cdr_traces(buf):
    """``(dims, data_offset, data)`` of a serialized Float32MultiArray (plain CDR: ROS 2's
    encoding on the wire), the data a zero-copy float32 view of ``buf``; None for another
    encapsulation."""
    if len(buf) >= _TRACES_PREFIX.size:  # the usual layout in one unpack; the general reader below gives the same
        enc, nd, l1, lab1, n, st1, l2, lab2, s, st2, off, count = _TRACES_PREFIX.unpack_from(buf)
        if (enc, nd, l1, lab1, l2, lab2) == _PREFIX_CONST and _TRACES_PREFIX.size + 4 * count <= len(buf):
            return ((_Dim(NOZZLE_LABEL, n, st1), _Dim(SAMPLE_LABEL, s, st2)), off,
                    np.frombuffer(buf, dtype=_FLOAT32["<"], count=count, offset=_TRACES_PREFIX.size))
    return _read_cdr_fields(buf)


def _read_cdr_fields(buf):
    """:func:`_read_cdr_traces` field by field: any layout, either byte order."""
    mv = memoryview(buf).cast("B")
    order = _CDR_BYTE_ORDER.get(bytes(mv[:2]))
    if order is None:
        return None
    u32 = struct.Struct(order + "I")
    end = len(mv)
    pos = 4  # CDR aligns relative to the end of the 4-byte encapsulation header

    def uint32():
        nonlocal pos
        pos += -(pos - 4) % 4
        if pos + 4 > end:
            raise FrameError(f"serialized trace frame truncated at byte {pos} of {end}")
        v = u32.unpack_from(mv, pos)[0]
        pos += 4
        return v

    n_dims = uint32()
    if n_dims > 64:
        raise FrameError(f"serialized trace frame: {n_dims} layout dimensions")
    dims = []
    for _ in range(n_dims):
        n_chars = uint32()  # with the terminating NUL
        if pos + n_chars > end:
            raise FrameError(f"serialized trace frame truncated in a dimension label (byte {pos} of {end})")
        label = bytes(mv[pos:pos + max(n_chars - 1, 0)]).decode("utf-8", "replace")
        pos += n_chars
        dims.append(_Dim(label, uint32(), uint32()))
    data_offset = uint32()
    count = uint32()
    if pos + 4 * count > end:
        raise FrameError(f"serialized trace frame: {count} data values announced, "
                         f"{(end - pos) // 4} present")
    data = np.frombuffer(buf, dtype=_FLOAT32[order], count=count, offset=pos)
    if order == ">":
        data = data.astype(np.float32)
    return dims, data_offset, data


def decode_traces_serialized(buf, *, max_nozzle_id: int | None = None, n_samples: int | None = None,
                             sample_rate_hz: float | None = None, cdr_only: bool = False) -> TraceFrame:
    """:func:`decode_traces` of a serialized trace message, as a raw subscription
    (``create_subscription(..., raw=True)``) takes it.

    The traces are a read-only view of ``buf``: no conversion to a Python message and
    no copy of the ``n_nozzles x n_samples`` float32 samples (a 1,024-nozzle frame is
    2 MB). The same checks and errors as :func:`decode_traces`.

    Parameters
    ----------
    buf : bytes or std_msgs.msg.Float32MultiArray
        The serialized ``std_msgs/Float32MultiArray`` (CDR, either byte order; another
        encapsulation is deserialized by rclpy first); a message object is decoded by
        :func:`decode_traces`.
    max_nozzle_id, n_samples, sample_rate_hz
        As for :func:`decode_traces`.
    cdr_only : bool
        Refuse (FrameError) bytes that are not plain CDR instead of handing them to rclpy, whose
        deserialiser prints its own complaints on stderr (a rosbag2 bag stores CDR only).

    Returns
    -------
    TraceFrame
    """
    if isinstance(buf, Float32MultiArray):
        return decode_traces(buf, max_nozzle_id=max_nozzle_id, n_samples=n_samples, sample_rate_hz=sample_rate_hz)
    if not isinstance(buf, (bytes, bytearray, memoryview)):
        raise FrameError(f"expected a serialized std_msgs/Float32MultiArray (bytes), got {type(buf).__name__}")
    if cdr_only and bytes(buf[:2]) not in _CDR_BYTE_ORDER:
        raise FrameError("not a serialised std_msgs/msg/Float32MultiArray: " + (
            f"its first bytes {bytes(buf[:4]).hex()} are not a CDR header" if len(buf) else "an empty message"))
    if len(buf) < 4:
        raise FrameError(f"serialized trace frame of {len(buf)} bytes")
    parts = _read_cdr_traces(buf)
    if parts is None:
        from rclpy.serialization import deserialize_message

        try:  # another encapsulation: rclpy's deserialiser, whose RMWError had ended the node (helper-140)
            msg = deserialize_message(bytes(buf), Float32MultiArray)
        except Exception as exc:  # noqa: BLE001 - any failure to read it is this message's
            raise FrameError(f"not a serialised std_msgs/msg/Float32MultiArray (its first bytes "
                             f"{bytes(buf[:4]).hex()}): {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}"
                             ) from None
        return decode_traces(msg, max_nozzle_id=max_nozzle_id, n_samples=n_samples, sample_rate_hz=sample_rate_hz)
    dims, data_offset, data = parts
    return _decode(dims, data_offset, data, max_nozzle_id=max_nozzle_id, n_samples=n_samples,
                   sample_rate_hz=sample_rate_hz)


def restamp_traces(msg, *, frame_id: int, stamp: float) -> None:
    """Rewrite the frame id and stamp of an encoded frame in place (for replaying frames).

    Cheaper than encoding again: only the header values change.
    """
    fid = _check_uint("frame_id", frame_id, _EXACT * _EXACT)
    st = float(stamp)
    if not (math.isfinite(st) and st >= 0):
        raise FrameError(f"stamp must be a finite time >= 0 s, got {stamp!r}")
    sec = int(st)
    usec = min(int(round((st - sec) * 1e6)), 999_999)
    msg.data[2], msg.data[3] = fid % _EXACT, fid // _EXACT
    msg.data[5], msg.data[6], msg.data[7] = sec % _EXACT, sec // _EXACT, usec
