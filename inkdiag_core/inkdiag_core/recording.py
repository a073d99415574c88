"""Recordings of sensed traces for the offline verbs: load, validate, save.

A recording is an ``.npz`` file:

=================  ==========================  ===========================================
key                shape, type                 meaning
=================  ==========================  ===========================================
``traces``         (n, n_samples) float32      sensed traces, V (required; float64 is taken too)
``sample_rate_hz`` scalar float                their sample rate, Hz (required)
``nozzle``         (n,) int                    nozzle id of each row (default 0..n-1)
``frame_id``       (n,) int                    measurement (frame) of each row (default 0)
``stamp``          (n,) float                  time of each row's frame, s (default NaN)
``label``          (n,) str                    class of each row (a FaultClass value, any case, padding ignored), if known;
                                               ``invalid`` or ``unknown`` (from ``inkdiag label``): none
=================  ==========================  ===========================================

Rows are independent: a row with a non-finite or out-of-range sample is
loaded as it is and becomes an ``invalid`` row where it is labelled, it never
costs the other rows. What makes the whole file unusable (no ``traces``, a
sample rate that is not a positive number, traces that are not floating-point
volts, arrays of another length, an unknown class name) is a :class:`RecordingError` naming the file and the key.
"""

from __future__ import annotations

import csv
import dataclasses
import math
import numbers
import re
import zipfile
from pathlib import Path

import numpy as np

from .checks import InputError
from .faults import FaultClass
from .openset import UNKNOWN

__all__ = ["LabelTable", "Recording", "RecordingError", "labels_from_csv", "load_recording", "read_labels_csv",
           "save_recording"]

#: Labels that name no class: what ``inkdiag label`` writes for a row it could not judge and for one
#: unlike every class. A recording may carry them (a label column from ``inkdiag label``); training
#: leaves their rows out.
NOT_CLASSES = ("invalid", UNKNOWN)
#: Every value a recording's ``label`` may hold.
LABEL_VALUES = frozenset(c.value for c in FaultClass) | frozenset(NOT_CLASSES)


def _as_float32(t):
    """``t`` as C-contiguous float32; a finite sample beyond float32's range (a float64 1e300) becomes the
    largest float32 of its sign, not inf, so that screening calls its row out of range, not non-finite."""
    if t.dtype == np.float32:
        return np.ascontiguousarray(t)
    with np.errstate(over="ignore"):
        out = np.ascontiguousarray(t, dtype=np.float32)
    big = np.isinf(out)
    if big.any():
        big &= np.isfinite(t)
        out[big] = np.copysign(np.finfo(np.float32).max, t[big])
    return out


class RecordingError(InputError):
    """A recording that cannot be read (a ``ValueError``)."""


