"""Fault labels per frame: one ``std_msgs/String`` JSON object, topic ``labels``.

Operator-readable (``ros2 topic echo`` shows the JSON). Every label frame
answers one trace frame::

    {
      "schema": "inkdiag.labels", "schema_version": 1,
      "frame_id": 42,                 # the trace frame's id
      "stamp": 1763798400.125,        # the trace frame's measurement time, s since the epoch
      "first_nozzle": 0, "n_nozzles": 64,
      "model_id": "fdi-rf-kpi_y-3f2a9c1b",   # which FDI model labelled it
      "counts": {"healthy_nozzle": 55, "deeply_dried": 1, ..., "invalid": 1},
      "gate_cleared": 50,             # rows the healthy gate cleared (0: none, or no gate)
      "faults": [{"nozzle": 7, "class": "deeply_dried", "confidence": 0.91}, ...],
      "invalid": [{"nozzle": 12, "reason": "non_finite"}, ...]
    }

``counts`` has one entry per class present in the frame plus ``"invalid"``
(always present); they sum to ``n_nozzles``. ``faults`` lists every valid
nozzle whose class is not healthy (not in :data:`HEALTHY_CLASSES`), sorted
by nozzle id, with the classifier's probability of that class
(``confidence`` in [0, 1], 3 decimals). ``invalid`` lists the rows that
could not be judged and why (``non_finite``, ``flat``, ``clipped``).
``gate_cleared`` counts the rows the healthy gate (``inkdiag_core.HealthyGate``)
labelled healthy without the full model; they are also counted under their class
in ``counts`` (so it is at most ``n_nozzles - counts["invalid"]``). A message
without it (an older publisher) reads as 0.

A nozzle unlike every class the model knows (its open-set layer, issue 16) has
the class :data:`UNKNOWN_CLASS` (``"unknown"``): it is a fault (listed under
``faults``, never healthy) whose ``confidence`` is its unknown score, 1 minus
its largest per-class conformal p-value (``{"nozzle": 9, "class": "unknown",
"confidence": 0.995}``), and ``counts`` has an ``"unknown"`` entry when the frame
has one. It is not a drying class.
"""

from __future__ import annotations

import functools
from collections import Counter
from dataclasses import dataclass, field

import numpy as np
from std_msgs.msg import String

from . import _json
from .errors import MessageError

__all__ = [
    "LABELS_SCHEMA",
    "LABELS_MSG_TYPE",
    "HEALTHY_CLASSES",
    "DRIED_CLASSES",
    "INVALID_KEY",
    "UNKNOWN_CLASS",
    "LabelsReport",
    "encode_labels",
    "serialize_labels",
    "decode_labels",
]

LABELS_SCHEMA = "inkdiag.labels"
LABELS_MSG_TYPE = String
#: Classes that are not listed under ``faults`` (only counted). The wire copy of
#: ``inkdiag_core.faults.HEALTHY_VALUES`` (msg_defs does not import the core);
#: tests/core/test_vocabulary.py pins the two together, as for DRIED_CLASSES.
HEALTHY_CLASSES = ("ok_signal", "healthy_nozzle")
#: Class of a nozzle unlike every known class: a fault of no known kind (wire copy of
#: ``inkdiag_core.openset.UNKNOWN``; tests/core/test_vocabulary.py pins the two together).
UNKNOWN_CLASS = "unknown"
#: The drying classes, in increasing severity (wire copy of ``inkdiag_core.faults.DRIED_VALUES``).
DRIED_CLASSES = ("slightly_dried", "intermediately_dried", "deeply_dried")
#: Key of the invalid-row count in ``counts``.
INVALID_KEY = "invalid"
_HEALTHY = frozenset(HEALTHY_CLASSES)
_STR = frozenset({str})


