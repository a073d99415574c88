"""Open-set layer of the FDI model: ``unknown`` for a trace unlike every known class.

The classifier of :class:`inkdiag_core.FaultDetector` always answers one of its
classes; a condition it was never trained on (a poor contact, crosstalk from a
neighbour, a foreign-body resonance, ...) comes out as a confident wrong class or,
worse, as healthy (issue 16). This module adds a Mondrian (per-class) split-conformal
test in front of the answer:

1. **Features** (:func:`openset_features`): what a single damped sinusoid says about
   the trace (the 7 KPIs, scale-like ones in log, the phase as cos/sin) plus what it
   cannot see: ``log10`` of the fraction of the trace's AC energy the fitted sinusoid
   leaves unexplained (:func:`unexplained_fraction`; a second mode, a foreign-body
   resonance, crosstalk or a cut pulse all leave energy outside it). With a nozzle's
   healthy baseline the KPIs relative to it are added (:func:`baseline_openset_features`).
2. **Nonconformity** (:class:`ConformalOpenSet`): per class ``c`` the squared
   Mahalanobis distance of the standardized features to that class, with the covariance
   of all the class's fit rows regularised by a ridge (0.05 in units of the features'
   robust scale over all classes: it keeps a class's ellipsoid from being narrower than
   the difference between our simulator and another generator's traces of the same
   class), fitted on held-out known rows. All its rows, not a robust core: the calibration
   rows set each class's threshold from the top of their scores, and a class with a long
   tail in one direction (a calibrated head's empty channels: weak or near-silent traces
   from the fault physics that healthy traces cannot pin, ``docs/calibration.md``) then
   gets a radius of that tail's size in *every* direction under a robust (minimum
   covariance determinant) covariance that leaves the tail out; under the plain one the
   ellipsoid is long only along the tail (``reports/heads.md``, off-class traces; ``tests/core/test_openset.py``).
   **Weak rows**: a row whose fitted sinusoid's amplitude is below
   :data:`SNR_FLOOR` times the head's noise (``noise_v``: :class:`inkdiag_core.FaultDetector`
   estimates it from its healthy training traces) has KPIs that mostly measure the noise: such rows
   are left out of the class models and of the Mahalanobis calibration (a calibrated head's
   near-silent empty channels would otherwise scatter over every direction and widen those classes
   everywhere). A weak row is judged by its weakness alone, against the class the classifier chose:
   ``p = (1 + #weak calibration rows of c) / (n_c + 1)`` over all of ``c``'s calibration rows, and
   the row is unknown when ``p <= a_c`` (the training-conditional level of ``n_c``): a class that
   is never weak (the healthy ones; every class of the default head) does not take a weak row,
   while a calibrated head's empty channels, weak in a share of their rows, do. So noise alone is
   unknown on the default head, as before, and never healthy on a calibrated one.
3. **Calibration**: the scores of a split of known rows held out from that fit, kept
   sorted per class (:class:`inkdiag_core.FaultDetector` fits the class models on its
   validation split and calibrates on its training split: the score does not involve the
   classifier, and the larger split steadies each class's threshold). A row's conformal p-value for
   class ``c`` is ``p_c = (1 + #{calibration scores of c >= its score under c}) / (n_c + 1)``.
4. **Decision** (training-conditional, Vovk 2012): per class the largest ``m_c`` with
   ``P(Binomial(n_c, rate) <= m_c) <= delta``; a row is ``unknown`` when, for every class,
   at most ``m_c`` calibration scores of that class are ``>=`` its score, i.e.
   ``p_c <= a_c = (1 + m_c) / (n_c + 1)`` for every ``c``. Its score is
   ``1 - max_c q_c`` with ``q_c = min(1, p_c * rate / a_c)``, so ``unknown`` is exactly
   ``max_c q_c <= rate``, as in the plain split-conformal rule it replaces.

Guarantee (per class): if the rows of known class ``c`` are exchangeable with its
calibration rows (drawn from the same distribution: the same head and conditions as
training), the probability that a row of ``c`` is called ``unknown``, *for the layer one
training run fitted*, is at most ``rate`` with probability at least ``1 - delta`` over the
calibration draw (the rate of a fitted layer is ``Beta(m_c + 1, n_c - m_c)``-distributed;
``P(Beta > rate) = P(Binomial(n_c, rate) <= m_c) <= delta``). With a noise floor that holds for
the class's rows above the floor (the Mahalanobis test, calibrated on them); its weak rows add the
weakness test's own share, which fires only for a class weak in at most its level's share of its
calibration rows: together at most about ``2 rate`` with probability ``1 - 2 delta`` in the worst
case (a class weak in about ``rate`` of its rows), ``rate`` for a class never weak (every class
of the default head) or weak in many rows. A weak row is judged against the class the classifier
chose, so a weak row of a class the classifier mistakes for a class never weak is ``unknown``
(a wrong class either way). The plain split-conformal rule
(``max_c p_c <= rate``) bounds it only on average over training runs, and with ~300
calibration rows per class one fitted layer's rate spread so that a single class of a
single training seed read 2.67 % at ``rate = 0.01`` (``reports/unknown.md``, before).
On average a class's rate is ``(1 + m_c) / (n_c + 1)``: 0.33 % with 300 calibration rows
(``m_c = 0``), 0.53 % with 750 (``m_c = 3``), at ``rate = 0.01``, ``delta = 0.1``. A class
with ``(1 - rate) ** n_c > delta`` (for those settings, fewer than 230 calibration rows)
cannot certify any row as unlike it, so with such a class (or a class without a model) the
layer calls no row unknown: conservative, never wrong about the guarantee.
Nothing is guaranteed about rows of unseen conditions: how often they come out ``unknown``
is measured (``scripts/report unknown``).
"""

