"""Simulator ground truth: one ``std_msgs/String`` JSON object per frame, topic ``ground_truth``.

Published by ``printhead_sim`` only, beside each trace frame, so a scorecard
can compare the graph's outputs with what was simulated::

    {"schema": "inkdiag.ground_truth", "schema_version": 1,
     "frame_id": 42, "stamp": 1763798400.125, "first_nozzle": 0, "n_nozzles": 64,
     "faults": [{"nozzle": 7, "class": "deeply_dried", "fm": -640000.0,
                 "mu_nozzle": 0.061}, ...]}

Nozzles not listed under ``faults`` are healthy (``healthy_nozzle``).
``fm`` (1/s) and ``mu_nozzle`` (Pa s) are the true values of that trace.
"""

from __future__ import annotations

from dataclasses import dataclass

from std_msgs.msg import String

from . import _json
from .errors import MessageError
from .labels import HEALTHY_CLASSES

__all__ = ["TRUTH_SCHEMA", "TRUTH_MSG_TYPE", "GroundTruth", "encode_truth", "decode_truth", "truth_from_arrays"]

TRUTH_SCHEMA = "inkdiag.ground_truth"
TRUTH_MSG_TYPE = String


@dataclass(frozen=True)
class GroundTruth:
    frame_id: int
    stamp: float
    first_nozzle: int
    n_nozzles: int
    #: tuple of (nozzle, class value, fm 1/s, mu_nozzle Pa s)
    faults: tuple = ()

    def class_of(self) -> dict:
        """``{nozzle: class}`` of the listed (faulty) nozzles."""
        return {f[0]: f[1] for f in self.faults}


def encode_truth(t: GroundTruth) -> String:
    return _json.dump(TRUTH_SCHEMA, {
        "frame_id": int(t.frame_id), "stamp": round(float(t.stamp), 6),
        "first_nozzle": int(t.first_nozzle), "n_nozzles": int(t.n_nozzles),
        "faults": [{"nozzle": int(nz), "class": str(c), "fm": float(fm), "mu_nozzle": float(mu)}
                   for nz, c, fm, mu in t.faults],
    })


def decode_truth(msg) -> GroundTruth:
    s = TRUTH_SCHEMA
    doc = _json.load(msg, s)
    try:
        faults = tuple((int(f["nozzle"]), str(f["class"]), float(f["fm"]), float(f["mu_nozzle"]))
                       for f in _json.field(doc, s, "faults", list))
    except (KeyError, TypeError, ValueError) as exc:
        raise MessageError(f"{s}: malformed fault entry ({exc!r})") from None
    return GroundTruth(_json.field(doc, s, "frame_id", int, nonneg=True),
                       _json.field(doc, s, "stamp", float, nonneg=True),
                       _json.field(doc, s, "first_nozzle", int, nonneg=True),
                       _json.field(doc, s, "n_nozzles", int, nonneg=True), faults)


def truth_from_arrays(*, frame_id, stamp, first_nozzle, classes, fm, mu_nozzle,
                      healthy=HEALTHY_CLASSES) -> GroundTruth:
    """A :class:`GroundTruth` listing the non-healthy rows of per-row arrays."""
    import numpy as np

    values = np.array([getattr(c, "value", c) for c in classes], dtype=object)
    rows = np.flatnonzero(~np.isin(values.astype(str), healthy))
    return GroundTruth(int(frame_id), float(stamp), int(first_nozzle), int(values.size),
                       tuple((int(first_nozzle + i), str(values[i]), float(fm[i]), float(mu_nozzle[i]))
                             for i in rows))