@dataclass(frozen=True)
class LabelsReport:
    """One frame's labels, as carried by the ``labels`` topic.

    Attributes
    ----------
    frame_id, first_nozzle, n_nozzles : int
    stamp : float
        Measurement time of the trace frame, s since the epoch.
    model_id : str
    counts : dict of str -> int
        Per class value, plus ``"invalid"``; sums to ``n_nozzles``.
    faults : tuple of (nozzle, class, confidence)
        Valid, non-healthy nozzles, by nozzle id.
    invalid : tuple of (nozzle, reason)
    gate_cleared : int
        Rows the healthy gate cleared (also counted under their class).
    """

    frame_id: int
    stamp: float
    first_nozzle: int
    n_nozzles: int
    model_id: str
    counts: dict = field(default_factory=dict)
    faults: tuple = ()
    invalid: tuple = ()
    gate_cleared: int = 0

    @classmethod
    def from_arrays(cls, *, frame_id, stamp, first_nozzle, classes, confidence, valid, reasons,
                    model_id: str, gate_cleared=None, class_codes=None, class_names=None) -> "LabelsReport":
        """Build a report from the per-row arrays of one frame.

        Parameters
        ----------
        classes : array_like of str, shape (n,)
            Predicted class value per row (ignored where ``valid`` is False).
        confidence : array_like of float, shape (n,)
            Probability of the predicted class.
        valid : array_like of bool, shape (n,)
        reasons : array_like of str, shape (n,)
            Why a row is invalid (``""`` for valid rows).
        gate_cleared : array_like of bool, shape (n,), optional
            Rows the healthy gate cleared; None: none.
        class_codes : ndarray of unsigned int, shape (n,), optional
            ``classes`` as indices into ``class_names`` (``class_names[class_codes[i]] == classes[i]``
            where ``valid``, the caller's promise: ``classes`` is then not read): with them the report is
            built from counts of the codes, not a string per row (the fdi node's reports,
            ``inkdiag_core.FrameLabels.class_codes``); the same report. Used only where every argument is
            an array of the expected kind (else ``classes``, and what they raise).
        class_names : tuple of str, optional
            Distinct class names, with ``class_codes``.
        """
        if class_codes is not None:
            report = cls._from_codes(frame_id, stamp, first_nozzle, class_codes, class_names, confidence, valid,
                                     reasons, model_id, gate_cleared, classes)
            if report is not None:
                return report
        classes = np.asarray(classes, dtype=object)
        valid = np.asarray(valid, dtype=bool)
        n = valid.shape[0] if valid.ndim else 0
        if valid.shape != (n,) or classes.shape != (n,) or np.shape(confidence) != (n,) or np.shape(reasons) != (n,):
            raise MessageError(
                f"labels: classes, confidence, valid and reasons must all have shape ({n},), got "
                f"{classes.shape}, {np.shape(confidence)}, {valid.shape}, {np.shape(reasons)}"
            )
        # Lists and counts of the Python strings instead of np.unique / np.isin, which sort and convert:
        # this runs for every published frame (scripts/bench node).
        cl = classes.tolist()
        n_valid = int(np.count_nonzero(valid))
        hint = None  # the gate's rows, a hint only: checked, and its errors raised, where they always were
        if gate_cleared is not None and n_valid == n:
            try:
                hint = np.asarray(gate_cleared, dtype=bool)
            except Exception:  # noqa: BLE001 - raised below, after what the old code checked first
                pass
            if hint is not None and hint.shape != (n,):
                hint = None
        if n_valid == n and set(map(type, cl)) <= _STR:  # plain str: list.count and `in` agree with a Counter's keys
            by_class = {h: k for h in HEALTHY_CLASSES if (k := cl.count(h))}  # mostly the very same str: fast
            n_healthy = sum(by_class.values())
            faulty = [] if n_healthy == n else None
            if faulty is None and hint is not None:  # the gate's rows are healthy: faults among the others only
                rest = (~hint).nonzero()[0].tolist()  # hint is 1-D: flatnonzero's ravel is not needed
                faulty = [i for i in rest if cl[i] not in _HEALTHY]
                if n - len(faulty) != n_healthy:  # a cleared row is not of a healthy class: every row, below
                    faulty = None
            if faulty is None:
                faulty = [i for i, c in enumerate(cl) if c not in _HEALTHY]
            for i in faulty:  # a few rows: a Counter costs more than it saves
                by_class[cl[i]] = by_class.get(cl[i], 0) + 1
        elif n_valid == n:
            by_class = Counter(cl)
            faulty = [i for i, c in enumerate(cl) if c not in _HEALTHY]
        else:
            ok = valid.tolist()
            by_class = Counter(c for c, v in zip(cl, ok) if v)
            faulty = [i for i, (c, v) in enumerate(zip(cl, ok)) if v and c not in _HEALTHY]
        counts = {str(c): by_class[c] for c in sorted(by_class)}
        counts[INVALID_KEY] = n - n_valid
        f0 = int(first_nozzle)
        faults = tuple(zip([f0 + i for i in faulty], [str(cl[i]) for i in faulty], _rounded(confidence, faulty)))
        invalid = () if n_valid == n else _invalid_rows(valid, reasons, f0)
        n_cleared = 0
        if gate_cleared is not None:
            g = hint if hint is not None else np.asarray(gate_cleared, dtype=bool)
            if g.shape != (n,):
                raise MessageError(f"labels: gate_cleared must have shape ({n},), got {g.shape}")
            n_cleared = int(np.count_nonzero(g if hint is not None else g & valid))  # a hint: every row valid
        return cls(int(frame_id), float(stamp), int(first_nozzle), int(n), str(model_id), counts,
                   faults, invalid, n_cleared)

    @classmethod
    def _from_codes(cls, frame_id, stamp, first_nozzle, codes, names, confidence, valid, reasons, model_id,
                    gate_cleared, classes):
        """:meth:`from_arrays` from class codes: the report, or None where an argument is not of the kind this
        takes (then the per-row strings build it, and raise what they raise)."""
        plain = type(names) is tuple and all(type(c) is str for c in names)  # checked here: the cache keys by ==
        vocab = _vocabulary(names) if plain else None
        if (vocab is None or type(codes) is not np.ndarray or codes.dtype.kind != "u" or codes.ndim != 1
                or type(valid) is not np.ndarray or valid.dtype != bool or valid.shape != codes.shape
                or type(confidence) is not np.ndarray or confidence.dtype != np.float64
                or confidence.shape != codes.shape or type(classes) is not np.ndarray or classes.shape != codes.shape
                or type(reasons) is not np.ndarray or reasons.shape != codes.shape):
            return None
        n = codes.shape[0]
        if gate_cleared is not None and (type(gate_cleared) is not np.ndarray or gate_cleared.dtype != bool
                                         or gate_cleared.shape != (n,)):
            return None
        fault, order = vocab
        n_valid = int(np.count_nonzero(valid))
        every = n_valid == n
        if n and codes.max() >= len(names):  # a code past the names (bincount would size its counts by it)
            return None
        counted = np.bincount(codes if every else codes[valid], minlength=len(names)).tolist()
        counts = {names[i]: counted[i] for i in order if counted[i]}  # by class name, as from_arrays sorts
        counts[INVALID_KEY] = n - n_valid
        faulty = np.flatnonzero(fault.take(codes) if every else fault.take(codes) & valid)
        f0 = int(first_nozzle)
        faults = tuple(zip((faulty + f0).tolist(), [names[c] for c in codes[faulty].tolist()],
                           _rounded(confidence, faulty)))
        invalid = () if every else _invalid_rows(valid, reasons, f0)
        n_cleared = 0 if gate_cleared is None else int(np.count_nonzero(gate_cleared if every
                                                                         else gate_cleared & valid))
        return cls(int(frame_id), float(stamp), f0, int(n), str(model_id), counts, faults, invalid, n_cleared)

    def nozzles_of(self, class_values) -> list:
        """Ids of the listed nozzles whose class is one of ``class_values``."""
        wanted = set(class_values)
        return [nz for nz, c, _ in self.faults if c in wanted]