from __future__ import annotations

import numbers

import numpy as np

__all__ = [
    "OPENSET_FEATURES_VERSION",
    "OPENSET_SCORES_VERSION",
    "SNR_FLOOR",
    "UNKNOWN",
    "ConformalOpenSet",
    "DEFAULT_DELTA",
    "baseline_openset_features",
    "check_unknown_rate",
    "openset_features",
    "training_conditional_level",
    "unexplained_fraction",
]

#: Default probability that a fitted layer's false-unknown rate of a class exceeds its ``rate``.
DEFAULT_DELTA = 0.1
#: The class value of a row unlike every known class (a string, like ``FaultClass`` values).
UNKNOWN = "unknown"
#: Version of :func:`openset_features` / :func:`baseline_openset_features` (2: without the
#: dc offset). A :class:`ConformalOpenSet` fitted on other features cannot score these.
OPENSET_FEATURES_VERSION = 2
#: Scores of :meth:`ConformalOpenSet.scores` (4: each class's covariance of all its fit rows, rows below
#: :data:`SNR_FLOOR` judged by their weakness alone; 3: the covariance of all rows, every row judged; 2: the
#: classes' minimum-covariance-determinant cores, every row judged; 2-4 scored alike, row by row,
#: :func:`inkdiag_core._kernels.mahalanobis_scores`; 1: numpy's matrix products of the batch,
#: whose summation order for a row depends on the batch). A layer scores test rows as it scored its calibration
#: rows: a layer of version 2 or 3 labels as it did (the default model is retrained,
#: :mod:`inkdiag_core.model_cache`).
OPENSET_SCORES_VERSION = 4

#: A row whose fitted amplitude is below this many times the head's noise standard deviation is weak: judged by
#: that weakness alone (module docstring). 3: white noise alone fits a sinusoid of 0.26 sigma (median), 1.45 at
#: most (1,000 traces of 512 samples at 10 MHz).
SNR_FLOOR = 3.0
_AMPLITUDE = 2  # the open-set features' column of log(amplitude / V)
_TINY = 1e-30
# Added to the diagonal of each class covariance, in standardized units (the features' robust
# scale over all classes): a class is never narrower than ~0.22 of that scale in any direction.
# Our simulator's classes are tighter than the gap to another generator's traces of the same
# class: with 1e-3, tests/foreign_head.py's fully_blocked traces (head h20, an independent
# simulator) were 28.5 % unknown; 0.03: 3.0 %; 0.05: 1.0 % (max over the 12 classes, 200 each),
# while our own mild ad-hoc crosstalk stayed 92 % unknown (97 % at 0.03, 46 % at 0.3); measured with the
# robust (MCD) class covariances of scores version 2.
_RIDGE = 0.05
_MIN_FIT_ROWS = 4  # fewer training rows of a class: no model for it (its p-value is 1)
_POW_BLOCK = 32  # z**k = (z**32)**a * z**b in _unexplained_fraction_numpy (the kernel's blocks too)
_CHUNK = 1024  # traces per chunk in _unexplained_fraction_numpy (a chunk's arrays stay in cache)
#: Rows up to which ConformalOpenSet's p-values are counted by the compiled kernel (``scripts/bench fdi``:
#: 2.8-5.0x on the gate's ~70 leftover rows, 0.93-1.09x on 1,600).
_P_KERNEL_MAX_ROWS = 256


