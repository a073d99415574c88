"""msg_defs: inkdiag's wire contract on std_msgs types.

Topic names (:mod:`msg_defs.topics`), QoS profiles (:mod:`msg_defs.qos`) and
codecs with validation (:mod:`msg_defs.codec`). Every wire detail of inkdiag
lives in this package and nowhere else.
"""

from .codec import (
    HEADER_LEN,
    SCHEMA_VERSION,
    TRACE_MSG_TYPE,
    FrameError,
    TraceFrame,
    decode_traces,
    encode_traces,
)
from .qos import DIAGNOSTICS_QOS, RELIABLE_QOS, TRACES_QOS
from . import topics

__all__ = [
    "DIAGNOSTICS_QOS",
    "FrameError",
    "HEADER_LEN",
    "RELIABLE_QOS",
    "SCHEMA_VERSION",
    "TRACES_QOS",
    "TRACE_MSG_TYPE",
    "TraceFrame",
    "decode_traces",
    "encode_traces",
    "topics",
]
