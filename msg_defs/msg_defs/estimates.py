"""f_m estimates of drying nozzles, in two forms published side by side.

``fm_estimates`` (``std_msgs/String``, operator-readable JSON), one per trace
message (a frame, or one nozzle range of a frame) in which the FE node
estimated anything::

    {"schema": "inkdiag.fm_estimates", "schema_version": 1,
     "frame_id": 42, "stamp": 1763798400.125, "first_nozzle": 0,
     "estimates": [{"nozzle": 7, "fm": -612000.0, "fm_std": 6700.0,
                    "d_mu": 0.0205, "viscosity": 0.0290,
                    "fm_trend": -598000.0, "fm_rate": -21000.0,
                    "eta_deeply_dried_s": 14.2}, ...]}

``fm_estimates/array`` (``std_msgs/Float64MultiArray``), the same numbers for
programs: ``layout.dim[0] = ("estimate", n, n * F)``,
``layout.dim[1] = ("field", F, F)``, ``layout.data_offset = 3`` with the
header ``data[0:3] = [schema_version, frame_id, stamp]`` and then row-major
``data[3 + i * F + j]`` = field ``FIELDS[j]`` of estimate ``i``. Unknown
values (no trend yet, no ETA) are NaN in the array and ``null`` in the JSON.
``first_nozzle`` (optional, JSON only) is the first nozzle of the trace
message the estimates come from: a frame sent as several nozzle ranges gets
one message per range, all with the frame's ``frame_id``.

Fields (:data:`FIELDS`, SI units):

================== ==========================================================
nozzle             nozzle id
fm                 this frame's f_m estimate, 1/s (negative when drying)
fm_std             its standard deviation, 1/s
d_mu               nozzle viscosity increase ``-fm / alpha``, Pa s
viscosity          nozzle ink viscosity, Pa s
fm_trend           smoothed f_m over this nozzle's history, 1/s
fm_rate            smoothed d f_m / dt, 1/s^2
eta_deeply_dried_s time until the trend reaches the deeply-dried level, s
                   (0 when already there; null/NaN when it is not heading there)
================== ==========================================================
"""

from __future__ import annotations

import array
import math
from dataclasses import dataclass

import numpy as np
from std_msgs.msg import Float64MultiArray, MultiArrayDimension, String

from . import _json
from .errors import MessageError

__all__ = [
    "ESTIMATES_SCHEMA",
    "FIELDS",
    "ESTIMATES_MSG_TYPE",
    "ESTIMATES_ARRAY_MSG_TYPE",
    "FmEstimates",
    "encode_estimates",
    "decode_estimates",
    "encode_estimates_array",
    "decode_estimates_array",
]

ESTIMATES_SCHEMA = "inkdiag.fm_estimates"
ESTIMATES_MSG_TYPE = String
ESTIMATES_ARRAY_MSG_TYPE = Float64MultiArray
FIELDS = ("nozzle", "fm", "fm_std", "d_mu", "viscosity", "fm_trend", "fm_rate", "eta_deeply_dried_s")
ARRAY_HEADER_LEN = 3
ESTIMATE_LABEL = "estimate"
FIELD_LABEL = "field"


@dataclass(frozen=True)
class FmEstimates:
    """One frame's (or frame range's) estimates: ``table`` is float64 (n, len(FIELDS)), columns in
    FIELDS order; ``first_nozzle`` the trace message's first nozzle (None: not said, e.g. the array form)."""

    frame_id: int
    stamp: float
    table: np.ndarray
    first_nozzle: int | None = None

    def column(self, name: str) -> np.ndarray:
        return self.table[:, FIELDS.index(name)]

    @property
    def nozzles(self) -> np.ndarray:
        return self.column("nozzle").astype(np.int64)

    @classmethod
    def from_columns(cls, frame_id, stamp, *, first_nozzle=None, **columns) -> "FmEstimates":
        """Build from one (n,) array per field name (every field of FIELDS required)."""
        missing = [f for f in FIELDS if f not in columns]
        extra = [k for k in columns if k not in FIELDS]
        if missing or extra:
            raise MessageError(f"fm_estimates: missing fields {missing}, unknown fields {extra}")
        table = np.column_stack([np.asarray(columns[f], dtype=np.float64).reshape(-1) for f in FIELDS])
        return cls(int(frame_id), float(stamp), table.reshape(-1, len(FIELDS)),
                   None if first_nozzle is None else int(first_nozzle))


