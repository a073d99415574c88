"""Drying nozzles: one ``std_msgs/String`` JSON object per labelled frame, topic ``drying_nozzles``.

What the FE node subscribes to: the nozzles that the FDI node labelled as
one of the dried classes in this frame (an empty list is published too, so
a subscriber knows that a nozzle recovered)::

    {"schema": "inkdiag.drying_nozzles", "schema_version": 1,
     "frame_id": 42, "stamp": 1763798400.125,
     "nozzles": [7, 19], "classes": ["deeply_dried", "slightly_dried"]}

``nozzles`` are sorted ids; ``classes[i]`` is the class of ``nozzles[i]``.
"""

from __future__ import annotations

from dataclasses import dataclass

from std_msgs.msg import String

from . import _json
from .errors import MessageError
from .labels import DRIED_CLASSES, LabelsReport

__all__ = ["DRYING_SCHEMA", "DRYING_MSG_TYPE", "DryingNozzles", "encode_drying", "decode_drying"]

DRYING_SCHEMA = "inkdiag.drying_nozzles"
DRYING_MSG_TYPE = String


@dataclass(frozen=True)
class DryingNozzles:
    frame_id: int
    stamp: float
    nozzles: tuple = ()
    classes: tuple = ()

    @classmethod
    def from_labels(cls, report: LabelsReport) -> "DryingNozzles":
        """The dried nozzles of a labels report."""
        pairs = [(nz, c) for nz, c, _ in report.faults if c in DRIED_CLASSES]
        return cls(report.frame_id, report.stamp, tuple(p[0] for p in pairs), tuple(p[1] for p in pairs))


def encode_drying(d: DryingNozzles) -> String:
    return _json.dump(DRYING_SCHEMA, {
        "frame_id": int(d.frame_id), "stamp": round(float(d.stamp), 6),
        "nozzles": [int(x) for x in d.nozzles], "classes": [str(c) for c in d.classes],
    })


def decode_drying(msg) -> DryingNozzles:
    """Parse and validate a ``drying_nozzles`` message; raise :class:`MessageError` otherwise."""
    s = DRYING_SCHEMA
    doc = _json.load(msg, s)
    frame_id = _json.field(doc, s, "frame_id", int, nonneg=True)
    stamp = _json.field(doc, s, "stamp", float, nonneg=True)
    nozzles = _json.field(doc, s, "nozzles", list)
    classes = _json.field(doc, s, "classes", list)
    if not all(isinstance(x, int) and not isinstance(x, bool) and x >= 0 for x in nozzles):
        raise MessageError(f"{s}: nozzles must be non-negative integers, got {nozzles!r:.80}")
    if len(classes) != len(nozzles) or not all(c in DRIED_CLASSES for c in classes):
        raise MessageError(
            f"{s}: classes must be one dried class per nozzle ({', '.join(DRIED_CLASSES)}), "
            f"got {len(classes)} for {len(nozzles)} nozzles: {classes!r:.80}"
        )
    return DryingNozzles(frame_id, stamp, tuple(nozzles), tuple(classes))
