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
