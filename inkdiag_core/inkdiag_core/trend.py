"""Smoothed f_m trend of drying nozzles and their time to the deeply-dried level.

A drying nozzle's f_m drifts slowly (seconds to minutes) while each frame's
estimate is noisy. The trend is a two-state Kalman filter per nozzle (level
and rate, a constant-velocity model with white acceleration noise) fed with
each frame's estimate and its standard deviation.

Built the filterpy way (``filterpy.kalman.KalmanFilter``): :func:`predict` and
:func:`update` are separate pure functions, the update returns its gain,
residual and residual variance for inspection, and both work on a *batch* of
independent nozzles at once (state ``x`` (n, 2), covariance ``P`` (n, 2, 2),
vectorised numpy, no per-nozzle Python loop). :class:`FmTrendBank` keeps
those arrays per nozzle id and calls them once per frame; :class:`FmTrend` is
the same filter for one nozzle (a batch of one). Pure numpy; no ROS.

The deeply-dried level is the simulator's class definition: the lower edge
of the ``deeply_dried`` nozzle viscosity factor (``MECHANISMS``) times the
channel viscosity, converted with Appendix F (:func:`deeply_dried_fm`).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from . import checks
from .faults import MECHANISMS, FaultClass
from .model import InkChannelParams, viscosity_to_fm

__all__ = [
    "CLOCK_RESET_S",
    "FmTrend",
    "FmTrendBank",
    "KalmanUpdate",
    "deeply_dried_fm",
    "eta_deep",
    "measurement_variance",
    "predict",
    "update",
]

#: Floor of a measurement variance, (1/s)^2: keeps the update finite for fm = 0, fm_std = 0.
R_FLOOR = 1e-12

#: A frame this much (s) or more before the latest one :meth:`FmTrendBank.fold_newer` was given is a
#: restarted clock (a controller restarted, a recording replayed again), not a late frame: every nozzle's
#: trend restarts at its next frame. fe joins a range's frames in the order its drying lists come, so a late
#: frame is one that overtook another in transit: milliseconds to a few frames at several frames a second.
CLOCK_RESET_S = 10.0


def deeply_dried_fm(params: InkChannelParams | None = None) -> float:
    """f_m (1/s, negative) at which a nozzle of ``params`` becomes deeply dried.

    ``viscosity_to_fm(params, k_low * params.mu)`` with ``k_low`` the lower edge
    of the deeply-dried viscosity factor range.
    """
    p = InkChannelParams() if params is None else params
    k_low = MECHANISMS[FaultClass.DEEPLY_DRIED].low
    return float(viscosity_to_fm(p, k_low * p.mu))


# --------------------------------------------------------------------------- pure batch functions


def predict(x, P, dt, accel_std):
    """Kalman prediction of a batch of constant-velocity states over ``dt``.

    ``x' = F x``, ``P' = F P F^T + Q`` with ``F = [[1, dt], [0, 1]]`` and the
    white-acceleration process noise
    ``Q = accel_std^2 [[dt^3/3, dt^2/2], [dt^2/2, dt]]``. ``dt = 0`` leaves
    ``x`` and ``P`` unchanged.

    Parameters
    ----------
    x : array_like, shape (n, 2)
        States ``[fm, rate]``, 1/s and 1/s^2.
    P : array_like, shape (n, 2, 2)
        Their covariances.
    dt : float or array_like, shape (n,)
        Time steps, s (>= 0).
    accel_std : float or array_like, shape (n,)
        Standard deviation of the white acceleration noise, 1/s^3.

    Returns
    -------
    x : ndarray, shape (n, 2)
    P : ndarray, shape (n, 2, 2)
        New arrays; the inputs are not modified.
    """
    x = np.asarray(x, dtype=float)
    P = np.asarray(P, dtype=float)
    n = x.shape[0]
    dt = np.broadcast_to(np.asarray(dt, dtype=float), (n,))
    q = np.broadcast_to(np.asarray(accel_std, dtype=float) ** 2, (n,))
    F = np.zeros((n, 2, 2))
    F[:, 0, 0] = F[:, 1, 1] = 1.0
    F[:, 0, 1] = dt
    Q = np.empty((n, 2, 2))
    Q[:, 0, 0] = q * (dt**3 / 3)
    Q[:, 0, 1] = Q[:, 1, 0] = q * (dt**2 / 2)
    Q[:, 1, 1] = q * dt
    x_new = np.matmul(F, x[:, :, None])[:, :, 0]
    P_new = np.matmul(np.matmul(F, P), F.transpose(0, 2, 1)) + Q
    return x_new, P_new


class KalmanUpdate(NamedTuple):
    """Result of :func:`update` for a batch of n nozzles.

    Attributes
    ----------
    x : ndarray, shape (n, 2)
        Posterior states ``[fm, rate]``.
    P : ndarray, shape (n, 2, 2)
        Posterior covariances.
    K : ndarray, shape (n, 2)
        Kalman gains.
    y : ndarray, shape (n,)
        Residuals (innovations) ``z - fm_prior``, 1/s.
    S : ndarray, shape (n,)
        Residual variances ``P_prior[0, 0] + r``, (1/s)^2.
    """

    x: np.ndarray
    P: np.ndarray
    K: np.ndarray
    y: np.ndarray
    S: np.ndarray


def update(x, P, z, r) -> KalmanUpdate:
    """Kalman measurement update of a batch of states with a level measurement.

    The measurement matrix is ``H = [1, 0]`` (the level ``fm`` is measured):
    ``y = z - x[0]``, ``S = P[0, 0] + r``, ``K = P[:, 0] / S``,
    ``x' = x + K y``, ``P' = P - K P[0, :]`` (outer product).

    Parameters
    ----------
    x : array_like, shape (n, 2)
        Prior states ``[fm, rate]``, 1/s and 1/s^2.
    P : array_like, shape (n, 2, 2)
        Prior covariances.
    z : array_like, shape (n,)
        Measured f_m, 1/s (finite).
    r : array_like, shape (n,)
        Measurement variances, (1/s)^2 (> 0).

    Returns
    -------
    KalmanUpdate
        ``(x, P, K, y, S)``; new arrays, the inputs are not modified.
    """
    x = np.asarray(x, dtype=float)
    P = np.asarray(P, dtype=float)
    n = x.shape[0]
    z = np.broadcast_to(np.asarray(z, dtype=float), (n,))
    r = np.broadcast_to(np.asarray(r, dtype=float), (n,))
    S = P[:, 0, 0] + r
    K = P[:, :, 0] / S[:, None]
    y = z - x[:, 0]
    x_new = x + K * y[:, None]
    P_new = P - K[:, :, None] * P[:, None, 0, :]
    return KalmanUpdate(x_new, P_new, K, y, S)


def measurement_variance(fm, fm_std, rel_floor):
    """Variance of each estimate, (1/s)^2, shape (n,).

    ``fm_std**2 + (rel_floor * fm)**2`` (a non-finite ``fm_std`` counts as 0),
    floored at :data:`R_FLOOR`: a single-trace estimate's own ``fm_std`` leaves
    out model error, hence the relative floor.
    """
    fm = np.asarray(fm, dtype=float)
    fm_std = np.asarray(fm_std, dtype=float)
    s = np.where(np.isfinite(fm_std), fm_std, 0.0)
    return np.maximum(s**2 + (rel_floor * fm) ** 2, R_FLOOR)


def _prior(fm, r):
    """First-update state and covariance: level measured, rate unknown (wide prior)."""
    n = fm.shape[0]
    x = np.zeros((n, 2))
    x[:, 0] = fm
    P = np.zeros((n, 2, 2))
    P[:, 0, 0] = r
    P[:, 1, 1] = (np.abs(fm) + np.sqrt(r)) ** 2
    return x, P


def eta_deep(x, n_updates, fm_deep):
    """Time from the last update until the trend reaches ``fm_deep``, s, shape (n,).

    0 where the level is already at or below ``fm_deep``; NaN where unknown (no
    update yet; fewer than two updates and not there yet) or where the trend is
    not heading there (rate >= 0). Otherwise ``(fm_deep - fm) / rate``.

    Parameters
    ----------
    x : array_like, shape (n, 2)
    n_updates : array_like of int, shape (n,)
    fm_deep : float
        Deeply-dried level, 1/s.
    """
    x = np.asarray(x, dtype=float)
    n_updates = np.asarray(n_updates)
    fm, rate = x[:, 0], x[:, 1]
    there = (n_updates >= 1) & (fm <= fm_deep)
    heading = (n_updates >= 2) & (rate < 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        eta = np.where(heading, (fm_deep - fm) / np.where(heading, rate, 1.0), np.nan)
    return np.where(there, 0.0, eta)


def _fold(x, P, t_last, n_updates, t, fm, fm_std, accel_std, rel_floor):
    """One measurement per row folded into per-row filter arrays; returns new arrays.

    Rows with a non-finite ``fm`` are left as they are. A row's first update
    sets the prior (:func:`_prior`); later ones run :func:`predict` over
    ``t - t_last`` (0 when ``t`` is not after ``t_last``: only the level is
    updated) and :func:`update`. The last time becomes ``t`` unless ``t_last``
    is later.

    Returns
    -------
    x (n, 2), P (n, 2, 2), t_last (n,), n_updates (n,), K (n, 2), y (n,)
        ``K`` and ``y`` are the update's gain and residual (NaN for rows not updated
        and for first updates, which have none).
    """
    fm = np.asarray(fm, dtype=float)
    t = np.broadcast_to(np.asarray(t, dtype=float), fm.shape)
    x, P, t_last, n_updates = x.copy(), P.copy(), t_last.copy(), n_updates.copy()
    K = np.full((fm.size, 2), np.nan)
    y = np.full(fm.size, np.nan)
    ok = np.isfinite(fm)
    r = measurement_variance(fm[ok], np.asarray(fm_std, dtype=float)[ok], rel_floor)
    rows = np.flatnonzero(ok)
    first = n_updates[rows] == 0
    if first.any():
        f = rows[first]
        x[f], P[f] = _prior(fm[f], r[first])
    later = ~first
    if later.any():
        g = rows[later]
        dt = np.where(t[g] > t_last[g], t[g] - t_last[g], 0.0)
        xp, Pp = predict(x[g], P[g], dt, accel_std)
        u = update(xp, Pp, fm[g], r[later])
        x[g], P[g], K[g], y[g] = u.x, u.P, u.K, u.y
    t_last[rows] = np.where(t_last[rows] > t[rows], t_last[rows], t[rows])
    n_updates[rows] += 1
    return x, P, t_last, n_updates, K, y


def _frame_arrays(nozzles, fm, fm_std):
    """One frame's ``(nozzles int64, fm, fm_std)`` as flat arrays of one size (else InputError)."""
    nozzles = np.asarray(nozzles, dtype=np.int64).reshape(-1)
    fm = np.asarray(fm, dtype=float).reshape(-1)
    fm_std = np.asarray(fm_std, dtype=float).reshape(-1)
    if not (fm.size == fm_std.size == nozzles.size):
        raise checks.InputError(f"nozzles, fm and fm_std must have one entry each per nozzle, "
                                f"got sizes {nozzles.size}, {fm.size}, {fm_std.size}")
    return nozzles, fm, fm_std


