"""Smoothed f_m trend of one drying nozzle and its time to the deeply-dried level.

A drying nozzle's f_m drifts slowly (seconds to minutes) while each frame's
estimate is noisy. :class:`FmTrend` is a two-state Kalman filter (level and
rate, a constant-velocity model with white acceleration noise) fed with each
frame's estimate and its standard deviation, filterpy-style: ``update()`` per
measurement, results as attributes. Pure numpy; no ROS.

The deeply-dried level is the simulator's class definition: the lower edge
of the ``deeply_dried`` nozzle viscosity factor (``MECHANISMS``) times the
channel viscosity, converted with Appendix F (:func:`deeply_dried_fm`).
"""

from __future__ import annotations

import math

import numpy as np

from .faults import MECHANISMS, FaultClass
from .model import InkChannelParams, viscosity_to_fm

__all__ = ["FmTrend", "FmTrendBank", "deeply_dried_fm"]


def deeply_dried_fm(params: InkChannelParams | None = None) -> float:
    """f_m (1/s, negative) at which a nozzle of ``params`` becomes deeply dried.

    ``viscosity_to_fm(params, k_low * params.mu)`` with ``k_low`` the lower edge
    of the deeply-dried viscosity factor range.
    """
    p = InkChannelParams() if params is None else params
    k_low = MECHANISMS[FaultClass.DEEPLY_DRIED].low
    return float(viscosity_to_fm(p, k_low * p.mu))


class FmTrend:
    """Kalman filter of one nozzle's f_m: state ``[fm, rate]`` (1/s, 1/s^2).

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
    """

    def __init__(self, accel_std: float = 5e3, rel_floor: float = 0.05, fm_deep: float | None = None):
        if not (accel_std > 0 and rel_floor >= 0):
            raise ValueError(f"accel_std must be > 0 and rel_floor >= 0, got {accel_std}, {rel_floor}")
        self.accel_std = float(accel_std)
        self.rel_floor = float(rel_floor)
        self.fm_deep = deeply_dried_fm() if fm_deep is None else float(fm_deep)
        self.x = np.zeros(2)
        self.P = np.diag([np.inf, np.inf])
        self.t = math.nan
        self.n_updates = 0

    def update(self, t: float, fm: float, fm_std: float = 0.0) -> "FmTrend":
        """Fold in the estimate ``fm`` +- ``fm_std`` (1/s) measured at time ``t`` (s).

        A non-finite ``fm`` is ignored; a time not after the last one only
        updates the level (no prediction step).
        """
        t, fm = float(t), float(fm)
        if not math.isfinite(fm):
            return self
        r = (fm_std if math.isfinite(fm_std) else 0.0) ** 2 + (self.rel_floor * fm) ** 2
        r = max(r, 1e-12)
        if self.n_updates == 0:
            self.x = np.array([fm, 0.0])
            self.P = np.diag([r, (abs(fm) + math.sqrt(r)) ** 2])  # rate unknown: wide prior
        else:
            dt = t - self.t if t > self.t else 0.0
            F = np.array([[1.0, dt], [0.0, 1.0]])
            q = self.accel_std**2
            Q = q * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
            self.x = F @ self.x
            self.P = F @ self.P @ F.T + Q
            S = self.P[0, 0] + r
            K = self.P[:, 0] / S
            self.x = self.x + K * (fm - self.x[0])
            self.P = self.P - np.outer(K, self.P[0, :])
        self.t = max(t, self.t) if self.n_updates else t
        self.n_updates += 1
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
        return float(math.sqrt(self.P[0, 0])) if self.n_updates else math.nan

    @property
    def eta_deep_s(self) -> float:
        """Time from the last update until the trend reaches ``fm_deep``, s.

        0 when already there; NaN when unknown (fewer than two updates) or when
        the trend is not heading there (rate >= 0, i.e. not drying further).
        """
        if self.n_updates == 0:
            return math.nan
        if self.x[0] <= self.fm_deep:
            return 0.0
        if self.n_updates < 2 or not self.x[1] < 0:
            return math.nan
        return float((self.fm_deep - self.x[0]) / self.x[1])


class FmTrendBank:
    """One :class:`FmTrend` per nozzle id, created on first sight and kept.

    Parameters are passed to each new :class:`FmTrend`. A loop over the
    given nozzles: meant for the few drying nozzles of a frame, not a head.

    Attributes
    ----------
    trends : dict of int -> FmTrend
    """

    def __init__(self, **trend_kwargs):
        FmTrend(**trend_kwargs)  # validate once, now
        self.trend_kwargs = trend_kwargs
        self.trends = {}

    def update(self, t: float, nozzles, fm, fm_std):
        """Fold one frame's estimates in; return ``(fm_trend, rate, eta_deep_s)`` arrays (n,)."""
        nozzles = np.asarray(nozzles, dtype=np.int64)
        fm = np.asarray(fm, dtype=float)
        fm_std = np.asarray(fm_std, dtype=float)
        out = np.full((3, nozzles.size), np.nan)
        for i, nz in enumerate(nozzles.tolist()):
            tr = self.trends.get(nz)
            if tr is None:
                tr = self.trends[nz] = FmTrend(**self.trend_kwargs)
            tr.update(t, fm[i], fm_std[i])
            out[:, i] = tr.fm, tr.rate, tr.eta_deep_s
        return out[0], out[1], out[2]
