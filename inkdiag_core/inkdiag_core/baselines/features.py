"""Baseline features: a trace's KPIs relative to its nozzle's own healthy KPIs.

- :func:`baseline_kpis`: a nozzle's baseline, the median KPIs over a few healthy frames
  (:func:`median_kpis`: the phase's on the circle where it wraps);
- :func:`with_baseline`: the input rows of a baseline pipeline, ``[trace, baseline]``;
- :class:`BaselineKpis`: transformer from those rows to KPI_Y plus the relative
  features (:data:`RELATIVE_NAMES`).
"""

from __future__ import annotations

import warnings

import numpy as np
from sklearn.base import BaseEstimator, TransformerMixin
from sklearn.utils.validation import check_is_fitted, validate_data

from ..kpis import KPI_NAMES, MIN_KPI_SAMPLES, extract_kpis, kpis_of_checked

__all__ = ["N_KPIS", "RELATIVE_NAMES", "BaselineKpis", "baseline_kpis", "with_baseline"]

#: KPIs per baseline row (the columns of :data:`inkdiag_core.KPI_NAMES`).
N_KPIS = len(KPI_NAMES)

#: Names of the relative features :class:`BaselineKpis` appends to KPI_Y.
RELATIVE_NAMES = ("frequency_ratio", "damping_ratio_difference", "damping_ratio_ratio",
                  "amplitude_ratio", "energy_ratio", "phase_difference_rad")

#: Offset of the relative features' denominators (a zero baseline KPI gives a large, finite ratio).
RELATIVE_EPS = 1e-30


def baseline_kpis(frames, sample_rate_hz: float) -> np.ndarray:
    """A nozzle's healthy baseline: the median of its KPIs over healthy frames.

    Parameters
    ----------
    frames : array_like, shape (n_nozzles, n_frames, n_samples)
        Healthy traces of each nozzle, V (each row's frames from the same nozzle).
    sample_rate_hz : float

    Returns
    -------
    ndarray, shape (n_nozzles, 7)
        Columns of :data:`inkdiag_core.KPI_NAMES`. The median keeps a frame with a
        passing disturbance from moving the baseline.
    """
    f = np.asarray(frames)
    if f.ndim != 3 or f.shape[1] < 1:
        raise ValueError(f"frames must be (n_nozzles, n_frames >= 1, n_samples), got shape {f.shape}")
    n, k, m = f.shape
    return median_kpis(extract_kpis(f.reshape(n * k, m), sample_rate_hz).reshape(n, k, N_KPIS))


#: Column of ``phase_rad`` in :data:`inkdiag_core.KPI_NAMES`.
PHASE = KPI_NAMES.index("phase_rad")


def median_kpis(kpis, *, skip_nan: bool = False) -> np.ndarray:
    """Each nozzle's median KPIs over its rows; the phase's median taken on the circle where it wraps.

    The phase is wrapped to ``(-pi, pi]``: a nozzle whose phase lies near ``+-pi`` has rows on both
    sides (3.14 and -3.14 rad), whose plain median can come out near 0 (the mean of the middle two),
    and every healthy trace of it then looks ``pi`` off its baseline. Where a nozzle's phases span more
    than ``pi``, the median is taken of their offsets from their circular mean (wrapped), and wrapped
    back; elsewhere it is the plain median (the same values as ``np.median``).

    Parameters
    ----------
    kpis : array_like, shape (n_nozzles, n_rows, n_columns)
        Each nozzle's rows; columns of :data:`inkdiag_core.KPI_NAMES` first (more columns are taken
        plainly).
    skip_nan : bool
        Rows with NaN left out, column by column (``np.nanmedian``); a nozzle with none gives NaN.

    Returns
    -------
    ndarray, shape (n_nozzles, n_columns)
    """
    x = np.asarray(kpis, dtype=float)
    median = np.nanmedian if skip_nan else np.median
    out = median(x, axis=1)
    phase = x[:, :, PHASE]
    if x.shape[1] == 0:
        return out
    with warnings.catch_warnings():  # a nozzle whose phases are all NaN (skip_nan): not one that wraps
        warnings.simplefilter("ignore", RuntimeWarning)
        wraps = np.flatnonzero(np.nanmax(phase, axis=1) - np.nanmin(phase, axis=1) > np.pi)
    if wraps.size:
        p = phase[wraps]
        centre = np.angle(np.nansum(np.exp(1j * p), axis=1))
        offsets = np.angle(np.exp(1j * (p - centre[:, None])))  # NaN stays NaN
        out[wraps, PHASE] = np.angle(np.exp(1j * (centre + median(offsets, axis=1))))
    return out


