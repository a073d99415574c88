"""Drying nozzles: one ``std_msgs/String`` JSON object per labelled trace message, topic ``drying_nozzles``.

What the FE node subscribes to: the nozzles that the FDI node labelled as
one of the dried classes in one trace message, i.e. one nozzle range of one
frame (an empty list is published too, so a subscriber knows that the range
has no dried nozzle, e.g. that a nozzle recovered)::

    {"schema": "inkdiag.drying_nozzles", "schema_version": 1,
     "frame_id": 42, "stamp": 1763798400.125,
     "first_nozzle": 200, "n_nozzles": 200,
     "nozzles": [207, 219], "classes": ["deeply_dried", "slightly_dried"]}

``nozzles`` are sorted ids; ``classes[i]`` is the class of ``nozzles[i]``.
``first_nozzle`` and ``n_nozzles`` are the labelled range (the trace
message's); every listed nozzle lies in it. Both are optional, together: a
message without them (written before they existed) covers an unknown range
of its frame, and a subscriber matches it on ``frame_id`` alone.

A bad entry (an id that is not an integer in the range, a class that is not
a dried one) costs only itself: :func:`decode_drying` keeps the others and
says what it left out in ``DryingNozzles.dropped``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from std_msgs.msg import String

from . import _json
from .errors import MessageError

#: Nozzle ids are below 2**24, as in the trace header (:mod:`.codec`).
MAX_NOZZLE_ID = 1 << 24
from .labels import DRIED_CLASSES, LabelsReport

__all__ = ["DRYING_SCHEMA", "DRYING_MSG_TYPE", "DryingNozzles", "encode_drying", "serialize_drying", "decode_drying"]

DRYING_SCHEMA = "inkdiag.drying_nozzles"
DRYING_MSG_TYPE = String


@dataclass(frozen=True)
class DryingNozzles:
    frame_id: int
    stamp: float
    nozzles: tuple = ()
    classes: tuple = ()
    first_nozzle: int | None = None  # the labelled range; None: unknown
    n_nozzles: int | None = None
    #: what :func:`decode_drying` left out (its bad entries), for the log; "" when nothing
    dropped: str = field(default="", compare=False)

    def __post_init__(self):
        if (self.first_nozzle is None) != (self.n_nozzles is None):
            raise MessageError(f"{DRYING_SCHEMA}: first_nozzle and n_nozzles go together, got "
                               f"{self.first_nozzle!r}, {self.n_nozzles!r}")

    @classmethod
    def from_labels(cls, report: LabelsReport) -> "DryingNozzles":
        """The dried nozzles of a labels report, with its range."""
        pairs = [(nz, c) for nz, c, _ in report.faults if c in DRIED_CLASSES]
        return cls(report.frame_id, report.stamp, tuple(p[0] for p in pairs), tuple(p[1] for p in pairs),
                   report.first_nozzle, report.n_nozzles)


def encode_drying(d: DryingNozzles) -> String:
    body = {"frame_id": int(d.frame_id), "stamp": round(float(d.stamp), 6)}
    if d.first_nozzle is not None:
        body.update(first_nozzle=int(d.first_nozzle), n_nozzles=int(d.n_nozzles))
    body.update(nozzles=[int(x) for x in d.nozzles], classes=[str(c) for c in d.classes])
    return _json.dump(DRYING_SCHEMA, body)


_DRYING_HEAD = _json.head(DRYING_SCHEMA)


def serialize_drying(d: DryingNozzles) -> bytes:
    """The CDR bytes of :func:`encode_drying`'s message, byte for byte ``serialized(encode_drying(d))``,
    the text written directly instead of through ``json`` (what the fdi node publishes for every frame).
    A stamp that is not finite, ``nozzles`` or ``classes`` not a tuple, or any value the conversions
    refuse goes the ``json`` way, which writes it or raises as :func:`encode_drying` does."""
    try:
        return _json.cdr(_drying_text(d))
    except Exception:  # noqa: BLE001 - NotPlain, or a value int() / float() refuse: the json way decides
        return _json.serialized(encode_drying(d))


def _drying_text(d: DryingNozzles) -> str:
    if type(d.nozzles) is not tuple or type(d.classes) is not tuple:
        raise _json.NotPlain  # read once, here: an iterator would be left empty for the json way
    frame_id, stamp = int(d.frame_id), _json.plain(round(float(d.stamp), 6), float)  # encode_drying's conversions
    span = "" if d.first_nozzle is None else f'"first_nozzle":{int(d.first_nozzle)},"n_nozzles":{int(d.n_nozzles)},'
    nozzles = ",".join([str(int(x)) for x in d.nozzles])
    classes = ",".join([_json.quote(str(c)) for c in d.classes])
    return f'{_DRYING_HEAD}"frame_id":{frame_id},"stamp":{stamp!r},{span}"nozzles":[{nozzles}],"classes":[{classes}]}}'


def decode_drying(msg) -> DryingNozzles:
    """Parse and validate a ``drying_nozzles`` message; raise :class:`MessageError` for a message that
    cannot be read (not JSON, another schema, a missing or mistyped field, ``classes`` not one per
    nozzle). An entry whose id is not an integer in [0, 2**24) and in the labelled range, or whose class
    is not a dried one, is left out alone: the result keeps the other entries and says which it left
    out in ``dropped``."""
    s = DRYING_SCHEMA
    doc = _json.load(msg, s)
    frame_id = _json.field(doc, s, "frame_id", int, nonneg=True)
    stamp = _json.field(doc, s, "stamp", float, nonneg=True)
    nozzles = _json.field(doc, s, "nozzles", list)
    classes = _json.field(doc, s, "classes", list)
    if len(classes) != len(nozzles):
        raise MessageError(f"{s}: classes must be one dried class per nozzle ({', '.join(DRIED_CLASSES)}), "
                           f"got {len(classes)} for {len(nozzles)} nozzles: {classes!r:.80}")
    first = n = None
    if "first_nozzle" in doc or "n_nozzles" in doc:  # the range: both or neither
        first = _json.field(doc, s, "first_nozzle", int, nonneg=True)
        n = _json.field(doc, s, "n_nozzles", int, nonneg=True)
    lo, hi = (0, MAX_NOZZLE_ID) if first is None else (first, min(first + n, MAX_NOZZLE_ID))
    keep = [type(x) is int and lo <= x < hi and c in DRIED_CLASSES for x, c in zip(nozzles, classes)]
    dropped = ""
    if not all(keep):
        bad = [(x, c) for x, c, k in zip(nozzles, classes, keep) if not k]
        where = "[0, 2**24)" if first is None else f"the labelled range first_nozzle {first}, n_nozzles {n}"
        dropped = (f"{s}: left out {len(bad)} of {len(nozzles)} entries, ids not integers in {where} or classes "
                   f"not one of {', '.join(DRIED_CLASSES)}: {bad!r:.100}")
        nozzles = [x for x, k in zip(nozzles, keep) if k]
        classes = [c for c, k in zip(classes, keep) if k]
    return DryingNozzles(frame_id, stamp, tuple(nozzles), tuple(classes), first, n, dropped)
