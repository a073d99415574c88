"""Label a whole frame of traces with a fitted FDI pipeline, invalid rows screened out."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .fdi import classify
from .screening import screen_traces

__all__ = ["FrameLabels", "label_traces"]


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
        labels, conf, _ = classify(pipeline, x[valid], fd_threshold=fd_threshold)
        classes[valid] = labels.astype(object)
        confidence[valid] = conf
    return FrameLabels(classes, confidence, valid, reasons)
