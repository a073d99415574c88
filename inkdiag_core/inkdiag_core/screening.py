"""Screening of trace rows before classification: which rows can be judged at all.

A printer controller's frame can hold rows that carry no information about the
nozzle: a dead sensing channel (flat), an overdriven one (clipped at the ADC
rails), or a transfer fault (NaN / Inf). Such rows are labelled *invalid* with
a reason instead of being classified; the rest of the frame is unaffected.
"""

from __future__ import annotations

import numpy as np

__all__ = ["INVALID_REASONS", "screen_traces"]

#: Reason codes, in the order of precedence used when several apply.
INVALID_REASONS = ("non_finite", "flat", "clipped")


def screen_traces(traces, *, flat_tol: float = 1e-6, clip_run: int = 5):
    """Find the rows of a frame that cannot be classified, and why.

    Parameters
    ----------
    traces : array_like, shape (n, n_samples)
        Sensor samples, V.
    flat_tol : float
        A row whose peak-to-peak range is at most this (V) is *flat*.
    clip_run : int
        A row with ``clip_run`` or more consecutive samples exactly at its
        maximum (or minimum) value, sitting on a plateau, is *clipped*: an ADC
        saturates there, a damped oscillation does not. 5 samples (0.5 us at
        10 MHz): with 3, 12-bit quantisation flagged 0.2 % of simulated
        healthy and faulty traces whose flat peak repeats one ADC code.

    Returns
    -------
    valid : ndarray of bool, shape (n,)
    reasons : ndarray of str (object), shape (n,)
        ``""`` for valid rows, else one of :data:`INVALID_REASONS`.
    """
    x = np.asarray(traces)
    if x.ndim != 2:
        raise ValueError(f"traces must be 2-D (n, n_samples), got shape {x.shape}")
    if clip_run < 2:
        raise ValueError(f"clip_run must be >= 2, got {clip_run}")
    n = x.shape[0]
    reasons = np.full(n, "", dtype=object)
    if n == 0 or x.shape[1] == 0:
        return np.ones(n, bool), reasons
    # One max and one min pass find the non-finite rows too: NaN propagates through both,
    # +Inf is a row's max and -Inf its min.
    hi = x.max(axis=1)
    lo = x.min(axis=1)
    finite = np.isfinite(hi) & np.isfinite(lo)
    with np.errstate(invalid="ignore"):  # inf - inf in non-finite rows
        flat = finite & ((hi - lo) <= flat_tol)
    if not finite.all():
        hi, lo = np.where(finite, hi, np.nan), np.where(finite, lo, np.nan)  # matches no sample
    at_hi, at_lo = x == hi[:, None], x == lo[:, None]
    # Only rows with clip_run samples at an extreme can hold such a run (few do); bytes
    # summed into uint16 count them fastest where a row is too short to overflow it.
    count = np.uint16 if x.shape[1] < 2**16 else np.intp
    cand = np.flatnonzero((np.add.reduce(at_hi.view(np.uint8), axis=1, dtype=count) >= clip_run)
                          | (np.add.reduce(at_lo.view(np.uint8), axis=1, dtype=count) >= clip_run))
    clipped = np.zeros(n, bool)
    clipped[cand] = _has_run(at_hi[cand], clip_run) | _has_run(at_lo[cand], clip_run)
    reasons[clipped] = "clipped"
    reasons[flat] = "flat"
    reasons[~finite] = "non_finite"
    return reasons == "", reasons


def _has_run(mask: np.ndarray, run: int) -> np.ndarray:
    """Rows of a boolean (n, m) mask holding ``run`` consecutive True values."""
    if mask.shape[1] < run:
        return np.zeros(mask.shape[0], bool)
    acc = mask[:, : mask.shape[1] - run + 1].copy()
    for k in range(1, run):  # a few whole-array ANDs, not a loop over rows
        acc &= mask[:, k : mask.shape[1] - run + 1 + k]
    return acc.any(axis=1)