def check_unknown_rate(rate):
    """``rate`` as a float in (0, 1), or None for "no open-set layer" (None or 0).

    Raises
    ------
    ValueError
        Anything else (a bool, a negative number, >= 1, NaN).
    """
    if rate is None:
        return None
    ok = isinstance(rate, numbers.Real) and not isinstance(rate, bool) and np.isfinite(rate) and 0.0 <= rate < 1.0
    if not ok:
        raise ValueError(f"unknown_rate must be None or a real number in [0, 1), got {rate!r}")
    return float(rate) if rate > 0 else None


def unexplained_fraction(traces, kpis, sample_rate_hz):
    """Fraction of each trace's AC energy that its fitted damped sinusoid leaves unexplained.

    ``sum((y - model)**2) / sum((y - dc)**2)`` with ``model`` the sinusoid of the KPIs
    (:func:`inkdiag_core.kpis.reconstruct`'s formula, batch, without its checks: a row
    with unusable KPIs gets NaN, not an error for the batch).

    The model is ``Re(C z**k)`` with ``C = A exp(i phi)`` and ``z`` the per-sample pole,
    so ``rest = total - 2 <y - dc, model> + |model|**2``: the cross term is, per block of
    32 samples ``k = 32 a + b``, ``Re(C z**(32 a) * sum_b (y - dc)[32 a + b] z**b)``,
    ``|model|**2`` per block in closed form; no ``exp`` or ``cos`` per sample. Compiled,
    one row at a time in float64 (:func:`inkdiag_core._kernels.unexplained`): within 1e-11
    (relative) of the direct formula on the simulator's 512-sample traces (short traces that
    the sinusoid fits almost exactly: within 1e-9, the cancellation in ``rest``). (Its numpy form,
    :func:`_unexplained_fraction_numpy`, sums in float32: within 0.3 %; ``scripts/bench fdi``
    times both.)

    Parameters
    ----------
    traces : ndarray, shape (n, n_samples)
        Raw traces, V.
    kpis : ndarray, shape (n, 7)
        Their KPIs (:func:`inkdiag_core.extract_kpis`).
    sample_rate_hz : float
        Sample rate, Hz.

    Returns
    -------
    ndarray of float64, shape (n,)
        Usually in [0, 1] (above 1 where the fit is worse than the DC level alone);
        NaN where the KPIs are not finite or the damping ratio is outside [0, 1).
    """
    from ._kernels import unexplained  # numba: imported when a kernel is first needed

    x = np.asarray(traces)
    if x.dtype not in (np.float32, np.float64):
        x = x.astype(np.float64)
    return unexplained(x, np.asarray(kpis, dtype=np.float64), sample_rate_hz, _TINY)


