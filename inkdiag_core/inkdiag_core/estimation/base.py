"""Common pieces of the f_m estimators: results, model scaling, input checks, regression.

Shared by :mod:`.uio` (the thesis's DT/CT estimators and ``"dt_exact"``), :mod:`.vp`
(variable projection and ``"vp_cal"``) and the dispatcher :mod:`.dispatch`. The names
here are public within the estimation package (helpers of its modules); the package
re-exports only :class:`FmEstimate`, :class:`FmBatchEstimate` and :data:`MIN_FM_SAMPLES`.

Internally time is in microseconds (:data:`T0`), the states are balanced by a diagonal
similarity (:class:`Scaled`) and each trace is divided by its RMS.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla
import scipy.signal

from .. import checks
from ..model import InkChannelModel

__all__ = [
    "MIN_FM_SAMPLES",
    "T0",
    "FmEstimate",
    "FmBatchEstimate",
    "Scaled",
    "check_x0",
    "default_bounds",
    "model_matrices",
    "period_samples",
    "prefilter",
    "scaled",
    "scaled_cached",
    "windowed_regression",
]

MIN_FM_SAMPLES = 16
"""Fewest samples per trace the f_m estimators accept (not :data:`~inkdiag_core.kpis.MIN_KPI_SAMPLES`)."""
T0 = 1e-6
"""Internal time unit of the estimators, s."""

# ---------------------------------------------------------------------------
# results
# ---------------------------------------------------------------------------
@dataclass(frozen=True)
class FmEstimate:
    """Estimate of the multiplicative fault for one trace.

    Attributes
    ----------
    fm : float
        Steady-state estimate of f_m, 1/s (negative for a drying nozzle).
    trace : ndarray, shape (n_samples,)
        Per-sample estimate, 1/s; NaN where undefined (before the first full
        window, or where the regressor is too small). For ``"vp"``: the
        growing-window fit on samples [0, k] (NaN for the first two periods),
        ending at ``fm``; constant when ``vp_trace_points`` < 2.
    method : str
        The method that ran ("dt", "dt_exact", "ct", "vp" or "vp_cal").
    std : float
        Standard deviation of ``fm`` (1/s), NaN where the method gives none.
    ci : tuple of float
        95 % confidence interval (lower, upper), 1/s; NaNs where not available.
    d_mu : float
        Nozzle viscosity increase ``-fm / alpha`` (eq. 37), Pa s; NaN when the
        model was given as matrices (no physical parameters).
    viscosity : float
        Absolute nozzle viscosity ``mu_n + d_mu``, Pa s (NaN as above).
    x0 : ndarray, shape (3,)
        Initial state used (given) or estimated (``"vp"``), SI.
    offset : float
        Estimated DC offset of ``y`` (m^3/s), 0 for "dt"/"ct".
    at_bound : bool
        ``"vp"``/``"vp_cal"``: the fit ended at an edge of its f_m search interval (``fm_bounds``,
        by default ``(-15, 0.9) |A33|``: a viscosity 16x the ink's, or a thinner ink than any
        nozzle's), so ``fm`` is that edge, not an estimate: the trace is no nozzle the drying model
        reaches (an empty channel), or drier than the interval. False for the other methods.
    residual_rel : float
        ``"vp"``/``"vp_cal"``: the rms of what the fitted channel leaves of the trace over the trace's
        rms about its mean (see :class:`FmBatchEstimate`); NaN for the other methods.
    """

    fm: float
    trace: np.ndarray
    method: str
    std: float
    ci: tuple
    d_mu: float
    viscosity: float
    x0: np.ndarray
    offset: float = 0.0
    at_bound: bool = False
    residual_rel: float = math.nan


@dataclass(frozen=True)
class FmBatchEstimate:
    """Estimates for a batch of traces: the fields of :class:`FmEstimate` as arrays.

    ``fm, std, d_mu, viscosity, offset, at_bound`` have shape (n,), ``ci`` (n, 2),
    ``x0`` (n, 3), ``trace`` (n, n_samples). ``residual_rel`` (n,), dimensionless: for
    ``"vp"``/``"vp_cal"``, the rms of what the fitted channel (at the "vp" f_m) leaves of a
    trace over the trace's rms about its mean (noise alone gives the noise's share; a trace
    the drying model does not describe, e.g. an air bubble, 0.4-0.9); NaN for the other methods.
    """

    fm: np.ndarray
    trace: np.ndarray
    method: str
    std: np.ndarray
    ci: np.ndarray
    d_mu: np.ndarray
    viscosity: np.ndarray
    x0: np.ndarray
    offset: np.ndarray
    at_bound: np.ndarray = None  # (n,) bool; None: all False (set in __post_init__)
    residual_rel: np.ndarray = None  # (n,) float; None: all NaN (set in __post_init__)

    def __post_init__(self):
        if self.at_bound is None:
            object.__setattr__(self, "at_bound", np.zeros(np.shape(self.fm)[0], bool))
        if self.residual_rel is None:
            object.__setattr__(self, "residual_rel", np.full(np.shape(self.fm)[0], np.nan))

    def __len__(self) -> int:
        return int(self.fm.shape[0])

    def __getitem__(self, i) -> FmEstimate:
        return FmEstimate(
            fm=float(self.fm[i]), trace=self.trace[i], method=self.method,
            std=float(self.std[i]), ci=(float(self.ci[i, 0]), float(self.ci[i, 1])),
            d_mu=float(self.d_mu[i]), viscosity=float(self.viscosity[i]),
            x0=self.x0[i], offset=float(self.offset[i]), at_bound=bool(self.at_bound[i]),
            residual_rel=float(self.residual_rel[i]),
        )


# ---------------------------------------------------------------------------
# validation and internal scaling
# ---------------------------------------------------------------------------
def model_matrices(model):
    """(A, C, B_f, params or None) from an InkChannelModel or an (A, C, B_f) triple.

    Shapes (3, 3), (1, 3), (3, 1); ``params`` is the model's InkChannelParams, None
    for matrices."""
    if isinstance(model, InkChannelModel):
        A, C, B_f = model.observable(0.0)
        return A, C, B_f, model.params
    if isinstance(model, (tuple, list)) and len(model) == 3:
        A, C, B_f = (checks.finite_array(f"model {name}", m, shape=shape)
                     for name, m, shape in zip(("A", "C", "B_f"), model,
                                               ((3, 3), (1, 3), (3, 1))))
        return A, C, B_f, None
    raise checks.InputError(
        "model must be an InkChannelModel or a tuple (A, C, B_f) of shapes "
        f"(3, 3), (1, 3), (3, 1); got {type(model).__name__}"
    )


def check_x0(x0, n: int) -> np.ndarray:
    """Initial states (SI) as an array of shape (n, 3); ``x0`` of shape (3,) or (n, 3)."""
    X = np.asarray(x0, dtype=float)
    if X.shape == (3,):
        X = np.broadcast_to(X, (n, 3))
    if X.shape != (n, 3):
        raise checks.InputError(f"x0 must have shape (3,) or ({n}, 3), got {X.shape}")
    if not np.all(np.isfinite(X)):
        raise checks.InputError("x0 contains non-finite values")
    return np.array(X)


class Scaled:
    """The model in internal units: time in microseconds, balanced states.

    With ``S = diag(s)`` from balancing ``A * T0``, the scaled state is
    ``xs = S^-1 x / c`` for an output scale ``c`` (per trace), so that
    ``ys = y / c = Cs xs`` and ``xs' = (As + fs Gs e3^T) xs`` with
    ``fs = f_m * T0``.
    """

    def __init__(self, A, C, B_f, sample_rate_hz):
        At = A * T0
        _, (s, _) = sla.matrix_balance(At, permute=False, separate=True)
        self.s = s.astype(float)
        self.A = At * (1.0 / self.s)[:, None] * self.s[None, :]
        self.C = (C * self.s[None, :]).ravel()  # (3,)
        self.G = (B_f.ravel() / self.s) * self.s[2]  # fault direction for fs * xs3
        self.dt = 1.0 / (sample_rate_hz * T0)
        self.w0 = float(np.abs(np.linalg.eigvals(self.A).imag).max())  # healthy pair's omega

    def to_scaled_x(self, x0, c):
        return x0 / self.s[None, :] / c[:, None]

    def from_scaled_x(self, xs, c):
        return xs * self.s[None, :] * c[:, None]


@functools.lru_cache(maxsize=16)
def scaled_cached(key):
    A, C, B_f, fs = key[0], key[1], key[2], key[3]
    return Scaled(np.array(A).reshape(3, 3), np.array(C).reshape(1, 3),
                   np.array(B_f).reshape(3, 1), fs)


def scaled(A, C, B_f, fs) -> Scaled:
    key = (tuple(A.ravel()), tuple(C.ravel()), tuple(B_f.ravel()), float(fs))
    return scaled_cached(key)


# ---------------------------------------------------------------------------
# regression f_hat = e^+ r (eq. 6), windowed
# ---------------------------------------------------------------------------
def windowed_regression(e, r, window: int, steady_start: int, rel_floor: float):
    """Sliding-window and steady-state least squares of ``r = f e`` per trace.

    e, r : (n, m). Returns trace (n, m) with NaN where the window is incomplete
    or its regressor energy is below ``rel_floor`` times the largest one, and
    the steady-state estimate (n,) over samples ``>= steady_start``.
    """
    n, m = e.shape
    er = np.cumsum(e * r, axis=1)
    ee = np.cumsum(e * e, axis=1)
    W = int(min(max(window, 2), m))
    num = er[:, W - 1:].copy()
    den = ee[:, W - 1:].copy()
    num[:, 1:] -= er[:, : m - W]
    den[:, 1:] -= ee[:, : m - W]
    trace = np.full((n, m), np.nan)
    ok = den > rel_floor * den.max(axis=1, keepdims=True)  # window >= 1 period: never ~0
    with np.errstate(invalid="ignore", divide="ignore"):
        trace[:, W - 1:] = np.where(ok, num / np.where(ok, den, 1.0), np.nan)
    k0 = int(min(max(steady_start, 0), m - 1))
    ss_num = np.sum(e[:, k0:] * r[:, k0:], axis=1)
    ss_den = np.sum(e[:, k0:] ** 2, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        fm = np.where(ss_den > 0, ss_num / np.where(ss_den > 0, ss_den, 1.0), np.nan)
    return trace, fm


def period_samples(As, dt) -> int:
    lam = np.linalg.eigvals(As)
    w = np.abs(lam.imag).max()
    if w <= 0:
        return 32
    return max(4, int(round(2 * np.pi / w / dt)))


def prefilter(x, prefilter_hz, sample_rate_hz):
    """First-order pre-filter ``tau`` (eq. 5) with corner ``prefilter_hz`` along axis 1
    of x (n, m), discretised as ``(1 - a) / (1 - a z^-1)``, ``a = exp(-2 pi fc / fs)``."""
    a = float(np.exp(-2 * np.pi * prefilter_hz / sample_rate_hz))
    return scipy.signal.lfilter([1 - a], [1, -a], x, axis=1)


def default_bounds(A, B_f):
    """Default search interval of f_m, 1/s: ``(-15, 0.9) * |(A B_f)_3|`` (``|A33|`` for
    ``B_f = e3``) for A (3, 3) and B_f (3, 1) in SI."""
    a33 = abs(float((A @ B_f).ravel()[2])) if B_f.ravel()[2] != 0 else abs(A).max()
    return (-15.0 * a33, 0.9 * a33)
