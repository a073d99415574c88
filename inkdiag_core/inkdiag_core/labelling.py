"""Label a whole frame of traces with a fitted FDI pipeline, invalid rows screened out."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .baselines import NozzleBaselines, with_baseline
from .fdi import classify_finite
from .screening import screen_traces

__all__ = ["BaselineModel", "FrameLabels", "label_frames", "label_frames_isolated", "label_traces"]


@dataclass(frozen=True)
class BaselineModel:
    """A ``"kpi_y+baseline"`` pipeline with the head's recorded baselines.

    pipeline : fitted pipeline taking ``[trace, baseline KPIs]`` rows (:func:`with_baseline`)
    baselines : :class:`inkdiag_core.NozzleBaselines` of the head's nozzles
    fd_threshold : float -- its fault-detection threshold (in its manifest)
    """

    pipeline: object
    baselines: NozzleBaselines
    fd_threshold: float = 0.5


@dataclass(frozen=True)
class FrameLabels:
    """Per-row labels of one frame (n = rows).

    classes : ndarray of str (object), (n,) -- class value, ``""`` for invalid rows
    confidence : ndarray of float, (n,) -- probability of that class, NaN for invalid rows
    valid : ndarray of bool, (n,)
    reasons : ndarray of str (object), (n,) -- why a row is invalid, ``""`` otherwise
    baseline : ndarray of bool, (n,) -- classified against its nozzle's baseline
    gate_cleared : ndarray of bool, (n,) or None -- cleared as healthy by the healthy
        gate (:class:`inkdiag_core.HealthyGate`) without the full model; None: no gate ran
    class_codes : ndarray of uint8, (n,) or None -- ``classes`` as indices into ``class_names``
        (``class_names[class_codes[i]] == classes[i]``): what a report of the frame is built from
        without reading a string per row (:class:`inkdiag_core.FrameLabeller` gives them); None: not given
    class_names : tuple of str or None -- the class names ``class_codes`` index, each once
    """

    classes: np.ndarray
    confidence: np.ndarray
    valid: np.ndarray
    reasons: np.ndarray
    baseline: np.ndarray | None = None
    gate_cleared: np.ndarray | None = None
    class_codes: np.ndarray | None = None
    class_names: tuple | None = None


def label_traces(pipeline, traces, *, fd_threshold: float = 0.5, nozzle_ids=None,
                 baseline: BaselineModel | None = None, max_abs_v: float | None = None) -> FrameLabels:
    """Screen a frame (:func:`screen_traces`) and classify its valid rows in one batch.

    With ``baseline`` and ``nozzle_ids``, the valid rows whose nozzle has a recorded
    baseline are classified by ``baseline.pipeline`` against it, the others by
    ``pipeline``. A row that passes screening but whose features come out NaN or
    Inf is invalid (``"non_finite_features"``); the other rows are labelled.

    Parameters
    ----------
    pipeline : fitted scikit-learn classifier with ``predict_proba`` and ``classes_``
        (class values as strings), taking raw traces (n, n_samples).
    traces : array_like, shape (n, n_samples)
        Sensor samples, V.
    fd_threshold : float
        Fault-detection threshold on P(faulty) (:func:`inkdiag_core.fdi.classify`;
        the default model stores its false-negative-averse one in its manifest).
    nozzle_ids : array_like of int, shape (n,), optional
        Each row's nozzle (needed with ``baseline``).
    baseline : BaselineModel, optional
    max_abs_v : float, optional
        Largest sample magnitude a sensor can produce, V: rows beyond it are
        invalid, ``"out_of_range"`` (:func:`screen_traces`). None: no such check.
    """
    x = np.asarray(traces)
    valid, reasons = screen_traces(x, max_abs_v=max_abs_v)
    n = x.shape[0]
    classes = np.full(n, "", dtype=object)
    confidence = np.full(n, np.nan)
    with_base = np.zeros(n, dtype=bool)
    if baseline is not None:
        if nozzle_ids is None or np.shape(nozzle_ids) != (n,):
            raise ValueError(f"nozzle_ids must give each of the {n} rows its nozzle to use baselines")
        has, base_kpis = baseline.baselines.lookup(nozzle_ids)
        with_base = valid & has
        if with_base.any():
            labels, conf, ok = classify_finite(
                baseline.pipeline, with_baseline(x[with_base], base_kpis[with_base]), fd_threshold=baseline.fd_threshold)
            classes[with_base], confidence[with_base] = labels, conf
            reasons[np.flatnonzero(with_base)[~ok]] = "non_finite_features"
    plain = valid & ~with_base
    if plain.any():
        rows = x if plain.all() else x[plain]  # no copy of a frame that is all valid
        labels, conf, ok = classify_finite(pipeline, rows, fd_threshold=fd_threshold)
        classes[plain], confidence[plain] = labels, conf
        reasons[np.flatnonzero(plain)[~ok]] = "non_finite_features"
    valid = reasons == ""
    return FrameLabels(classes, confidence, valid, reasons, with_base & valid)


def label_frames(pipeline, frames, *, fd_threshold: float = 0.5, first_nozzles=None,
                 baseline: BaselineModel | None = None, max_abs_v: float | None = None) -> list:
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
    first_nozzles : sequence of int, optional
        Each frame's first nozzle id (its rows are a contiguous nozzle range);
        needed with ``baseline``.
    baseline : BaselineModel, optional
        As for :func:`label_traces`.
    max_abs_v : float, optional
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
    ids = None
    if baseline is not None:
        if first_nozzles is None or len(first_nozzles) != len(arrays):
            raise ValueError("first_nozzles must give each frame's first nozzle id to use baselines")
        ids = np.concatenate([int(f) + np.arange(a.shape[0]) for f, a in zip(first_nozzles, arrays)])
    rows = label_traces(pipeline, np.concatenate(arrays) if len(arrays) > 1 else arrays[0],
                        fd_threshold=fd_threshold, nozzle_ids=ids, baseline=baseline, max_abs_v=max_abs_v)
    cuts = np.cumsum([a.shape[0] for a in arrays])[:-1]
    cols = (rows.classes, rows.confidence, rows.valid, rows.reasons, rows.baseline)
    return [FrameLabels(*p) for p in zip(*(np.split(col, cuts) for col in cols))]


def label_frames_isolated(pipeline, frames, *, fd_threshold: float = 0.5, first_nozzles,
                          baseline: BaselineModel | None = None, max_abs_v: float | None = None) -> list:
    """:func:`label_frames`, and where that raises, each frame alone: one bad frame costs only itself.

    Parameters are those of :func:`label_frames` (``first_nozzles`` required).

    Returns
    -------
    list
        Per frame, its :class:`FrameLabels`, or a ``str`` naming the exception
        that labelling it alone raised.
    """
    try:
        return label_frames(pipeline, frames, fd_threshold=fd_threshold, first_nozzles=first_nozzles,
                            baseline=baseline, max_abs_v=max_abs_v)
    except Exception:  # noqa: BLE001 - find the frame(s) at fault
        out = []
        for a, first in zip(frames, first_nozzles):
            try:
                a = np.asarray(a)
                out.append(label_traces(pipeline, a, fd_threshold=fd_threshold,
                                        nozzle_ids=int(first) + np.arange(a.shape[0]), baseline=baseline,
                                        max_abs_v=max_abs_v))
            except Exception as exc:  # noqa: BLE001 - the caller counts and reports it
                out.append(f"{type(exc).__name__}: {exc}")
        return out
