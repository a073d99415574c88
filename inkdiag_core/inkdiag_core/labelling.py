"""Label a whole frame of traces with a fitted FDI pipeline, invalid rows screened out."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .fdi import classify
from .screening import screen_traces

__all__ = ["FrameLabels", "label_frames", "label_traces"]


@dataclass(frozen=True)
class FrameLabels:
    """Per-row labels of one frame (n = rows).

    classes : ndarray of str (object), (n,) -- class value, ``""`` for invalid rows
    confidence : ndarray of float, (n,) -- probability of that class, NaN for invalid rows
    valid : ndarray of bool, (n,)
    reasons : ndarray of str (object), (n,) -- why a row is invalid, ``""`` otherwise
    """

    classes: np.ndarray
    confidence: np.ndarray
    valid: np.ndarray
    reasons: np.ndarray


def label_traces(pipeline, traces, *, fd_threshold: float = 0.5) -> FrameLabels:
    """Screen a frame (:func:`screen_traces`) and classify its valid rows in one batch.

    Parameters
    ----------
    pipeline : fitted scikit-learn classifier with ``predict_proba`` and ``classes_``
        (class values as strings), taking raw traces (n, n_samples).
    traces : array_like, shape (n, n_samples)
        Sensor samples, V.
    fd_threshold : float
        Fault-detection threshold on P(faulty) (:func:`inkdiag_core.fdi.classify`;
        the default model stores its false-negative-averse one in its manifest).
    """
    x = np.asarray(traces)
    valid, reasons = screen_traces(x)
    n = x.shape[0]
    classes = np.full(n, "", dtype=object)
    confidence = np.full(n, np.nan)
    if valid.any():
        rows = x if valid.all() else x[valid]  # no copy of a frame that is all valid
        labels, conf, _ = classify(pipeline, rows, fd_threshold=fd_threshold)
        classes[valid] = labels.astype(object)
        confidence[valid] = conf
    return FrameLabels(classes, confidence, valid, reasons)


def label_frames(pipeline, frames, *, fd_threshold: float = 0.5) -> list:
    """Label several frames in one batch: one screening, feature and classifier pass.

    A classifier call has a fixed cost (feature pipeline set-up, one call per
    tree), so frames that arrived together are labelled together; each row's
    result is the same as :func:`label_traces` gives it alone (every feature
    and every tree is per row).

    Parameters
    ----------
    pipeline : fitted scikit-learn classifier, as for :func:`label_traces`
    frames : sequence of array_like, each of shape (n_i, n_samples)
        The frames' traces, V; every frame must have the same ``n_samples``.
    fd_threshold : float
        As for :func:`label_traces`.

    Returns
    -------
    list of FrameLabels
        One per frame, in order, with ``n_i`` rows each.
    """
    arrays = [np.asarray(f) for f in frames]
    if not arrays:
        return []
    bad = [i for i, a in enumerate(arrays) if a.ndim != 2]
    if bad:
        raise ValueError(f"each frame must be 2-D (n_traces, n_samples); frame {bad[0]} has "
                         f"shape {arrays[bad[0]].shape}")
    widths = {a.shape[1] for a in arrays}
    if len(widths) != 1:
        raise ValueError(f"frames labelled together must have one sample count, got {sorted(widths)}")
    rows = label_traces(pipeline, np.concatenate(arrays) if len(arrays) > 1 else arrays[0],
                        fd_threshold=fd_threshold)
    cuts = np.cumsum([a.shape[0] for a in arrays])[:-1]
    parts = zip(*(np.split(col, cuts) for col in (rows.classes, rows.confidence, rows.valid, rows.reasons)))
    return [FrameLabels(*p) for p in parts]
