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
    finite = np.isfinite(x).all(axis=1)
    xf = x if finite.all() else np.where(finite[:, None], x, 0.0)
    hi = xf.max(axis=1, keepdims=True)
    lo = xf.min(axis=1, keepdims=True)
    flat = (hi - lo)[:, 0] <= flat_tol
    at_hi, at_lo = xf == hi, xf == lo
    # Only rows with clip_run samples at an extreme can hold such a run (few do).
    cand = np.flatnonzero((at_hi.sum(axis=1) >= clip_run) | (at_lo.sum(axis=1) >= clip_run))
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
