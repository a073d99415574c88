"""msg_defs: inkdiag's wire contract on std_msgs types.

Topic names (:mod:`msg_defs.topics`), QoS profiles (:mod:`msg_defs.qos`),
the trace codec (:mod:`msg_defs.codec`), the JSON messages for operators
(:mod:`msg_defs.labels`, :mod:`msg_defs.drying`, :mod:`msg_defs.estimates`,
:mod:`msg_defs.truth`) and ``/diagnostics`` (:mod:`msg_defs.diagnostics`).
Every wire detail of inkdiag lives in this package and nowhere else.
"""

from .errors import MessageError
from .codec import (
    HEADER_LEN,
    SCHEMA_VERSION,
    TRACE_MSG_TYPE,
    FrameError,
    TraceFrame,
    decode_traces,
    decode_traces_serialized,
    encode_traces,
    restamp_traces,
)
from ._json import JSON_SCHEMA_VERSION, serialized
from .labels import (
    DRIED_CLASSES,
    HEALTHY_CLASSES,
    LABELS_MSG_TYPE,
    UNKNOWN_CLASS,
    LabelsReport,
    decode_labels,
    encode_labels,
    serialize_labels,
)
from .drying import DRYING_MSG_TYPE, MAX_NOZZLE_ID, DryingNozzles, decode_drying, encode_drying, serialize_drying
from .estimates import (
    ESTIMATES_ARRAY_MSG_TYPE,
    ESTIMATES_MSG_TYPE,
    FIELDS,
    FmEstimates,
    decode_estimates,
    decode_estimates_array,
    encode_estimates,
    encode_estimates_array,
)
from .truth import TRUTH_MSG_TYPE, GroundTruth, decode_truth, encode_truth, truth_from_arrays
from .diagnostics import DIAGNOSTICS_MSG_TYPE, GATE_CLEARED_KEY, build_diagnostics, diagnostics_values
from .qos import DIAGNOSTICS_QOS, RELIABLE_QOS, TRACES_QOS
from . import topics

__all__ = [
    "DIAGNOSTICS_MSG_TYPE",
    "GATE_CLEARED_KEY",
    "DIAGNOSTICS_QOS",
    "DRIED_CLASSES",
    "DRYING_MSG_TYPE",
    "MAX_NOZZLE_ID",
    "DryingNozzles",
    "ESTIMATES_ARRAY_MSG_TYPE",
    "ESTIMATES_MSG_TYPE",
    "FIELDS",
    "FmEstimates",
    "FrameError",
    "GroundTruth",
    "HEADER_LEN",
    "HEALTHY_CLASSES",
    "JSON_SCHEMA_VERSION",
    "LABELS_MSG_TYPE",
    "LabelsReport",
    "MessageError",
    "RELIABLE_QOS",
    "SCHEMA_VERSION",
    "TRACES_QOS",
    "TRACE_MSG_TYPE",
    "TRUTH_MSG_TYPE",
    "TraceFrame",
    "UNKNOWN_CLASS",
    "build_diagnostics",
    "decode_drying",
    "decode_estimates",
    "decode_estimates_array",
    "decode_labels",
    "decode_traces",
    "decode_traces_serialized",
    "decode_truth",
    "diagnostics_values",
    "encode_drying",
    "encode_estimates",
    "encode_estimates_array",
    "encode_labels",
    "encode_traces",
    "encode_truth",
    "restamp_traces",
    "serialize_drying",
    "serialize_labels",
    "serialized",
    "topics",
    "truth_from_arrays",
]