def _check_params(accel_std, rel_floor):
    checks.positive_float("accel_std", accel_std)
    checks.nonnegative_float("rel_floor", rel_floor)


# --------------------------------------------------------------------------- stateful wrappers


class FmTrend:
    """Kalman filter of one nozzle's f_m: state ``[fm, rate]`` (1/s, 1/s^2).

    The batch functions on a batch of one (:class:`FmTrendBank` runs the same
    code on many nozzles).

    Parameters
    ----------
    accel_std : float
        Standard deviation of the white acceleration noise, 1/s^3 (how fast
        the rate may change). Default 5e3.
    rel_floor : float
        Relative floor of the measurement standard deviation: each
        measurement's variance is ``fm_std**2 + (rel_floor * fm)**2``, since a
        single-trace estimate's own ``fm_std`` leaves out model error. Default 0.05.
    fm_deep : float, optional
        Deeply-dried level, 1/s (default :func:`deeply_dried_fm`).

    Attributes
    ----------
    x : ndarray (2,)
        ``[fm, rate]`` after the last update.
    P : ndarray (2, 2)
        Its covariance.
    t : float
        Time of the last update, s (NaN before the first).
    n_updates : int
    K : ndarray (2,)
        Gain of the last update (NaN before the second update).
    y : float
        Residual of the last update, 1/s (NaN before the second update).
    """

    def __init__(self, accel_std: float = 5e3, rel_floor: float = 0.05, fm_deep: float | None = None):
        _check_params(accel_std, rel_floor)
        self.accel_std = float(accel_std)
        self.rel_floor = float(rel_floor)
        self.fm_deep = deeply_dried_fm() if fm_deep is None else float(fm_deep)
        self.x = np.zeros(2)
        self.P = np.diag([np.inf, np.inf])
        self.t = math.nan
        self.n_updates = 0
        self.K = np.full(2, np.nan)
        self.y = math.nan

    def update(self, t: float, fm: float, fm_std: float = 0.0) -> "FmTrend":
        """Fold in the estimate ``fm`` +- ``fm_std`` (1/s) measured at time ``t`` (s).

        A non-finite ``fm`` is ignored; a time not after the last one only
        updates the level (no prediction step).
        """
        fm = float(fm)
        if not math.isfinite(fm):
            return self
        x, P, tl, n, K, y = _fold(self.x[None], self.P[None], np.array([self.t]),
                                  np.array([self.n_updates]), float(t), np.array([fm]),
                                  np.array([float(fm_std)]), self.accel_std, self.rel_floor)
        self.x, self.P, self.t, self.n_updates = x[0], P[0], float(tl[0]), int(n[0])
        self.K, self.y = K[0], float(y[0])
        return self

    @property
    def fm(self) -> float:
        """Smoothed f_m, 1/s (NaN before the first update)."""
        return float(self.x[0]) if self.n_updates else math.nan

    @property
    def rate(self) -> float:
        """Smoothed d f_m / dt, 1/s^2 (NaN until two updates)."""
        return float(self.x[1]) if self.n_updates >= 2 else math.nan

    @property
    def fm_std(self) -> float:
        """Standard deviation of the smoothed f_m, 1/s (NaN before the first update)."""
        return float(math.sqrt(self.P[0, 0])) if self.n_updates else math.nan

    @property
    def eta_deep_s(self) -> float:
        """Time from the last update until the trend reaches ``fm_deep``, s.

        0 when already there; NaN when unknown (fewer than two updates) or when
        the trend is not heading there (rate >= 0, i.e. not drying further).
        """
        return float(eta_deep(self.x[None], np.array([self.n_updates]), self.fm_deep)[0])