def _unexplained_fraction_numpy(traces, kpis, sample_rate_hz):
    """:func:`unexplained_fraction` in numpy, its samples summed in float32 blocks (one small
    matrix product per trace on the powers ``z**b``): within 0.3 % (relative) of the direct
    formula. The compiled kernel's reference in the tests and in ``scripts/bench fdi``."""
    x = np.asarray(traces)
    k = np.asarray(kpis, dtype=np.float64)
    n, N = x.shape
    B = _POW_BLOCK
    n_hi = (N + B - 1) // B
    pad = n_hi * B - N
    with np.errstate(all="ignore"):
        zeta = k[:, 2]
        bad = ~(np.isfinite(k).all(axis=1) & (zeta >= 0) & (zeta < 1))
        kk = np.where(bad[:, None], 0.0, k)
        w = 2.0 * np.pi * kk[:, 1] / float(sample_rate_hz)  # rad per sample
        sigma = kk[:, 2] * w / np.sqrt(1.0 - kk[:, 2] ** 2)  # decay per sample
        log_z = -sigma + 1j * w
        z = np.exp(log_z)
        C = kk[:, 3] * np.exp(1j * kk[:, 4])
        lo = np.empty((n, B), dtype=np.complex64)  # z**b, b < B (32 products: float32 is exact enough)
        lo[:, 0] = 1.0
        lo[:, 1:] = z[:, None]
        np.cumprod(lo, axis=1, out=lo)
        hi = np.empty((n, n_hi), dtype=np.complex64)  # C z**(B a)
        hi[:, 0] = C
        hi[:, 1:] = np.exp(B * log_z)[:, None]
        np.cumprod(hi, axis=1, out=hi)
        G = np.empty((n, B, 2), dtype=np.float32)
        G[:, :, 0] = lo.real
        G[:, :, 1] = lo.imag
        hr, hq = np.ascontiguousarray(hi.real), np.ascontiguousarray(hi.imag)
        # |model|**2 = |C|**2/2 sum r**(2k) + Re(C**2 sum z**(2k))/2, k < N (geometric series)
        d1, d2 = -np.expm1(-2.0 * sigma), 1.0 - np.exp(2.0 * log_z)
        s1 = np.where(d1 > 1e-12, -np.expm1(-2.0 * N * sigma) / np.where(d1 > 1e-12, d1, 1.0), N)
        s2 = np.where(np.abs(d2) > 1e-12, (1.0 - np.exp(2.0 * N * log_z)) / np.where(np.abs(d2) > 1e-12, d2, 1.0), N)
        model2 = 0.5 * np.abs(C) ** 2 * s1 + 0.5 * np.real(C * C * s2)
        dc = kk[:, 0].astype(np.float32)
        total, cross = np.empty(n), np.empty(n)
        for a in range(0, n, _CHUNK):
            b = min(a + _CHUNK, n)
            ac = x[a:b].astype(np.float32, copy=False) - dc[a:b, None]
            if pad:
                ac = np.concatenate([ac, np.zeros((b - a, pad), dtype=np.float32)], axis=1)
            total[a:b] = np.einsum("ij,ij->i", ac, ac)
            P = np.matmul(ac.reshape(b - a, n_hi, B), G[a:b])  # (chunk, n_hi, 2)
            cross[a:b] = np.einsum("na,na->n", hr[a:b], P[:, :, 0]) - np.einsum("na,na->n", hq[a:b], P[:, :, 1])
        out = np.maximum(total - 2.0 * cross + model2, 0.0) / np.maximum(total, _TINY)
    out[bad | ~np.isfinite(out)] = np.nan
    return out


def training_conditional_level(n, rate, delta=DEFAULT_DELTA):
    """The p-value level ``a = (1 + m) / (n + 1)`` of a PAC conformal test, or 0 if none exists.

    ``m`` is the largest count of calibration scores allowed at or above a row's score with
    ``P(Binomial(n, rate) <= m) <= delta``: with ``n`` calibration scores, the rule
    ``p <= a`` then rejects a row of the calibrated distribution with probability ``<= rate``,
    with probability ``>= 1 - delta`` over the calibration draw (Vovk 2012, *Conditional
    validity of inductive conformal predictors*).

    Parameters
    ----------
    n : int
        Calibration scores, ``>= 0``.
    rate, delta : float in (0, 1)

    Returns
    -------
    float
        ``a`` in ``(0, rate]``, or 0.0 when even ``m = 0`` does not hold (``(1 - rate) ** n > delta``).
    """
    from scipy.stats import binom

    n = int(n)
    if n <= 0:
        return 0.0
    ok = np.flatnonzero(binom.cdf(np.arange(n), n, rate) <= delta)
    # never above rate: for delta >= ~0.5 the binomial rule alone would be looser than the
    # plain split-conformal one, which bounds the rate on average
    return 0.0 if ok.size == 0 else min(float((1 + ok[-1]) / (n + 1)), float(rate))


def openset_features(traces, kpis, sample_rate_hz):
    """Open-set features of traces from their KPIs: (n, 8), float64.

    Columns: ``log`` of dominant frequency, damping ratio, amplitude, energy and
    magnitude, cos and sin of the phase, and ``log10`` of :func:`unexplained_fraction`.
    Not the dc offset: it is the sensor channel's, not the ink channel's response, and a
    healthy nozzle whose offset sits in the tail of the head's spread would be ``unknown``
    in every frame (``scripts/run``: one of 64 nozzles, 42 of 42 frames). Logs are taken of values floored at 1e-30 (so a
    zero stays finite); a row with non-finite KPIs comes out non-finite.

    Parameters
    ----------
    traces : ndarray, shape (n, n_samples)
        Raw traces, V.
    kpis : ndarray, shape (n, 7)
        Their KPIs (:data:`inkdiag_core.KPI_NAMES` order).
    sample_rate_hz : float
        Sample rate, Hz.

    Returns
    -------
    ndarray of float64, shape (n, 8)
    """
    k = np.asarray(kpis, dtype=np.float64)
    with np.errstate(all="ignore"):
        lg = np.log(np.maximum(k[:, [1, 2, 3, 5, 6]], _TINY))
        u = np.log10(np.maximum(unexplained_fraction(traces, k, sample_rate_hz), 1e-12))
        return np.column_stack([lg, np.cos(k[:, 4]), np.sin(k[:, 4]), u])