def with_baseline(traces, baseline) -> np.ndarray:
    """Input rows of a ``"kpi_y+baseline"`` pipeline: each trace followed by its nozzle's baseline.

    Parameters
    ----------
    traces : array_like, shape (n, n_samples)
    baseline : array_like, shape (n, 7)
        Row ``i``: the baseline KPIs (:func:`baseline_kpis`) of trace ``i``'s nozzle.

    Returns
    -------
    ndarray, shape (n, n_samples + 7)
        float64 (float32 if both inputs are float32).
    """
    x = np.asarray(traces)
    b = np.asarray(baseline)
    if x.ndim != 2 or b.shape != (x.shape[0], N_KPIS):
        raise ValueError(f"traces must be (n, n_samples) and baseline (n, {N_KPIS}); got shapes "
                         f"{x.shape} and {b.shape}")
    return np.hstack([x, b.astype(np.result_type(x.dtype, b.dtype), copy=False)])


class BaselineKpis(TransformerMixin, BaseEstimator):
    """KPI_Y of each trace plus its KPIs relative to its nozzle's healthy baseline.

    Input rows are ``[trace (n_samples), baseline KPIs (7)]`` (:func:`with_baseline`).
    Output (n, 7 + 6): :data:`inkdiag_core.KPI_NAMES`, then :data:`RELATIVE_NAMES`:
    frequency ratio, damping-ratio difference and ratio, amplitude ratio, energy
    ratio (dimensionless) and phase difference (rad, wrapped to (-pi, pi]).

    Parameters
    ----------
    sample_rate_hz : float
        Sample rate of the traces, Hz.
    """

    def __init__(self, sample_rate_hz=10e6):
        self.sample_rate_hz = sample_rate_hz

    def fit(self, X, y=None):
        validate_data(self, X, dtype=[np.float64, np.float32], ensure_min_features=MIN_KPI_SAMPLES + N_KPIS)
        return self

    def transform(self, X):
        check_is_fitted(self, "n_features_in_")
        X = validate_data(self, X, dtype=[np.float64, np.float32], reset=False)
        return self._transform_checked(X)

    def _transform_checked(self, X):
        """:meth:`transform` of rows already validated against this fitted step (finite float32/64 ndarray,
        ``n_features_in_`` columns): the same result without scikit-learn's checks (the detector's hot path)."""
        return self._features_of(X[:, :-N_KPIS], X[:, -N_KPIS:])

    def _features_of(self, traces, baseline):
        """The features of ``traces`` (n, n_features_in_ - 7; finite float32/64) against ``baseline``
        (n, 7; finite) without stacking them into one copy (the detector's hot path).

        The KPIs are fitted in the traces' own precision, as the plain branch fits them
        (:func:`inkdiag_core.kpis.kpis_of_checked`): float32 traces in float32, where the stacked
        rows of float32 traces and float64 baselines are float64 (:meth:`_transform_checked` of
        :func:`with_baseline`). The relative features are computed in float64 either way. On
        float32 traces of every class (14,400 rows, 6 seeds, the default detector) not one class
        or confidence differs from the stacked rows' (a scratch check, 2026-11-26; the open-set
        layer's unknown score moved on 16 of them, none across its threshold); float64 traces give
        the stacked rows' features bit for bit (tests).
        """
        k = kpis_of_checked(traces, float(self.sample_rate_hz))
        b = np.asarray(baseline).astype(np.float64)
        dphi = np.angle(np.exp(1j * (k[:, 4] - b[:, 4])))
        rel = np.column_stack([
            k[:, 1] / (b[:, 1] + RELATIVE_EPS), k[:, 2] - b[:, 2], k[:, 2] / (b[:, 2] + RELATIVE_EPS),
            k[:, 3] / (b[:, 3] + RELATIVE_EPS), k[:, 5] / (b[:, 5] + RELATIVE_EPS), dphi,
        ])
        return np.hstack([k, rel])

    def get_feature_names_out(self, input_features=None):
        return np.array(KPI_NAMES + RELATIVE_NAMES, dtype=object)