@dataclasses.dataclass(frozen=True, eq=False)
class Recording:
    """Traces and their per-row identity, as loaded from a recording.

    Attributes
    ----------
    traces : ndarray, shape (n, n_samples), float32
        Sensed traces, V.
    sample_rate_hz : float
        Hz.
    nozzle, frame_id : ndarray, shape (n,), int64
        Nozzle and frame of each row.
    stamp : ndarray, shape (n,), float64
        Time of each row's frame, s (NaN where the recording has none).
    label : ndarray of str, shape (n,), or None
        Known class of each row (FaultClass values), if the recording has labels.
    source : str
        Where it was read from.
    """

    traces: np.ndarray
    sample_rate_hz: float
    nozzle: np.ndarray
    frame_id: np.ndarray
    stamp: np.ndarray
    label: np.ndarray | None = None
    source: str = "recording"

    @property
    def n_rows(self) -> int:
        """Number of traces."""
        return int(self.traces.shape[0])

    @property
    def n_samples(self) -> int:
        """Samples per trace."""
        return int(self.traces.shape[1])

    @classmethod
    def from_arrays(cls, traces, sample_rate_hz, *, nozzle=None, frame_id=None, stamp=None, label=None,
                    source: str = "recording") -> "Recording":
        """Validate arrays into a recording (what :func:`load_recording` does after reading).

        Raises
        ------
        RecordingError
            Naming ``source`` and the key that is wrong.
        """
        t = np.asarray(traces)
        if t.ndim != 2 or t.shape[0] < 1 or t.shape[1] < 2:
            raise RecordingError(f"{source}: traces must be a 2-D array (n, n_samples) with at least one row of at "
                                 f"least two samples, got shape {t.shape}")
        if t.dtype.kind != "f":
            raise RecordingError(f"{source}: traces must be floating-point volts (float32), got dtype {t.dtype}"
                                 + (": convert ADC counts or millivolts to volts first" if t.dtype.kind in "iu"
                                    else ""))
        t = _as_float32(t)
        fs = sample_rate_hz
        if isinstance(fs, np.ndarray):
            if fs.size != 1:
                raise RecordingError(f"{source}: sample_rate_hz must be a scalar, got shape {fs.shape}")
            fs = fs.reshape(()).item()
        if isinstance(fs, bool) or not isinstance(fs, numbers.Real) or not math.isfinite(fs) or fs <= 0:
            raise RecordingError(f"{source}: sample_rate_hz must be a positive number of Hz, got {fs!r}")
        n = t.shape[0]

        def per_trace(name, a):
            if a.shape == (t.shape[1],) and t.shape[1] != n:
                raise RecordingError(f"{source}: {name} has {t.shape[1]} entries, one per column of traces {t.shape}: "
                                     "are the traces transposed? (one row per trace: shape (n, n_samples))")
            if a.shape != (n,):
                raise RecordingError(f"{source}: {name} must have one entry per trace, shape ({n},), got {a.shape}")

        def column(name, value, kind, default):
            if value is None:
                return default
            a = np.asarray(value)
            per_trace(name, a)
            if kind == "int":
                if a.dtype.kind not in "iu" and not (a.dtype.kind == "f" and np.all(np.isfinite(a))
                                                     and np.all(a == np.round(a))):
                    raise RecordingError(f"{source}: {name} must be integers, got dtype {a.dtype}")
                if a.size and (a.min() < 0 or a.max() >= 2**63):
                    raise RecordingError(f"{source}: {name} must be integers from 0 to 2**63 - 1, got "
                                         f"{a.min() if a.min() < 0 else a.max()}")
                return a.astype(np.int64)
            if a.dtype.kind not in "fiu":
                raise RecordingError(f"{source}: {name} must be numbers (s), got dtype {a.dtype}")
            return a.astype(np.float64)

        nozzle = column("nozzle", nozzle, "int", np.arange(n, dtype=np.int64))
        frame = column("frame_id", frame_id, "int", np.zeros(n, dtype=np.int64))
        st = column("stamp", stamp, "float", np.full(n, np.nan))
        lab = None
        if label is not None:
            lab = np.asarray(label)
            per_trace("label", lab)
            lab = np.array([(v.decode("utf-8", "replace") if isinstance(v, bytes) else str(v)).strip().lower()
                            for v in lab.tolist()], dtype=object)  # bytes (an 'S' array, as h5py or MATLAB write)
            # are UTF-8 text; class names are lower case and padding is no part of them (a MATLAB char
            # matrix pads its rows with spaces): read as a labels CSV's cells are
            bad = sorted(set(lab.tolist()) - LABEL_VALUES)
            if bad:
                raise RecordingError(f"{source}: label {', '.join(map(repr, bad[:5]))}{', ...' if len(bad) > 5 else ''} "
                                     f"{'is not a class' if len(bad) == 1 else 'are not classes'} (expected one of "
                                     f"{', '.join(c.value for c in FaultClass)}, or {', '.join(NOT_CLASSES)})")
        return cls(t, float(fs), nozzle, frame, st, lab, source)


def refuse_an_unclosed_bag(path) -> None:
    """Raise :class:`RecordingError` if the directory ``path`` holds a bag's storage files but no
    metadata.yaml (its recorder stopped before it closed the bag); else nothing."""
    path = Path(path)
    if path.is_dir() and (any(path.glob("*.mcap")) or any(path.glob("*.db3"))):
        raise RecordingError(f"{path}: a bag directory without its metadata.yaml (a recorder writes it when it "
                             "closes the bag: one still recording, or stopped before it closed the bag, has none): "
                             "not readable as a rosbag2 bag")