def baseline_openset_features(traces, features13, sample_rate_hz):
    """Open-set features of the baseline branch: :func:`openset_features` + relative KPIs, (n, 13).

    Parameters
    ----------
    traces : ndarray, shape (n, n_samples)
        Raw traces, V.
    features13 : ndarray, shape (n, 13)
        The baseline branch's features (:class:`inkdiag_core.baselines.BaselineKpis`):
        the 7 KPIs, then frequency ratio, damping-ratio difference and ratio, amplitude
        ratio, energy ratio and phase difference against the nozzle's healthy baseline.
    sample_rate_hz : float
        Sample rate, Hz.

    Returns
    -------
    ndarray of float64, shape (n, 13)
        :func:`openset_features` columns, then ``log`` frequency ratio, damping-ratio
        difference, ``log`` amplitude ratio, ``log`` energy ratio, cos of the phase difference.
    """
    f = np.asarray(features13, dtype=np.float64)
    with np.errstate(all="ignore"):
        rel = np.column_stack([np.log(np.maximum(f[:, 7], _TINY)), f[:, 8],
                               np.log(np.maximum(f[:, 10], _TINY)), np.log(np.maximum(f[:, 11], _TINY)),
                               np.cos(f[:, 12])])
    return np.hstack([openset_features(traces, f[:, :7], sample_rate_hz), rel])