def _rounded(confidence, rows) -> list:
    """The confidences of ``rows`` rounded to 3 decimals (``np.round(., 3)``), as floats."""
    conf = np.asarray(confidence, dtype=float)[rows]
    return (np.rint(conf * 1e3, out=conf) / 1e3).tolist()


def _invalid_rows(valid, reasons, first_nozzle: int) -> tuple:
    """``(nozzle, reason)`` of each row not ``valid``."""
    bad = ~valid
    ids = np.arange(first_nozzle, first_nozzle + valid.shape[0])
    return tuple(zip(ids[bad].tolist(), map(str, np.asarray(reasons, dtype=object)[bad].tolist())))


@functools.lru_cache(maxsize=64)
def _vocabulary(names: tuple):
    """``(fault, order)`` of a tuple of plain ``str`` class names (the caller checks their type: an equal tuple of
    other strings shares the entry): which are listed as faults (not healthy; a bool array by code), and the codes
    in the order of their names; None if the names are not distinct."""
    if len(set(names)) != len(names) or not names:
        return None
    return np.array([c not in _HEALTHY for c in names]), sorted(range(len(names)), key=names.__getitem__)


def encode_labels(report: LabelsReport) -> String:
    """``std_msgs/String`` with the report's JSON (see the module docstring)."""
    return _json.dump(LABELS_SCHEMA, {
        "frame_id": report.frame_id,
        "stamp": round(report.stamp, 6),
        "first_nozzle": report.first_nozzle,
        "n_nozzles": report.n_nozzles,
        "model_id": report.model_id,
        "counts": report.counts,
        "gate_cleared": report.gate_cleared,
        "faults": [{"nozzle": nz, "class": c, "confidence": p} for nz, c, p in report.faults],
        "invalid": [{"nozzle": nz, "reason": r} for nz, r in report.invalid],
    })


_LABELS_HEAD = _json.head(LABELS_SCHEMA)
#: repr(k / 1000) for k in 0..1000: a rounded confidence's text without repr's shortest-digits search (the same
#: text: the 3-decimal string is the shortest that reads back as that double).
_MILLI = [repr(k / 1000) for k in range(1001)]