def encode_estimates(e: FmEstimates) -> String:
    """The JSON form (``fm_estimates``)."""
    rows = []
    for r in e.table:
        d = {f: _json.finite_or_none(v) for f, v in zip(FIELDS, r)}
        d["nozzle"] = int(r[0])
        rows.append(d)
    body = {"frame_id": e.frame_id, "stamp": round(e.stamp, 6)}
    if e.first_nozzle is not None:
        body["first_nozzle"] = int(e.first_nozzle)
    body["estimates"] = rows
    return _json.dump(ESTIMATES_SCHEMA, body)


def decode_estimates(msg) -> FmEstimates:
    """Parse and validate the JSON form; raise :class:`MessageError` otherwise."""
    s = ESTIMATES_SCHEMA
    doc = _json.load(msg, s)
    frame_id = _json.field(doc, s, "frame_id", int, nonneg=True)
    stamp = _json.field(doc, s, "stamp", float, nonneg=True)
    first = _json.field(doc, s, "first_nozzle", int, nonneg=True) if "first_nozzle" in doc else None
    rows = _json.field(doc, s, "estimates", list)
    table = np.empty((len(rows), len(FIELDS)))
    for i, row in enumerate(rows):
        if not isinstance(row, dict) or set(row) != set(FIELDS):
            raise MessageError(f"{s}: estimate {i} must have exactly the fields {FIELDS}, got {row!r:.80}")
        for j, f in enumerate(FIELDS):
            v = row[f]
            if v is None and f != "nozzle":
                table[i, j] = math.nan
            elif isinstance(v, (int, float)) and not isinstance(v, bool):
                table[i, j] = v
            else:
                raise MessageError(f"{s}: estimate {i} field {f!r} must be a number, got {v!r}")
    return FmEstimates(frame_id, stamp, table, first)


def encode_estimates_array(e: FmEstimates) -> Float64MultiArray:
    """The numeric form (``fm_estimates/array``)."""
    n, F = e.table.shape[0], len(FIELDS)
    msg = Float64MultiArray()
    msg.layout.dim = [MultiArrayDimension(label=ESTIMATE_LABEL, size=n, stride=n * F),
                      MultiArrayDimension(label=FIELD_LABEL, size=F, stride=F)]
    msg.layout.data_offset = ARRAY_HEADER_LEN
    buf = np.concatenate([[_json.JSON_SCHEMA_VERSION, e.frame_id, e.stamp], e.table.ravel()])
    data = array.array("d")
    data.frombytes(buf.astype(np.float64).tobytes())
    msg.data = data
    return msg


def decode_estimates_array(msg) -> FmEstimates:
    """Decode and validate the numeric form; raise :class:`MessageError` otherwise."""
    if not isinstance(msg, Float64MultiArray):
        raise MessageError(f"expected a std_msgs/Float64MultiArray, got {type(msg).__name__}")
    dims = msg.layout.dim
    F = len(FIELDS)
    if len(dims) != 2 or (dims[0].label, dims[1].label) != (ESTIMATE_LABEL, FIELD_LABEL):
        raise MessageError(f"expected dimensions ('{ESTIMATE_LABEL}', '{FIELD_LABEL}'), "
                           f"got {[d.label for d in dims]}")
    n = int(dims[0].size)
    if int(dims[1].size) != F or int(dims[1].stride) != F or int(dims[0].stride) != n * F:
        raise MessageError(f"expected field size/stride {F} and estimate stride {n * F}, got "
                           f"({dims[1].size}, {dims[1].stride}, {dims[0].stride})")
    if int(msg.layout.data_offset) != ARRAY_HEADER_LEN:
        raise MessageError(f"expected data_offset {ARRAY_HEADER_LEN}, got {msg.layout.data_offset}")
    try:
        data = np.frombuffer(msg.data, dtype=np.float64)
    except TypeError:
        data = np.asarray(msg.data, dtype=np.float64)
    if data.size != ARRAY_HEADER_LEN + n * F:
        raise MessageError(f"expected {ARRAY_HEADER_LEN + n * F} values, got {data.size}")
    if data[0] != _json.JSON_SCHEMA_VERSION:
        raise MessageError(f"expected schema version {_json.JSON_SCHEMA_VERSION}, got {data[0]:g}")
    return FmEstimates(int(data[1]), float(data[2]), data[ARRAY_HEADER_LEN:].reshape(n, F).copy())