class ConformalOpenSet:
    """Per-class (Mondrian) split-conformal open-set test on feature rows.

    See the module docstring for the score, the p-values and the guarantee.

    Parameters
    ----------
    rate : float in (0, 1)
        The bound on a known class's false-unknown probability.
    delta : float in (0, 1)
        The probability, over the calibration draw, that a fitted layer's rate of a class
        exceeds ``rate`` (default :data:`DEFAULT_DELTA`).

    Attributes
    ----------
    classes_ : ndarray, shape (n_classes,)
        Classes in the order of the p-value columns.
    center_, scale_ : ndarray of float64, shape (d,)
        Standardization of the features (median and IQR-based scale of the fit rows).
    means_ : ndarray of float64, shape (n_classes, d)
        Class centres (standardized units).
    whiten_ : ndarray of float64, shape (n_classes, d, d)
        Per class a matrix ``W`` with ``W W^T`` the inverse regularised covariance.
    calibration_ : list of ndarray of float32
        Per class its calibration scores (:meth:`scores`), sorted (possibly empty).
    modelled_ : ndarray of bool, shape (n_classes,)
        Classes with a model (>= 4 fit rows); the others get p-value 1.
    noise_v_ : float or None
        The head's noise standard deviation, V (``fit``'s ``noise_v``); rows whose amplitude is below
        :data:`SNR_FLOOR` times it are weak (module docstring). None: no row is.
    weak_q_ : ndarray of float64, shape (n_classes,), or None
        Per class the ``q`` of a weak row chosen as that class (``min(1, p rate / a)`` of its weak p-value;
        1 for a class without a model or a level): the row is unknown where it is ``<= rate``. None without
        ``noise_v_``.
    levels_ : ndarray of float64, shape (n_classes,)
        Per class the p-value level ``a_c`` at or below which the class calls a row unlike it
        (:func:`training_conditional_level` of its calibration count; 0: never).
    """

    def __init__(self, rate=0.01, delta=DEFAULT_DELTA):
        self.rate = rate
        self.delta = delta

    def fit(self, X_fit, y_fit, X_cal, y_cal, classes, *, noise_v=None):
        """Fit the class models on ``(X_fit, y_fit)`` and calibrate on ``(X_cal, y_cal)``.

        Parameters
        ----------
        X_fit : ndarray, shape (n_fit, d)
            Finite feature rows for the class models (the classifier's training rows).
        y_fit : ndarray, shape (n_fit,)
        X_cal : ndarray, shape (n_cal, d)
            Feature rows held out from the fit (rows with non-finite features are dropped).
        y_cal : ndarray, shape (n_cal,)
        classes : array_like, shape (n_classes,)
            Class order of the p-value columns (the classifier's ``classes_``).
        noise_v : float, optional
            The head's noise standard deviation, V: rows of amplitude (column 2, ``log`` V) below
            :data:`SNR_FLOOR` times it are weak: left out of the class models and the Mahalanobis
            calibration, and judged by their weakness alone (:attr:`weak_q_`). None: no row is weak.

        Returns
        -------
        self
        """
        from sklearn.covariance import EmpiricalCovariance

        rate = check_unknown_rate(self.rate)
        if rate is None:
            raise ValueError("ConformalOpenSet needs a rate in (0, 1)")
        if noise_v is not None and not (np.isfinite(noise_v) and noise_v > 0):
            raise ValueError(f"noise_v must be a positive number of volts or None, got {noise_v!r}")
        self.noise_v_ = None if noise_v is None else float(noise_v)
        X_fit = np.asarray(X_fit, dtype=np.float64)
        X_cal = np.asarray(X_cal, dtype=np.float64)
        y_fit, y_cal = np.asarray(y_fit), np.asarray(y_cal)
        self.classes_ = np.asarray(classes)
        ok = np.isfinite(X_fit).all(axis=1) & self._judged(X_fit)
        X_fit, y_fit = X_fit[ok], y_fit[ok]
        d = X_fit.shape[1]
        self.center_ = np.median(X_fit, axis=0)
        q75, q25 = np.percentile(X_fit, [75, 25], axis=0)
        spread = (q75 - q25) / 1.349
        std = X_fit.std(axis=0)
        self.scale_ = np.where(spread > 1e-12 * (np.abs(self.center_) + 1), spread, np.where(std > 0, std, 1.0))
        k = len(self.classes_)
        self.means_ = np.zeros((k, d))
        self.whiten_ = np.tile(np.eye(d), (k, 1, 1))
        self.modelled_ = np.zeros(k, dtype=bool)
        Z = self._standardize(X_fit)
        for i, c in enumerate(self.classes_):
            Zc = Z[y_fit == c]
            if Zc.shape[0] < _MIN_FIT_ROWS:
                continue
            est = EmpiricalCovariance().fit(Zc)  # all the class's rows (module docstring)
            cov = est.covariance_ + _RIDGE * np.eye(d)
            prec = np.linalg.inv(cov)
            prec = (prec + prec.T) / 2
            self.whiten_[i] = np.linalg.cholesky(prec)
            self.means_[i] = est.location_
            self.modelled_[i] = True
        for cache in ("_w_all", "_mu_w", "_block_sum", "_cal_table", "_tail"):  # rebuilt from the fit
            self.__dict__.pop(cache, None)
        self.features_version_ = OPENSET_FEATURES_VERSION
        self.scores_version_ = OPENSET_SCORES_VERSION
        cal_ok = np.isfinite(X_cal).all(axis=1) & self._judged(X_cal)
        S = self.scores(X_cal[cal_ok])
        yc = y_cal[cal_ok]
        self.calibration_ = [np.sort(S[yc == c, i]) for i, c in enumerate(self.classes_)]
        self.levels_ = self._levels()
        self.weak_q_ = None
        if self.noise_v_ is not None:  # a weak row against each class: (1 + its weak rows) / (all its rows + 1)
            finite = np.isfinite(X_cal).all(axis=1)
            weak = finite & ~self._judged(X_cal)
            delta = float(getattr(self, "delta", DEFAULT_DELTA))
            self.weak_q_ = np.ones(len(self.classes_))
            for i, c in enumerate(self.classes_):
                n_all, n_weak = int((finite & (y_cal == c)).sum()), int((weak & (y_cal == c)).sum())
                a = training_conditional_level(n_all, rate, delta) if self.modelled_[i] else 0.0
                if a > 0:
                    self.weak_q_[i] = min(1.0, (1.0 + n_weak) / (n_all + 1.0) * (rate / a))
        return self

    def _log_min_amplitude(self) -> float:
        """``log`` of the smallest amplitude the layer judges, V (-inf: every row; a layer without ``noise_v_``)."""
        noise = getattr(self, "noise_v_", None)
        return -np.inf if noise is None else float(np.log(SNR_FLOOR * noise))

    def _judged(self, X):
        """Rows the layer judges: amplitude (``log``, column 2) at least :data:`SNR_FLOOR` noise sigmas (bool (n,))."""
        X = np.asarray(X, dtype=np.float64)
        if getattr(self, "noise_v_", None) is None:  # any feature rows (not only the open-set features)
            return np.ones(X.shape[0], dtype=bool)
        with np.errstate(invalid="ignore"):
            return ~(X[:, _AMPLITUDE] < self._log_min_amplitude())

    def _levels(self):
        delta = float(getattr(self, "delta", DEFAULT_DELTA))  # a layer pickled before delta existed
        if not 0.0 < delta < 1.0:
            raise ValueError(f"delta must be in (0, 1), got {delta!r}")
        return np.array([training_conditional_level(cal.size, float(self.rate), delta) if m else 0.0
                         for cal, m in zip(self.calibration_, self.modelled_)])

    def _standardize(self, X):
        return (np.asarray(X, dtype=np.float64) - self.center_) / self.scale_

    def scores(self, X):
        """Nonconformity of each row to each class: squared Mahalanobis distances, float32 (n, n_classes).

        ``|z W_c - mu_c W_c|**2`` for every class, in float32 (calibration and test rows alike, so
        their ranks compare like with like), one row at a time
        (:func:`inkdiag_core._kernels.mahalanobis_scores`): a row's scores do not depend on the
        rows scored with it. Non-finite for a row with non-finite features. A layer fitted before
        (:data:`OPENSET_SCORES_VERSION` 1) scores as it was calibrated, by numpy's matrix products.
        """
        Z = self._standardize(X)
        k, d = self.means_.shape
        if not hasattr(self, "_w_all"):  # float32: the same arithmetic for calibration and test rows
            self._w_all = self.whiten_.transpose(1, 0, 2).reshape(d, k * d).astype(np.float32)  # (d, k*d)
            self._mu_w = np.einsum("kd,kde->ke", self.means_, self.whiten_).reshape(k * d).astype(np.float32)
        with np.errstate(all="ignore"):
            if getattr(self, "scores_version_", 1) < 2:  # calibrated by numpy's matrix products: scored so
                W = Z.astype(np.float32) @ self._w_all
                W -= self._mu_w
                W *= W
                return W @ np.repeat(np.eye(k, dtype=np.float32), d, axis=0)  # (k*d, k): sums d squares
            from ._kernels import mahalanobis_scores  # numba: imported when a kernel is first needed

            return mahalanobis_scores(Z.astype(np.float32), self._w_all, self._mu_w)

    def p_values(self, X):
        """Conformal p-value of each row for each class, (n, n_classes), in (0, 1].

        ``(1 + #{calibration scores of c >= score}) / (n_c + 1)``; 1 for a class without a
        model; NaN for a row with non-finite features.
        """
        return self._p_of_scores(self.scores(X))

    def _p_of_scores(self, S):
        """:meth:`p_values` of the scores ``S`` (n, n_classes): compiled (:func:`inkdiag_core._kernels.p_values`)
        up to :data:`_P_KERNEL_MAX_ROWS` rows, where one ``searchsorted`` call per class is the fixed cost;
        beyond, numpy's (as fast there, ``scripts/bench fdi``). The same p-values either way."""
        if S.shape[0] > _P_KERNEL_MAX_ROWS or S.dtype != np.float32:
            return self._p_of_scores_numpy(S)
        from ._kernels import p_values  # numba: imported when a kernel is first needed

        table = self._calibration_table()
        if table is None:  # scores calibrated in another precision than scores() gives
            return self._p_of_scores_numpy(S)
        return p_values(S, *table, np.asarray(self.modelled_, dtype=bool))

    def _calibration_table(self):
        """``(scores, starts)``: every class's calibration scores in one float32 array and where each
        class's begin, built again whenever ``calibration_`` holds other arrays (a refit, a reassigned
        list or element; the arrays are not to be changed in place); None unless all are float32.
        Not pickled (:meth:`__getstate__`): a saved layer's bytes do not depend on its use."""
        cal = self.calibration_
        cached = self.__dict__.get("_cal_table")
        # the list and its arrays themselves (held, so no new array can take a freed one's place)
        if cached is None or cached[0] is not cal or len(cached[1]) != len(cal) or any(
                a is not b for a, b in zip(cached[1], cal)):
            table = None
            if all(np.asarray(c).dtype == np.float32 for c in cal):
                table = (np.concatenate([np.empty(0, np.float32), *cal]),
                         np.cumsum([0] + [len(c) for c in cal]).astype(np.int64))
            self._cal_table = cached = (cal, tuple(cal), table)
        return cached[2]

    def _tail_params(self):
        """What :func:`inkdiag_core._kernels.detector_tail` needs of this layer, or None where its scores are
        not the kernel's (its calibration in another precision, or by numpy's matrix products):
        ``(center, scale, w_all, mu_w, cal, starts, modelled, levels, rate, rate_bound, tiny, log_min_amplitude,
        weak_q)``, as :meth:`scores`,
        :meth:`_p_of_scores`, :meth:`unknown_score` and :meth:`is_unknown` use them: the whitening ``w_all``
        (d, k * d) and the centres ``mu_w`` (k * d) in float32, as :meth:`scores` builds them; ``tiny``
        the floor of the features' logs (:func:`openset_features`); ``log_min_amplitude`` the ``log`` of the
        smallest amplitude judged by the Mahalanobis scores, V (-inf: every row), ``weak_q`` :attr:`weak_q_`."""
        table = self._calibration_table()
        if table is None or getattr(self, "scores_version_", 1) < 2:
            return None
        if not hasattr(self, "_w_all"):
            self.scores(np.zeros((0, self.means_.shape[1])))  # builds the float32 whitening once
        levels = getattr(self, "levels_", None)
        if levels is None:  # a layer fitted before the training-conditional levels
            levels = self.levels_ = self._levels()
        # built again whenever one of the arrays (or the rate) it comes from is another object
        weak_q = getattr(self, "weak_q_", None)
        key = (table, self.center_, self.scale_, self._w_all, self._mu_w, self.modelled_, levels, self.rate,
               getattr(self, "noise_v_", None), weak_q)
        cached = self.__dict__.get("_tail")
        if cached is not None and len(cached[0]) == len(key) and all(a is b for a, b in zip(cached[0], key)):
            return cached[1]

        def c(a, dtype):
            return np.require(a, dtype, ["C", "W"])

        params = (c(self.center_, np.float64), c(self.scale_, np.float64), c(self._w_all, np.float32),
                  c(self._mu_w, np.float32), c(table[0], np.float32), c(table[1], np.int64),
                  c(self.modelled_, bool), c(levels, np.float64), float(self.rate), self.rate * (1 + 1e-12), _TINY,
                  self._log_min_amplitude(), c(np.ones(len(levels)) if weak_q is None else weak_q, np.float64))
        self._tail = (key, params)
        return params

    def __getstate__(self):
        state = dict(self.__dict__)
        for cache in ("_cal_table", "_tail", "_cal_flat", "_cal_starts"):  # rebuilt on first use (the last two:
            state.pop(cache, None)  # an earlier form of the table, in layers pickled after use)
        return state

    def _p_of_scores_numpy(self, S):
        """:meth:`_p_of_scores` in numpy: one ``searchsorted`` per class (the kernel's reference in the tests)."""
        P = np.ones(S.shape)
        for i, cal in enumerate(self.calibration_):
            if not self.modelled_[i]:
                continue
            n_ge = cal.size - np.searchsorted(cal, S[:, i], side="left")
            P[:, i] = (1.0 + n_ge) / (cal.size + 1.0)
        P[~np.isfinite(S).all(axis=1)] = np.nan
        return P

    def unknown_score(self, X, chosen=None):
        """``1 - max_c q_c`` per row, (n,), in [0, 1); NaN for non-finite features.

        ``q_c = min(1, p_c * rate / a_c)``: the class's p-value scaled so that ``q_c <= rate``
        exactly where ``p_c <= a_c`` (:attr:`levels_`; 1 for a class that never calls a row
        unlike it, or has no model). A row is unknown when this is ``>= 1 - rate``. A weak row
        (module docstring): ``1 - weak_q_[chosen]``, against the class the classifier chose (``chosen``:
        column indices, (n,)); without ``chosen``, against every class (``1 - max_c weak_q_``).
        """
        P = self.p_values(X)
        levels = getattr(self, "levels_", None)
        if levels is None:  # a layer fitted before the training-conditional levels
            levels = self.levels_ = self._levels()
        with np.errstate(divide="ignore", invalid="ignore"):
            Q = np.where(levels > 0, np.minimum(1.0, P * (float(self.rate) / np.where(levels > 0, levels, 1.0))), 1.0)
        Q[np.isnan(P)] = np.nan
        out = 1.0 - Q.max(axis=1)
        weak = ~self._judged(X) & np.isfinite(P).all(axis=1)  # finite features, as the weak rows fit() counted
        if weak.any():  # the weak rows: by their weakness alone
            q = self.weak_q_
            out[weak] = 1.0 - (q.max() if chosen is None else q[np.asarray(chosen)[weak]])
        return out

    def is_unknown(self, score):
        """Rows whose :meth:`unknown_score` makes them unknown (``max_c q_c <= rate``), bool (n,)."""
        with np.errstate(invalid="ignore"):
            # 1 - score == max p exactly enough: compare in p to keep p == rate inclusive
            return (1.0 - np.asarray(score)) <= self.rate * (1 + 1e-12)