class FmTrendBank:
    """The f_m trends of many nozzles, as arrays indexed by nozzle id.

    A nozzle gets a row on first sight and keeps it. :meth:`update` folds one
    frame's estimates in with one :func:`predict` and one :func:`update` call
    over all its nozzles (vectorised; a nozzle id repeated within one call is
    folded in once per occurrence, in order).

    Parameters
    ----------
    accel_std, rel_floor, fm_deep
        As for :class:`FmTrend`, shared by all nozzles.

    Attributes
    ----------
    ids : ndarray of int64, shape (m,)
        Nozzle ids seen so far, sorted.
    x : ndarray, shape (m, 2)
        Per nozzle ``[fm, rate]``, 1/s and 1/s^2 (zeros before its first update).
    P : ndarray, shape (m, 2, 2)
        Their covariances (infinite before the first update).
    t : ndarray, shape (m,)
        Time of each nozzle's last update, s (NaN before the first).
    n_updates : ndarray of int64, shape (m,)
    K : ndarray, shape (m, 2)
        Gain of each nozzle's last update (NaN if the last call did not update it
        or it was its first update).
    y : ndarray, shape (m,)
        Residual of each nozzle's last update, 1/s (NaN likewise).
    clock : float
        The latest frame time :meth:`fold_newer` was given, s (NaN before the first).
    epoch : int
        How often :meth:`fold_newer` found the clock restarted.
    nozzle_epoch : ndarray of int64, shape (m,)
        ``epoch`` at each nozzle's last update (-1 before the first).
    t_ended, ended_epoch : ndarray, shape (m,)
        Per nozzle, the time (s; NaN: none) and ``epoch`` of the news that last ended its trend
        (:meth:`forget`): :meth:`fold_newer` leaves out its entries at or before that time on that clock.
    misses, t_missed : ndarray, shape (m,)
        Per nozzle, :meth:`forget`'s news counted since its last update (``after`` > 1), and the time of
        the latest (s; NaN: none).
    """

    def __init__(self, accel_std: float = 5e3, rel_floor: float = 0.05, fm_deep: float | None = None):
        _check_params(accel_std, rel_floor)
        self.accel_std = float(accel_std)
        self.rel_floor = float(rel_floor)
        self.fm_deep = deeply_dried_fm() if fm_deep is None else float(fm_deep)
        self.trend_kwargs = {"accel_std": accel_std, "rel_floor": rel_floor, "fm_deep": fm_deep}
        self.ids = np.empty(0, dtype=np.int64)
        self.x = np.zeros((0, 2))
        self.P = np.zeros((0, 2, 2))
        self.t = np.empty(0)
        self.n_updates = np.empty(0, dtype=np.int64)
        self.K = np.empty((0, 2))
        self.y = np.empty(0)
        self.epoch = 0
        self.clock = math.nan
        self.nozzle_epoch = np.empty(0, dtype=np.int64)
        self.t_ended = np.empty(0)  # per nozzle: the time of the news that ended its trend (forget), s; NaN: none
        self.ended_epoch = np.empty(0, dtype=np.int64)  # per nozzle: ``epoch`` when that news came (-1: none)
        self.misses = np.empty(0, dtype=np.int64)  # per nozzle: forget's news since its last update (frames)
        self.t_missed = np.empty(0)  # per nozzle: the time of the latest of them, s (NaN: none)

    def __len__(self) -> int:
        return int(self.ids.size)

    def _rows(self, nozzles: np.ndarray) -> np.ndarray:
        """Rows of ``nozzles`` (adding new ids, sorted)."""
        rows = np.searchsorted(self.ids, nozzles)
        if rows.size == 0 or (rows.max() < self.ids.size and np.array_equal(self.ids[rows], nozzles)):
            return rows
        new = np.setdiff1d(nozzles, self.ids)
        if new.size:
            ids = np.union1d(self.ids, new)
            old = np.searchsorted(ids, self.ids)
            m = ids.size

            def grow(a, fill):
                out = np.full((m,) + a.shape[1:], fill, dtype=a.dtype)
                out[old] = a
                return out

            self.x, self.P, self.t = grow(self.x, 0.0), grow(self.P, 0.0), grow(self.t, np.nan)
            self.n_updates, self.K, self.y = grow(self.n_updates, 0), grow(self.K, np.nan), grow(self.y, np.nan)
            self.nozzle_epoch = grow(self.nozzle_epoch, -1)
            self.t_ended, self.ended_epoch = grow(self.t_ended, np.nan), grow(self.ended_epoch, -1)
            self.misses, self.t_missed = grow(self.misses, 0), grow(self.t_missed, np.nan)
            self.ids = ids
            self._clear(np.searchsorted(ids, new))
        return np.searchsorted(self.ids, nozzles)

    def _known_rows(self, nozzles) -> np.ndarray:
        """Rows of those of ``nozzles`` (ids) the bank has (unlike :meth:`_rows`, adding none)."""
        ids = np.asarray(nozzles, dtype=np.int64).reshape(-1)
        rows = np.searchsorted(self.ids, ids)
        known = rows < self.ids.size
        return rows[known][self.ids[rows[known]] == ids[known]]

    def _clear(self, rows) -> None:
        """Rows ``rows`` as a nozzle before its first update (a new one, or one whose trend restarts)."""
        self.x[rows], self.P[rows], self.t[rows], self.n_updates[rows] = 0.0, 0.0, np.nan, 0
        self.misses[rows], self.t_missed[rows] = 0, np.nan
        self.P[rows, 0, 0] = self.P[rows, 1, 1] = np.inf
        self.K[rows], self.y[rows] = np.nan, np.nan

    def forget(self, nozzles, before: float = math.inf, *, after: int = 1) -> int:
        """Restart the trends of ``nozzles`` (ids; those without a trend are ignored): their next estimate
        starts a new one, as a nozzle's first does (a nozzle that recovered, then dries again).

        Parameters
        ----------
        nozzles : array_like of int
        before : float
            Only trends last updated before this time, s (a frame's stamp: news of a recovery older than
            a trend's last estimate, a late frame's, does not end it). A trend it ends keeps it as
            :attr:`t_ended` (its last update's time when infinite): :meth:`fold_newer` then leaves out
            the nozzle's entries at or before it on the same clock.
        after : int
            Restart a trend at its ``after``-th such news since its last update or :meth:`heard` (each
            at a later, finite ``before`` than the one before it: a frame given twice counts once); the
            news before it are counted, the trend kept. 1: at once.

        Returns
        -------
        int
            How many trends were restarted (nozzles with at least one update).
        """
        rows = self._known_rows(nozzles)
        rows = rows[(self.n_updates[rows] > 0) & (self.t[rows] < before)]
        if after > 1 and not math.isfinite(before):
            raise ValueError(f"forget(after={after}) needs a finite time 'before' to tell its news apart, got {before}")
        if after > 1:  # count the news; a time not after the latest one counted is the same news again
            new = rows[~(self.t_missed[rows] >= before)]
            self.misses[new] += 1
            self.t_missed[new] = before
            rows = rows[self.misses[rows] >= after]
        # a frame older than the news that ended the trend is stale for fold_newer (a late frame: no restart)
        self.t_ended[rows] = before if math.isfinite(before) else self.t[rows]
        self.ended_epoch[rows] = self.epoch
        self._clear(rows)
        return int(rows.size)

    def heard(self, nozzles, t: float) -> None:
        """News at time ``t`` (s) that ``nozzles`` are still drying (a list names them, estimated or not): the
        count of :meth:`forget`'s news against them starts again, unless that news is newer than ``t``."""
        rows = self._known_rows(nozzles)
        rows = rows[~(self.t_missed[rows] > t)]  # NaN (none, or no time): reset
        self.misses[rows], self.t_missed[rows] = 0, np.nan

    def update(self, t: float, nozzles, fm, fm_std):
        """Fold one frame's estimates in.

        Parameters
        ----------
        t : float
            Frame time, s.
        nozzles : array_like of int, shape (n,)
        fm, fm_std : array_like, shape (n,)
            Estimates and their standard deviations, 1/s. A non-finite ``fm`` is
            ignored (the nozzle's trend is returned as it was).

        Returns
        -------
        fm_trend, rate, eta_deep_s : ndarray, shape (n,)
            Smoothed f_m (1/s), its rate (1/s^2, NaN until two updates) and the
            time to the deeply-dried level (s, see :func:`eta_deep`).
        """
        nozzles, fm, fm_std = _frame_arrays(nozzles, fm, fm_std)
        rows = self._rows(nozzles)
        self.K[rows], self.y[rows] = np.nan, np.nan
        out = np.full((3, rows.size), np.nan)
        # occurrence rank of each entry among equal ids: rank r is folded in at pass r
        order = np.argsort(rows, kind="stable")
        sr = rows[order]
        repeated = sr[1:] == sr[:-1]
        passes = [np.arange(rows.size)]
        if repeated.any():
            start = np.r_[0, np.flatnonzero(~repeated) + 1]
            rank = np.empty(rows.size, dtype=np.int64)
            rank[order] = np.arange(rows.size) - np.repeat(start, np.diff(np.r_[start, rows.size]))
            passes = [np.flatnonzero(rank == r) for r in range(int(rank.max()) + 1)]
        for sel in passes:  # one pass unless ids repeat
            g = rows[sel]
            x, P, tl, n, K, y = _fold(self.x[g], self.P[g], self.t[g], self.n_updates[g], t,
                                      fm[sel], fm_std[sel], self.accel_std, self.rel_floor)
            self.x[g], self.P[g], self.t[g], self.n_updates[g] = x, P, tl, n
            upd = np.isfinite(fm[sel])
            self.K[g[upd]], self.y[g[upd]] = K[upd], y[upd]
            self.nozzle_epoch[g[upd]] = self.epoch
            self.misses[g[upd]], self.t_missed[g[upd]] = 0, np.nan  # news of a recovery before it: void
            out[0, sel] = np.where(n >= 1, x[:, 0], np.nan)
            out[1, sel] = np.where(n >= 2, x[:, 1], np.nan)
            out[2, sel] = eta_deep(x, n, self.fm_deep)
        return out[0], out[1], out[2]

    def fold_newer(self, t: float, nozzles, fm, fm_std, *, reset_after_s: float = CLOCK_RESET_S):
        """Fold in one frame's estimates where they are new: each nozzle once, and only after its last update.

        :meth:`update` folds every entry in (a repeated id once per occurrence; a time not after a
        nozzle's last one as a level update). A monitor must not: a frame sent twice, or arriving
        after a later one, would count as a new measurement. Here a nozzle's first finite entry is
        folded in if ``t`` is after its last update; an entry at or before it is left out (stale), and
        so is one at or before the news that ended its trend (:meth:`forget`'s ``before``: a late frame
        of a nozzle that recovered does not start a new trend).
        A ``t`` ``reset_after_s`` or more before the latest frame given here restarts the clock (a
        controller restarted, a recording replayed again): from then on each nozzle's trend
        restarts (its old state dropped) at its first entry on the new clock, whatever its last
        update's time, so no trend spans two clocks.

        Parameters
        ----------
        t : float
            Frame time, s (finite).
        nozzles : array_like of int, shape (n,)
        fm, fm_std : array_like, shape (n,)
            As :meth:`update` (a non-finite ``fm`` is not folded).
        reset_after_s : float
            s, > 0.

        Returns
        -------
        fm_trend, rate, eta_deep_s : ndarray, shape (n,)
            As :meth:`update` for the entries folded in; NaN for the others.
        folded, restarted : ndarray of bool, shape (n,)
            The entries folded in; those of them that restarted their nozzle's trend.
        """
        ids, fm, fm_std = _frame_arrays(nozzles, fm, fm_std)
        if not (math.isfinite(t) and reset_after_s > 0):
            raise checks.InputError(f"t must be finite and reset_after_s > 0, got {t!r}, {reset_after_s!r}")
        if self.clock - t >= reset_after_s:  # NaN (nothing folded yet): False
            self.epoch += 1
            self.clock = t
        self.clock = t if not self.clock >= t else self.clock
        fin = np.flatnonzero(np.isfinite(fm))
        keep = np.zeros(ids.size, dtype=bool)
        keep[fin[np.unique(ids[fin], return_index=True)[1]]] = True  # each nozzle's first finite entry
        at = np.searchsorted(self.ids, ids)
        seen = at < self.ids.size
        seen[seen] = self.ids[at[seen]] == ids[seen]
        seen[seen] = self.n_updates[at[seen]] > 0
        other_clock = np.zeros(ids.size, dtype=bool)
        other_clock[seen] = self.nozzle_epoch[at[seen]] != self.epoch
        older = np.zeros(ids.size, dtype=bool)
        older[seen] = self.t[at[seen]] >= t
        ended = (at < self.ids.size) & ~seen  # known, no trend now: ended by forget on this clock, after t?
        ended[ended] = self.ids[at[ended]] == ids[ended]
        ended[ended] = (self.t_ended[at[ended]] >= t) & (self.ended_epoch[at[ended]] == self.epoch)
        older |= ended
        restart = keep & other_clock
        keep &= restart | ~older
        if restart.any():
            self._clear(at[restart])
        out = np.full((3, ids.size), np.nan)
        if keep.any():
            out[:, keep] = self.update(t, ids[keep], fm[keep], fm_std[keep])
        return out[0], out[1], out[2], keep, restart

    def trend(self, nozzle: int) -> FmTrend:
        """A copy of one nozzle's filter as an :class:`FmTrend` (KeyError if never seen)."""
        i = int(np.searchsorted(self.ids, nozzle))
        if i >= self.ids.size or self.ids[i] != nozzle:
            raise KeyError(nozzle)
        tr = FmTrend(self.accel_std, self.rel_floor, self.fm_deep)
        tr.x, tr.P, tr.t, tr.n_updates = self.x[i].copy(), self.P[i].copy(), float(self.t[i]), int(self.n_updates[i])
        tr.K, tr.y = self.K[i].copy(), float(self.y[i])
        return tr

    @property
    def trends(self) -> dict:
        """``{nozzle id: FmTrend}`` copies of every nozzle's filter (read-only snapshot)."""
        return {int(nz): self.trend(int(nz)) for nz in self.ids}