def load_recording(path) -> Recording:
    """Read a recording (``.npz``, see the module docstring).

    Parameters
    ----------
    path : str or os.PathLike

    Raises
    ------
    RecordingError
        A missing or unreadable file, not an npz archive, no ``traces`` or
        ``sample_rate_hz``, or a key of the wrong shape or type.
    """
    path = Path(path)
    src = str(path)
    if not path.exists():
        raise RecordingError(f"{src}: no such recording")
    if path.is_dir():
        if (path / "metadata.yaml").is_file():  # the core cannot decode the wire's trace frames (msg_defs does)
            raise RecordingError(f"{src}: is a rosbag2 bag; read it with inkdiag_ros.bags.load_recording "
                                 "(the inkdiag verbs do)")
        refuse_an_unclosed_bag(path)
        raise RecordingError(f"{src}: is a directory; a recording is an .npz file or a rosbag2 bag directory")
    if not path.is_file():  # a pipe or a device: np.load needs to seek, and the check below reads
        raise RecordingError(f"{src}: not a regular file; a recording is an .npz file or a rosbag2 bag directory")
    try:
        with open(path, "rb") as f:
            magic = f.read(6)
        if magic.startswith(b"\x89MCAP") or (magic.startswith(b"SQLite") and path.suffix == ".db3"):
            raise RecordingError(f"{src}: a rosbag2 storage file: give the bag's directory ({path.parent}, with its "
                                 "metadata.yaml), not the file inside it")
        if not magic.startswith((b"PK\x03\x04", b"PK\x05\x06", b"\x93NUMPY")):  # a zip (.npz) or an .npy
            raise RecordingError(f"{src}: not an .npz archive (a zip of numpy arrays): "
                                 + (f"it starts with {magic!r}" if magic else "an empty file"))
        z = np.load(path, allow_pickle=False)
        if not isinstance(z, np.lib.npyio.NpzFile):
            raise RecordingError(f"{src}: not an .npz archive (a single .npy array?)")
        with z:
            keys = set(z.files)
            for req in ("traces", "sample_rate_hz"):
                if req not in keys:
                    raise RecordingError(f"{src}: no {req!r} in the recording (it has {', '.join(sorted(keys)) or 'nothing'})")
            data = {k: z[k] for k in ("traces", "sample_rate_hz", "nozzle", "frame_id", "stamp", "label") if k in keys}
        for k, v in data.items():  # a member that is not .npy data: NpzFile gives its raw bytes
            if not isinstance(v, np.ndarray):
                raise RecordingError(f"{src}: {k!r} is not a numpy array in the archive (not .npy data)")
    except RecordingError:
        raise
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise RecordingError(f"{src}: cannot read the recording: {exc}") from None
    return Recording.from_arrays(data.pop("traces"), data.pop("sample_rate_hz"), source=src, **data)


def save_recording(path, recording: Recording) -> Path:
    """Write ``recording`` as an ``.npz`` that :func:`load_recording` reads back; returns the path."""
    path = Path(path)
    arrays = {"traces": recording.traces.astype(np.float32), "sample_rate_hz": np.float64(recording.sample_rate_hz),
              "nozzle": recording.nozzle, "frame_id": recording.frame_id, "stamp": recording.stamp}
    if recording.label is not None:
        arrays["label"] = np.asarray(recording.label, dtype=str)
    with open(path, "wb") as f:
        np.savez(f, **arrays)
    return path



@dataclasses.dataclass(frozen=True, eq=False)
class LabelTable:
    """A labels CSV, read and checked on its own (:func:`read_labels_csv`), before any recording is read.

    Attributes
    ----------
    source : str
        The file.
    key : str
        ``"row"``, ``"nozzle"`` or ``"nozzle+frame_id"``: what names a row.
    row, nozzle, frame_id : ndarray of int64, shape (m,), or None
        Each line's values of the columns it has (None: no such column; the int64 minimum: a
        cell left empty beside ``row``).
    classes : ndarray of object, shape (m,)
        Each line's class.
    lines : ndarray of int64, shape (m,)
        Each entry's line in the file (the header is line 1).
    columns : tuple of str
        The header's column names (lower case).
    """

    source: str
    key: str
    row: np.ndarray | None
    nozzle: np.ndarray | None
    frame_id: np.ndarray | None
    classes: np.ndarray
    lines: np.ndarray
    columns: tuple = ()

    def coverage_warning(self, n_named: int, n_rows: int, recording) -> str | None:
        """What to say when this CSV looks like ``inkdiag label``'s (rows named by ``row``, with its
        ``confidence`` and ``reason`` columns), which names every row of the recording it labelled, but names
        ``n_named`` of the ``n_rows`` rows of ``recording``: the labels of another recording? None otherwise."""
        if self.key != "row" or not {"confidence", "reason"} <= set(self.columns) or not 0 < n_named < n_rows:
            return None
        return (f"{self.source} looks like `inkdiag label`'s CSV, which names every row of the recording it "
                f"labelled, but it names {n_named} of the {n_rows} rows of {recording} (rows "
                f"{int(self.row.min())}..{int(self.row.max())}): the labels of another recording?")


_INTEGER = re.compile(r"[+-]?[0-9]+")
_EMPTY = np.iinfo(np.int64).min  # an empty nozzle or frame_id cell beside a row