def serialize_labels(report: LabelsReport) -> bytes:
    """The CDR bytes of :func:`encode_labels`'s message, byte for byte ``serialized(encode_labels(report))``,
    the text written directly instead of through ``json`` (what the fdi node publishes for every frame).

    A report whose values are not exactly what :meth:`LabelsReport.from_arrays` and :func:`decode_labels`
    give (a numpy scalar, a NaN, a bool, ``counts`` not a dict, ``faults`` not a tuple) goes the
    ``json`` way, which writes it or raises as :func:`encode_labels` does.
    """
    try:
        return _json.cdr(_labels_text(report))
    except Exception:  # noqa: BLE001 - NotPlain, or anything else amiss: the json way writes it or raises its error
        return _json.serialized(encode_labels(report))


def _labels_text(r: LabelsReport) -> str:
    if type(r.counts) is not dict or type(r.faults) is not tuple or type(r.invalid) is not tuple:
        raise _json.NotPlain  # read once, here: an iterator would be left empty for the json way
    p, q = _json.plain, _json.quote
    counts = ",".join([f"{q(p(c, str))}:{p(k, int)}" for c, k in r.counts.items()])
    quoted = {}  # each class's JSON string once (a frame of faults repeats a few classes)
    faults = []
    for f in r.faults:
        if type(f) is not tuple:  # read once, here: an iterator would be left empty for the json way
            raise _json.NotPlain
        nz, c, x = f
        if type(nz) is not int or type(c) is not str or type(x) is not float or x - x != 0.0:  # _json.plain's rules
            raise _json.NotPlain
        qc = quoted.get(c) or quoted.setdefault(c, q(c))
        k = int(x * 1000.0 + 0.5) if 0.0 <= x <= 1.0 else 0  # a confidence from from_arrays: 3 decimals in [0, 1]
        text = _MILLI[k] if k / 1000 == x and x > 0.0 else repr(x)  # -0.0 and 0.0: repr tells them apart
        faults.append(f'{{"nozzle":{nz},"class":{qc},"confidence":{text}}}')
    faults = ",".join(faults)
    if not all(type(f) is tuple for f in r.invalid):
        raise _json.NotPlain
    invalid = ",".join([f'{{"nozzle":{p(nz, int)},"reason":{q(p(why, str))}}}' for nz, why in r.invalid])
    return (f'{_LABELS_HEAD}"frame_id":{p(r.frame_id, int)},"stamp":{p(round(r.stamp, 6), float)!r},'
            f'"first_nozzle":{p(r.first_nozzle, int)},"n_nozzles":{p(r.n_nozzles, int)},'
            f'"model_id":{q(p(r.model_id, str))},"counts":{{{counts}}},"gate_cleared":{p(r.gate_cleared, int)},'
            f'"faults":[{faults}],"invalid":[{invalid}]}}')


def decode_labels(msg) -> LabelsReport:
    """Parse and validate a ``labels`` message; raise :class:`MessageError` otherwise."""
    s = LABELS_SCHEMA
    doc = _json.load(msg, s)
    frame_id = _json.field(doc, s, "frame_id", int, nonneg=True)
    stamp = _json.field(doc, s, "stamp", float, nonneg=True)
    first = _json.field(doc, s, "first_nozzle", int, nonneg=True)
    n = _json.field(doc, s, "n_nozzles", int, nonneg=True)
    model_id = _json.field(doc, s, "model_id", str)
    counts = _json.field(doc, s, "counts", dict)
    if not all(isinstance(v, int) and v >= 0 for v in counts.values()):
        raise MessageError(f"{s}: counts must be non-negative integers, got {counts}")
    if sum(counts.values()) != n:
        raise MessageError(f"{s}: counts sum to {sum(counts.values())}, n_nozzles is {n}")
    faults, invalid = [], []
    try:
        for f in _json.field(doc, s, "faults", list):
            nz, c, p = int(f["nozzle"]), str(f["class"]), float(f["confidence"])
            if not first <= nz < first + n:
                raise MessageError(f"{s}: fault nozzle {nz} outside {first}..{first + n - 1}")
            faults.append((nz, c, p))
        for f in _json.field(doc, s, "invalid", list):
            invalid.append((int(f["nozzle"]), str(f["reason"])))
    except (KeyError, TypeError, ValueError) as exc:
        if isinstance(exc, MessageError):
            raise
        raise MessageError(f"{s}: malformed faults/invalid entry ({exc!r})") from None
    if counts.get(INVALID_KEY, 0) != len(invalid):
        raise MessageError(f"{s}: counts['invalid'] = {counts.get(INVALID_KEY)}, {len(invalid)} listed")
    cleared = doc.get("gate_cleared", 0)
    if isinstance(cleared, bool) or not isinstance(cleared, int) or not 0 <= cleared <= n - len(invalid):
        raise MessageError(f"{s}: gate_cleared must be an integer in 0..{n - len(invalid)} (the valid rows), "
                           f"got {cleared!r}")
    return LabelsReport(frame_id, stamp, first, n, model_id, counts, tuple(faults), tuple(invalid), cleared)
