"""The ``inkdiag`` subcommands, one module each (see :mod:`inkdiag_ros.cli`), and what several share."""

from __future__ import annotations

import contextlib
import sys

#: What a summary line adds where rows had no baseline for their nozzle id (label, estimate).
NO_BASELINE_HINT = ("no baseline for that nozzle id: check the recording's nozzle ids, its 'nozzle' column; "
                    "without one its rows are numbered 0..n-1")


@contextlib.contextmanager
def open_csv_out(path: str):
    """The text stream a verb writes its CSV to: standard output for ``-``, else the file (closed after)."""
    if path == "-":  # (cli refuses it where stdout is closed)
        yield sys.stdout
        sys.stdout.flush()
        return
    with open(path, "w", newline="", encoding="utf-8") as f:
        yield f


def summary_stream(path: str):
    """Where a verb prints its summary line: standard error when its CSV goes to standard output."""
    return sys.stderr if path == "-" else sys.stdout


def repeated_pairs(nozzle, frame_id, stamp=None) -> int:
    """Rows whose nozzle, frame_id and stamp (NaN stamps alike) an earlier row already has: a frame holds one
    trace per nozzle, so these are a nozzle column gone wrong (e.g. all zeros), rows given twice, or frames
    told apart by neither a frame_id nor a stamp column.

    Parameters
    ----------
    nozzle, frame_id : array_like of int, shape (n,)
    stamp : array_like of float, shape (n,), optional
        s; None: not compared.
    """
    import numpy as np

    cols = [np.asarray(nozzle, dtype=np.int64), np.asarray(frame_id, dtype=np.int64)]
    if stamp is not None:
        st = np.asarray(stamp, dtype=np.float64)
        cols.append(np.where(np.isnan(st), np.nan, st + 0.0).view(np.int64))  # one NaN; -0.0 as 0.0
    keys = np.stack(cols, axis=1)
    return int(keys.shape[0] - (np.unique(keys, axis=0).shape[0] if keys.size else 0))


def repeated_pairs_warning(verb: str, n_repeated: int, what: str) -> str:
    """The warning line of a recording with :func:`repeated_pairs` rows (``what``: how the verb took them)."""
    return (f"inkdiag {verb}: warning: {n_repeated} row(s) repeat the nozzle, frame_id and stamp of an earlier row; "
            f"{what}, but a frame holds one trace per nozzle: is the recording's nozzle column right, and does it "
            "tell its frames apart (frame_id or stamp)?")


def check_max_abs_v(value) -> None:
    """ValueError unless ``--max-abs-v`` is left out (None: the head's bound) or a finite number > 0 V (every verb
    that takes it: ``inf`` had screened nothing out in label and been refused by baseline, helper-137)."""
    if value is not None and not 0 < value < float("inf"):
        raise ValueError(f"--max-abs-v must be a finite number > 0 V, got {value!r}")


def units_warning(verb: str, n_out_of_range: int, n_rows: int, max_abs_v: float, given: bool = False) -> str:
    """The warning line when at least half the rows have a sample no sensor of the head can produce (a
    recording in other units, not a head whose sensor broke), else "". ``given``: the bound is the user's
    ``--max-abs-v``, which may be what is wrong."""
    if not (n_rows and n_out_of_range >= n_rows / 2):
        return ""
    if given:
        return (f"inkdiag {verb}: warning: {n_out_of_range} of {n_rows} rows have a sample beyond --max-abs-v "
                f"{max_abs_v:g} V: is that what the sensor can produce, and are the traces in volts?")
    return (f"inkdiag {verb}: warning: {n_out_of_range} of {n_rows} rows have a sample beyond {max_abs_v:g} V, more "
            "than the head's sensor can produce: are the traces in volts (not millivolts or ADC counts)?")


#: What each screening reason of a row most often means, for :func:`invalid_warning`.
_INVALID_HINTS = {"non_finite": "NaN or infinite samples: a recorder's gaps or a float32 overflow",
                  "flat": "constant traces: a channel not wired or a sensor stuck",
                  "clipped": "traces held at the ADC's limits: a sense gain too high",
                  "out_of_range": "samples beyond what the head's sensor can produce",
                  "non_finite_features": "features that overflow"}


#: :func:`invalid_warning` speaks from this many invalid rows (one flat row of two picked is a channel, not a head),
#: or when every row of 3 or more is invalid.
MIN_INVALID_WARNED = 8


def invalid_warning(verb: str, per_reason, n_rows: int) -> str:
    """The warning line when at least half the rows are invalid (screening's reasons in ``per_reason``, a
    mapping reason -> rows; other keys are ignored), naming the reasons, else ""."""
    counts = sorted(((k, r) for r, k in per_reason.items() if r in _INVALID_HINTS and k),
                    key=lambda kr: (-kr[0], kr[1]))  # most first, then by name
    n_bad = sum(k for k, _ in counts)
    if not ((n_bad >= MIN_INVALID_WARNED and n_bad >= n_rows / 2) or n_bad == n_rows >= 3):  # or all of a few
        return ""
    reasons = ", ".join(f"{k} {r}" for k, r in counts)
    most = ("" if len(counts) > 1 and counts[1][0] == counts[0][0]  # a tie: no one reason is most
            else f"; most are {_INVALID_HINTS[counts[0][1]]}")
    return (f"inkdiag {verb}: warning: {n_bad} of {n_rows} rows are invalid ({reasons}){most}: is this the "
            "recording of a working head?")

