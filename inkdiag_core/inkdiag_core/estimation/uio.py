"""The thesis's UIO-based f_m estimators ("dt", "ct") and ours, "dt_exact".

``"dt"`` (eq. 22-25): the DT UIO on ``A_H^DT = expm(A_H dt)`` and the Appendix-E fault
term; ``"dt_exact"``: the same regression with the exact discretisation linearised in
f_m (Gauss-Newton re-linearisations); ``"ct"`` (eq. 26): the continuous-time UIO with
the pre-filter ``tau`` making ``tau[y']`` proper. All need the initial state ``x0``.
The package docstring (:mod:`inkdiag_core.estimation`) describes each method; the
functions here work on scaled traces (:class:`~.base.Scaled`) and are called by
:func:`~inkdiag_core.estimation.estimate_fm_batch`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla

from ..checks import InputError
from ..observer import design_uio
from .base import T0, Scaled, period_samples, prefilter, windowed_regression

__all__ = [
    "CtOptions",
    "DtExactOptions",
    "DtOptions",
    "ct_batch",
    "cubic_hold",
    "dt_batch",
    "dt_exact_batch",
]


@dataclass(frozen=True)
class DtOptions:
    """Options of ``"dt"`` (the thesis's discrete-time estimator).

    Parameters
    ----------
    exact_T : bool
        UIO injection ``T = (I - HC) A H`` (eq. 19, default) or ``T = A H`` (eq. 20).
    prefilter_hz : float, optional
        Corner of the first-order pre-filter ``tau`` (eq. 5), Hz; default none.
    window : int, optional
        Samples in the sliding regression window of ``.trace`` (default: one period of
        the healthy mode).
    steady_frac : float
        ``.fm`` is the regression over samples ``>= steady_frac * n_samples``.
    """

    exact_T: bool = True
    prefilter_hz: float | None = None
    window: int | None = None
    steady_frac: float = 0.2


@dataclass(frozen=True)
class DtExactOptions(DtOptions):
    """Options of ``"dt_exact"``: those of :class:`DtOptions` and

    Parameters
    ----------
    n_iter : int
        Re-linearisations after the first pass around f = 0.
    sensitivity : bool
        The regressor includes the UIO state's sensitivity to f (default); False gives
        the bare ``C D x_hat`` regressor (slower, linear convergence).
    fm_bounds : (float, float), optional
        The linearisation points are clipped to this interval, 1/s (default
        ``(-15, 0.9) * |A33|``).
    """

    n_iter: int = 3
    sensitivity: bool = True
    fm_bounds: tuple | None = None


@dataclass(frozen=True)
class CtOptions:
    """Options of ``"ct"`` (the thesis's continuous-time estimator).

    Parameters
    ----------
    exact_T : bool
        As in :class:`DtOptions`.
    prefilter_hz : float
        Corner of ``tau``, Hz; required (> 0), default 1 MHz.
    window : int, optional
        As in :class:`DtOptions`.
    steady_frac : float
        As in :class:`DtOptions`.
    """

    exact_T: bool = True
    prefilter_hz: float | None = 1e6
    window: int | None = None
    steady_frac: float = 0.2


# ---------------------------------------------------------------------------
# the thesis's DT approach (eq. 22-25)
# ---------------------------------------------------------------------------
def dt_batch(sc: Scaled, Ys, Xs0, *, exact_T=True, prefilter_hz=None, sample_rate_hz,
             window=None, steady_frac=0.2, rel_floor=1e-12):
    """"dt" on scaled traces Ys (n, N) from scaled initial states Xs0 (n, 3).

    Returns the steady-state estimate (n,) and the per-sample trace (n, N), both
    scaled (1/us); the trace is NaN at sample 0 and where the window is incomplete."""
    n, N = Ys.shape
    Ad = sla.expm(sc.A * sc.dt)  # A_H^DT (eq. 25)
    uio = design_uio(Ad, sc.C[None, :], sc.G[:, None], dt=sc.dt)
    H = uio.H[:, 0]
    F = uio.F
    T = (uio.T if exact_T else uio.T_approx)[:, 0]
    z = Xs0 - Ys[:, :1] * H[None, :]
    Z = np.empty((N, n, 3))
    FT = F.T.copy()
    YT = np.ascontiguousarray(Ys.T)[:, :, None]
    for k in range(N):  # vectorised over traces; 3x3 per step
        Z[k] = z
        z = z @ FT + YT[k] * T
    CAd = sc.C @ Ad
    # x_hat = z + H y;  r(k) = y(k+1) - C A_H^DT x_hat(k);  e(k) = C B_f E(x3) dt
    r = Ys[:, 1:] - (Z[:-1] @ CAd).T - (CAd @ H) * Ys[:, :-1]
    e = (sc.C @ sc.G) * (Z[:-1, :, 2].T + H[2] * Ys[:, :-1]) * sc.dt
    if prefilter_hz:
        r = prefilter(r, prefilter_hz, sample_rate_hz)
        e = prefilter(e, prefilter_hz, sample_rate_hz)
    W = window or period_samples(sc.A, sc.dt)
    trace, fm = windowed_regression(e, r, W, int(steady_frac * N), rel_floor)
    full = np.full((n, N), np.nan)
    full[:, 1:] = trace  # the estimate from r(k) is available at sample k+1
    return fm, full


# ---------------------------------------------------------------------------
# ours: the DT approach with the exact discretisation, linearised in f_m
# ---------------------------------------------------------------------------
def _expm_frechet_batch(sc: Scaled, f):
    """``A_d(f) = expm((As + f G e3^T) dt)`` and its derivative ``D(f) = dA_d/df``
    for scaled faults f (n,): the Frechet derivative ``L(M, G e3^T dt)`` of expm at
    ``M = (As + f G e3^T) dt``, from the block identity
    ``expm([[M, E], [0, M]]) = [[expm(M), L(M, E)], [0, expm(M)]]`` (stacked, one
    6x6 expm per trace). Returns (n, 3, 3) each."""
    n = f.shape[0]
    M = np.broadcast_to(sc.A * sc.dt, (n, 3, 3)).copy()
    M[:, :, 2] += (f * sc.dt)[:, None] * sc.G[None, :]
    big = np.zeros((n, 6, 6))
    big[:, :3, :3] = M
    big[:, 3:, 3:] = M
    big[:, :3, 5] = sc.G * sc.dt  # E = G e3^T dt
    X = sla.expm(big)
    return X[:, :3, :3], X[:, :3, 3:]


def _dt_exact_pass(sc: Scaled, Ys, Xs0, f0, *, exact_T, prefilter_hz, sample_rate_hz, W,
                   steady_start, rel_floor, sensitivity=True):
    """One pass of the linearised exact-DT regression around the scaled faults f0 (n,).

    Model: ``x(k+1) = A_d(f) x(k) ~ A_d(f0) x(k) + (f - f0) D(f0) x(k)``. The DT UIO
    (eq. 14-19) is built on ``A_d(f0)`` per trace and started from x0; then
    ``r(k) = y(k+1) - C A_d(f0) x_hat(k)``, ``e(k) = C D(f0) x_hat(k)`` and
    ``f - f0 = e^+ r`` (eq. 6), windowed as for "dt". Returns (fm, trace) scaled."""
    n, N = Ys.shape
    Ad, D = _expm_frechet_batch(sc, f0)
    H = sc.G / float(sc.C @ sc.G)  # H = B_f (C B_f)^+, independent of A
    IHC = np.eye(3) - np.outer(H, sc.C)
    F = IHC @ Ad  # (n, 3, 3)
    T = F @ H if exact_T else Ad @ H  # (n, 3)
    dF = IHC @ D  # dF/df
    dT = dF @ H if exact_T else D @ H
    z = Xs0 - Ys[:, :1] * H[None, :]
    sz = np.zeros_like(z)  # dz/df; x_hat(0) = x0 does not depend on f
    Z = np.empty((N, n, 3))
    SZ = np.empty((N, n, 3))
    for k in range(N):  # vectorised over traces; 3x3 per step
        Z[k] = z
        SZ[k] = sz
        yk = Ys[:, k:k + 1]
        if sensitivity:
            sz = np.einsum("nij,nj->ni", F, sz) + np.einsum("nij,nj->ni", dF, z) + yk * dT
        z = np.einsum("nij,nj->ni", F, z) + yk * T
    Xh = Z[:-1] + Ys[:, :-1].T[:, :, None] * H  # x_hat(k), (N-1, n, 3)
    CAd = np.einsum("i,nij->nj", sc.C, Ad)
    CD = np.einsum("i,nij->nj", sc.C, D)
    r = Ys[:, 1:] - np.einsum("knj,nj->nk", Xh, CAd)
    e = np.einsum("knj,nj->nk", Xh, CD)
    if sensitivity:  # + C A_d(f0) dx_hat/df: the UIO does not decouple D's O(dt^2) part
        e = e + np.einsum("knj,nj->nk", SZ[:-1], CAd)
    if prefilter_hz:
        r = prefilter(r, prefilter_hz, sample_rate_hz)
        e = prefilter(e, prefilter_hz, sample_rate_hz)
    trace, dfm = windowed_regression(e, r, W, steady_start, rel_floor)
    full = np.full((n, N), np.nan)
    full[:, 1:] = f0[:, None] + trace
    return f0 + dfm, full


def dt_exact_batch(sc: Scaled, Ys, Xs0, *, exact_T=True, prefilter_hz=None, sample_rate_hz,
                   window=None, steady_frac=0.2, rel_floor=1e-12, n_iter=3, sensitivity=True,
                   bounds_s=(-np.inf, np.inf)):
    """"dt_exact": a pass around f = 0, then ``n_iter`` re-linearisations around the
    current steady-state estimate (removes the O(f_m^2) bias of the first pass). Each
    linearisation point is clipped to ``bounds_s`` (scaled f), so a wild step on noisy or
    mismatched data does not move the next expm far outside the model's range."""
    n, N = Ys.shape
    W = window or period_samples(sc.A, sc.dt)
    f = np.zeros(n)
    for _ in range(int(n_iter) + 1):
        f_new, trace = _dt_exact_pass(sc, Ys, Xs0, f, exact_T=exact_T,
                                      prefilter_hz=prefilter_hz, sample_rate_hz=sample_rate_hz,
                                      W=W, steady_start=int(steady_frac * N),
                                      rel_floor=rel_floor, sensitivity=sensitivity)
        # a NaN (no regressor energy) keeps the last f
        f = np.clip(np.where(np.isfinite(f_new), f_new, f), *bounds_s)
    return f_new, trace


# ---------------------------------------------------------------------------
# the thesis's CT approach (eq. 26)
# ---------------------------------------------------------------------------
def cubic_hold(M, Nv, dt):
    """Exact discretisation of ``w' = M w + Nv u`` for a cubic input between samples.

    Between samples k and k+1 the input is the cubic through 4 neighbouring
    samples (j0 .. j0+3). Returns ``Phi`` (m, m) and ``Gam`` (3, 4, m): for the
    interval starting at local node ``i = k - j0`` (0, 1 or 2),
    ``w(k+1) = Phi w(k) + y[j0:j0+4] @ Gam[i]``.
    """
    m = M.shape[0]
    Big = np.zeros((m + 4, m + 4))
    Big[:m, :m] = M * dt
    Big[:m, m] = Nv * dt
    for j in range(3):  # chain of the derivatives of the input (in samples)
        Big[m + j, m + j + 1] = 1.0
    E = sla.expm(Big)
    Phi = E[:m, :m]
    Gm = E[:m, m:]  # response to the input and its 3 derivatives at the interval start
    Gam = np.empty((3, 4, m))
    nodes = np.arange(4.0)
    for i in range(3):
        tau = nodes - i  # node positions relative to the interval start, in samples
        V = np.vander(tau, 4, increasing=True)  # u(tau) = sum a_j tau^j
        Lc = np.linalg.inv(V)  # a = Lc @ y_nodes
        D = Lc * np.array([1.0, 1.0, 2.0, 6.0])[:, None]  # derivatives at tau = 0
        Gam[i] = (Gm @ D).T
    return Phi, Gam


def ct_batch(sc: Scaled, Ys, Xs0, *, exact_T=True, prefilter_hz=1e6, window=None,
             steady_frac=0.2, rel_floor=1e-12):
    """"ct" on scaled traces Ys (n, N) from scaled initial states Xs0 (n, 3): the
    continuous-time UIO driven by the cubic-hold input, ``tau`` with corner
    ``prefilter_hz`` (Hz, required). Returns (fm (n,), trace (n, N)), scaled."""
    n, N = Ys.shape
    uio = design_uio(sc.A, sc.C[None, :], sc.G[:, None])
    H = uio.H[:, 0]
    F = uio.F
    T = (uio.T if exact_T else uio.T_approx)[:, 0]
    if not prefilter_hz:
        raise InputError("method 'ct' needs a pre-filter (prefilter_hz > 0): tau makes tau[y'] proper")
    Tf = 1.0 / (2 * np.pi * prefilter_hz * T0)  # in microseconds
    CA = sc.C @ sc.A
    # augmented state w = [z (3), q = tau[y], p = tau[C A x_hat], s = tau[x_hat3]], input y
    M = np.zeros((6, 6))
    Nv = np.zeros(6)
    M[:3, :3] = F
    Nv[:3] = T
    M[3, 3] = -1 / Tf
    Nv[3] = 1 / Tf
    M[4, :3] = CA / Tf
    M[4, 4] = -1 / Tf
    Nv[4] = (CA @ H) / Tf
    M[5, 2] = 1 / Tf
    M[5, 5] = -1 / Tf
    Nv[5] = H[2] / Tf
    Phi, Gam = cubic_hold(M, Nv, sc.dt)
    w = np.zeros((n, 6))
    w[:, :3] = Xs0 - Ys[:, :1] * H[None, :]
    w[:, 3] = Ys[:, 0]
    W6 = np.empty((n, N, 6))
    PhiT = Phi.T.copy()
    for k in range(N):
        W6[:, k, :] = w
        if k + 1 < N:
            # the input between samples k and k+1 is the cubic through 4 neighbours
            j0 = min(max(k - 1, 0), N - 4)
            w = w @ PhiT + Ys[:, j0:j0 + 4] @ Gam[k - j0]
    r = (Ys - W6[:, :, 3]) / Tf - W6[:, :, 4]  # tau[y'] - tau[C A x_hat]
    e = (sc.C @ sc.G) * W6[:, :, 5]  # tau[C B_f x_hat3]
    Wn = window or period_samples(sc.A, sc.dt)
    trace, fm = windowed_regression(e, r, Wn, int(steady_frac * N), rel_floor)
    return fm, trace