def read_labels_csv(path) -> LabelTable:
    """Read and check a labels CSV (see :func:`labels_from_csv` for its columns).

    Header names are matched without case or surrounding blanks (a UTF-8 byte-order mark, as
    spreadsheets write, is dropped); lines whose cells are all blank are skipped; other columns
    are ignored.

    Raises
    ------
    RecordingError
        A missing or unreadable file, a header without ``class`` or without ``row`` and
        ``nozzle``, no line after the header, a column named twice, a class that is not one, a value that is not an
        integer, or a row (nozzle, nozzle in a frame) named twice; naming the file and line.
    """
    path = Path(path)
    src = str(path)
    if not path.exists():
        raise RecordingError(f"{src}: no such labels file")
    if path.is_dir():
        raise RecordingError(f"{src}: is a directory, not a labels CSV")
    ints = {"row": [], "nozzle": [], "frame_id": []}
    classes, lines = [], []
    line = 0  # the last line read whole: a csv error is in the record after it
    try:
        with open(path, "rb") as f:
            if f.read(2) in (b"\xff\xfe", b"\xfe\xff"):
                raise RecordingError(f"{src}: UTF-16 text (a spreadsheet's 'Unicode text' export): save the labels "
                                     "as a UTF-8 CSV")
        with open(path, newline="", encoding="utf-8-sig") as f:
            reader = csv.reader(f, strict=True)  # an unclosed quote is an error, not the rest of the file as one cell
            header = next(reader, None)
            line = reader.line_num
            cols = [c.strip().lower() for c in (header or [])]
            twice = sorted({c for c in cols if c and cols.count(c) > 1})
            if twice:
                raise RecordingError(f"{src}: the header names {', '.join(map(repr, twice))} twice")
            if "class" not in cols or not ({"row", "nozzle"} & set(cols)):
                raise RecordingError(f"{src}: a labels CSV needs a header with a 'class' column and a 'row' or "
                                     f"'nozzle' column (as `inkdiag label` writes), got {header or 'no header'}")
            at = {c: cols.index(c) for c in ("class", *ints) if c in cols}
            for cells in reader:
                line = reader.line_num
                if not any(c.strip() for c in cells):
                    continue
                if any(c.strip() for c in cells[len(cols):]):  # empty trailing cells (a spreadsheet's) are fine
                    raise RecordingError(f"{src}:{line}: {len(cells)} fields, the header has {len(cols)}: "
                                         f"{cells[len(cols):]!r} beyond its columns")
                get = {c: (cells[j].strip() if j < len(cells) else "") for c, j in at.items()}
                cls = get["class"].lower()  # class names are lower case; a spreadsheet may have capitalised them
                if cls not in LABEL_VALUES:
                    raise RecordingError(f"{src}:{line}: class {get['class']!r} is not a class (expected one of "
                                         f"{', '.join(c.value for c in FaultClass)}, or {', '.join(NOT_CLASSES)})")
                for name, out in ints.items():
                    if name not in at:
                        continue
                    v = get[name]
                    if v == "" and name != "row" and "row" in at:
                        out.append(_EMPTY)  # a cell left empty beside the row that names the line: not checked
                        continue
                    if not _INTEGER.fullmatch(v):
                        raise RecordingError(f"{src}:{line}: {name} {v!r} is not an integer")
                    if not -2**62 <= (iv := int(v)) <= 2**62:  # no row, nozzle or frame: an int64 would overflow
                        raise RecordingError(f"{src}:{line}: {name} {v} is too large to be one")
                    out.append(iv)
                classes.append(cls)
                lines.append(line)
    except csv.Error as exc:  # e.g. a quote never closed: where its record began
        raise RecordingError(f"{src}:{line + 1}: cannot read the labels CSV: {exc}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise RecordingError(f"{src}: cannot read the labels CSV: {exc}") from None
    if not classes:  # else "no row is usable" once the recording is read, blaming its rows
        raise RecordingError(f"{src}: a header and no labelled line: it names no row")
    key = "row" if "row" in at else ("nozzle+frame_id" if "frame_id" in at else "nozzle")
    arrays = {name: (np.asarray(v, dtype=np.int64) if name in at else None) for name, v in ints.items()}
    table = LabelTable(src, key, arrays["row"], arrays["nozzle"], arrays["frame_id"],
                       np.asarray(classes, dtype=object), np.asarray(lines, dtype=np.int64), tuple(cols))
    keys = _table_keys(table)
    if keys.size:
        order = np.lexsort(keys.T[::-1])
        k = keys[order]
        dup = np.flatnonzero((k[1:] == k[:-1]).all(axis=1))
        if dup.size:
            a, b = np.sort(order[dup[0]:dup[0] + 2])
            what = {"row": "row {}", "nozzle": "nozzle {}", "nozzle+frame_id": "nozzle {} in frame {}"}[key]
            raise RecordingError(f"{src}:{table.lines[b]}: {what.format(*keys[b])} is named twice (first on line "
                                 f"{table.lines[a]})")
    return table


def _table_keys(table: LabelTable) -> np.ndarray:
    """(m, 1) or (m, 2) int64: each entry's key."""
    if table.key == "row":
        return table.row[:, None]
    if table.key == "nozzle":
        return table.nozzle[:, None]
    return np.column_stack([table.nozzle, table.frame_id])


def labels_from_csv(recording: Recording, labels) -> tuple:
    """The recording with each row's class read from a CSV file (hand labels, or ``inkdiag label``'s corrected).

    The CSV has a header line and a ``class`` column (a FaultClass value, or ``invalid`` /
    ``unknown``: no class) and names the rows by one of:

    - ``row``: the recording's row index (0-based, as ``inkdiag label`` numbers them); a
      ``nozzle`` or ``frame_id`` column beside it must agree with the recording's (a CSV of
      another recording is refused);
    - ``nozzle`` (no ``row``): every row of that nozzle, or with a ``frame_id`` column every
      row of that nozzle in that frame (an inspection's "nozzle 17 is blocked").

    A row may be named once; rows the CSV does not name are labelled ``unknown`` (training
    leaves them out). Other columns are ignored.

    Parameters
    ----------
    recording : Recording
    labels : str, os.PathLike or LabelTable
        The CSV file, or the table :func:`read_labels_csv` read from it.

    Returns
    -------
    recording : Recording
        A copy with ``label`` set, shape (n,), the CSV's classes.
    n_named : int
        Rows the CSV named.

    Raises
    ------
    RecordingError
        As :func:`read_labels_csv`; and a row out of range, not the CSV's nozzle or frame, or
        a nozzle (in a frame) the recording lacks, naming the file and its line.
    """
    t = labels if isinstance(labels, LabelTable) else read_labels_csv(labels)
    src = t.source
    n = recording.n_rows
    label = np.full(n, UNKNOWN, dtype=object)
    named = np.zeros(n, dtype=bool)
    if t.key == "row":
        out = np.flatnonzero((t.row < 0) | (t.row >= n))
        if out.size:
            j = out[0]
            raise RecordingError(f"{src}:{t.lines[j]}: row {t.row[j]} is not a row of {recording.source} "
                                 f"(0..{n - 1})")
        for name, have in (("nozzle", recording.nozzle), ("frame_id", recording.frame_id)):
            col = getattr(t, name)
            if col is None:
                continue
            bad = np.flatnonzero((col != _EMPTY) & (col != have[t.row]))
            if bad.size:
                j = bad[0]
                raise RecordingError(f"{src}:{t.lines[j]}: row {t.row[j]} is {name} {have[t.row[j]]} in "
                                     f"{recording.source}, the CSV says {col[j]}: labels of another recording?")
        label[t.row] = t.classes
        named[t.row] = True
    else:
        have = (recording.nozzle[:, None] if t.key == "nozzle"
                else np.column_stack([recording.nozzle, recording.frame_id]))
        keys = _table_keys(t)
        # each recording row's entry in the table (its keys are distinct), through the distinct keys of both
        _, inv = np.unique(np.concatenate([keys, have]), axis=0, return_inverse=True)
        inv = inv.reshape(-1)
        lookup = np.full(int(inv.max()) + 1, -1, dtype=np.int64)
        lookup[inv[:len(keys)]] = np.arange(len(keys))
        entry_of_row = lookup[inv[len(keys):]]
        hit = entry_of_row >= 0
        entry = entry_of_row[hit]
        label[hit] = t.classes[entry]
        named[hit] = True
        used = np.zeros(len(keys), dtype=bool)
        used[entry] = True
        if not used.all():
            j = int(np.flatnonzero(~used)[0])
            what = (f"nozzle {keys[j, 0]}" if t.key == "nozzle" else f"nozzle {keys[j, 0]} in frame {keys[j, 1]}")
            raise RecordingError(f"{src}:{t.lines[j]}: {recording.source} has no row of {what}")
    return dataclasses.replace(recording, label=label), int(named.sum())

