"""Model-based residual filters (thesis sections 3.1, 3.3 and 3.4.1).

Residual generation on the healthy ink-channel model, the thesis's way: the
channel is modelled as autonomous (no input is measured while the piezo
senses), its initial state is reconstructed from the KPIs of healthy
reference traces and averaged, and an observer of the healthy model turns a
trace ``y`` into the residual ``r = y - y_hat``. A healthy trace leaves a
residual that dies out with the observer's error dynamics; a faulty one
leaves its mismatch with the healthy model.

Original filter (``kind="original"``, features KPI_R)
    Discrete-time Luenberger observer of the healthy observable model (eq. 12,
    exact ZOH), output injection ``L`` placed so that the error poles are the
    model's own poles with their decay rates tripled::

        x_hat[k+1] = A_d x_hat[k] + L (y[k] - C x_hat[k]),   r[k] = y[k] - C x_hat[k]

Modified filter (``kind="modified"``, features KPI_R_Modified)
    The thesis adds lightly damped pole pairs at three frequency bands so that
    the residual keeps their content: (1) empty channel 1 (2124.4 kHz), (2) the
    mean of the mature and intermediate air bubbles (344.1 kHz), (3) the mean of
    partially blocked, slightly and intermediately dried (212.8 kHz). Poles
    placed on the imaginary axis alone are not stable; the thesis closes a PI
    loop around them and checks margins on a Bode plot. Here the observer's
    output injection becomes PI (an integrator on the output error, which
    also rejects each channel's sensor offset), the PI gains are chosen by loop
    shaping for a phase margin >= 45 deg, and the residual passes through three
    resonators ``1 + sum_i g_i H_i(z)`` with poles at the band frequencies and
    damping ratio 0.05 (lightly damped, strictly inside the unit circle).

Both filters are LTI from ``y`` to ``r``; the common reference initial state
adds one fixed zero-input response. So a whole batch is one
``scipy.signal.lfilter`` call along the sample axis plus a broadcast
subtraction: no loop over traces.

The thesis does not publish its filters' coefficients; these designs follow
its description and are reported (poles, margins, Bode plots) by
``scripts/report fdi``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.signal
from sklearn.base import BaseEstimator, TransformerMixin
from sklearn.utils.validation import check_is_fitted, validate_data

from .faults import HEALTHY_VALUES
from .kpis import MIN_KPI_SAMPLES, extract_kpis, reconstruct
from .model import InkChannelModel, InkChannelParams

__all__ = [
    "MODIFIED_BANDS_HZ",
    "FilterDesign",
    "head_bands_hz",
    "design_residual_filter",
    "ResidualFilter",
]

#: The three bands of the modified filter (thesis 3.4.1), Hz.
MODIFIED_BANDS_HZ = (
    2124.4e3,
    (357.45e3 + 330.78e3) / 2.0,
    (200.48e3 + 225.13e3 + 212.73e3) / 3.0,
)


def head_bands_hz(profile=None) -> tuple:
    """The modified filter's three bands for a head, Hz: :data:`MODIFIED_BANDS_HZ` times its frequency scale.

    The bands sit at the default head's fault modes; another head's modes move
    with its healthy mode, so its bands are the default's times
    :meth:`inkdiag_core.HeadProfile.frequency_scale` (exactly 1 for the default head).
    A band at or above 0.45 x the head's sample rate (the empty-channel band of a
    head sampled slowly for its modes) is left out: a resonator there would sit on
    the Nyquist frequency; the filter keeps the other bands.

    Parameters
    ----------
    profile : HeadProfile or None
        A complete head profile; None: the default head.

    Returns
    -------
    tuple of float
        Band centre frequencies, Hz (3, or fewer when the sampling cannot hold one).
    """
    if profile is None:
        return MODIFIED_BANDS_HZ
    scale = profile.frequency_scale()
    return tuple(float(f * scale) for f in MODIFIED_BANDS_HZ if f * scale < 0.45 * profile.sample_rate_hz)


@dataclass(frozen=True)
class FilterDesign:
    """A residual filter as one discrete-time LTI system from ``y`` to ``r``.

    Attributes
    ----------
    kind : str
    A, B, C, D : ndarray
        State space of the filter in balanced coordinates (input y, output r).
    b, a : ndarray
        The same as a transfer function (for ``scipy.signal.lfilter``).
    loop : tuple of ndarray
        ``(num, den)`` of the open observer loop (output injection), whose
        margins are reported.
    dt : float
        Sample period, s.
    """

    kind: str
    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    D: np.ndarray
    b: np.ndarray
    a: np.ndarray
    loop: tuple
    dt: float
    observer_state_dim: int

    @property
    def poles(self) -> np.ndarray:
        """Poles of the filter in the z-plane (complex, (n,))."""
        return np.linalg.eigvals(self.A)

    @property
    def poles_hz(self) -> np.ndarray:
        """Continuous-time equivalents ``log(z) / dt`` of the poles, rad/s."""
        return np.log(self.poles.astype(complex)) / self.dt

    @property
    def is_stable(self) -> bool:
        return bool(np.all(np.abs(self.poles) < 1.0))

    def frequency_response(self, f_hz):
        """Complex response of the filter at frequencies ``f_hz`` (Hz)."""
        _, h = scipy.signal.freqz(self.b, self.a, worN=np.asarray(f_hz, float), fs=1.0 / self.dt)
        return h

    def margins(self, n_points: int = 20000):
        """Gain and phase margins of the observer loop (output injection, negative feedback).

        Returns
        -------
        dict
            ``gain_margin_db`` (inf when the loop's Nyquist curve never crosses
            the negative real axis), ``phase_crossover_hz``, ``phase_margin_deg``
            (inf when the loop gain never reaches 1), ``gain_crossover_hz``.
        """
        fs = 1.0 / self.dt
        f = np.linspace(fs * 1e-5, fs / 2 * 0.999, n_points)
        _, h = scipy.signal.freqz(*self.loop, worN=f, fs=fs)
        out = dict(gain_margin_db=math.inf, phase_crossover_hz=math.nan,
                   phase_margin_deg=math.inf, gain_crossover_hz=math.nan)
        mag = np.abs(h)
        gc = np.nonzero(np.diff(np.sign(mag - 1.0)) != 0)[0]
        if gc.size:
            pm = 180.0 - np.abs(np.degrees(np.angle(h[gc])))
            k = int(np.argmin(pm))
            out.update(phase_margin_deg=float(pm[k]), gain_crossover_hz=float(f[gc[k]]))
        pc = np.nonzero((np.diff(np.sign(h.imag)) != 0) & (h.real[:-1] < 0))[0]
        if pc.size:
            gm = -20.0 * np.log10(mag[pc])
            k = int(np.argmin(gm))
            out.update(gain_margin_db=float(gm[k]), phase_crossover_hz=float(f[pc[k]]))
        return out


def _balanced_dt_model(params: InkChannelParams, sample_rate_hz: float):
    """Healthy observable model, balanced for conditioning, discretised exactly."""
    A, C, _ = InkChannelModel(params).observable()
    Ab, T = scipy.linalg.matrix_balance(A, permute=False)
    Cb = C @ T
    Ad = scipy.linalg.expm(Ab / sample_rate_hz)
    return Ad, Cb, np.linalg.eigvals(Ab)


def _bandpass(f_hz: float, zeta: float, fs: float):
    """Second-order resonator, unit gain at ``f_hz``, poles at ``f_hz`` with damping ``zeta``.

    Returns a discrete state space (A, B, C, D) of ``2 zeta w s / (s^2 + 2 zeta w s + w^2)``
    mapped by the bilinear transform prewarped at ``f_hz``.
    """
    w0 = 2 * math.pi * f_hz
    wp = 2 * fs * math.tan(w0 / (2 * fs))  # prewarp so the peak stays at f_hz
    num, den = [2 * zeta * wp, 0.0], [1.0, 2 * zeta * wp, wp * wp]
    bz, az = scipy.signal.bilinear(num, den, fs=fs)
    return scipy.signal.tf2ss(bz, az)


def design_residual_filter(kind: str = "original", *, params: InkChannelParams | None = None,
                           sample_rate_hz: float = 10e6, band_gain: float = 2.0,
                           band_zeta: float = 0.05, bands_hz=None) -> FilterDesign:
    """Design the original or the modified residual filter.

    Parameters
    ----------
    kind : {"original", "modified"}
    params : InkChannelParams, optional
        Healthy channel (defaults to the nominal one).
    sample_rate_hz : float
        Trace sample rate, Hz.
    band_gain : float
        Peak gain ``g_i`` of each band resonator of the modified filter.
    band_zeta : float
        Damping ratio of the band resonators (lightly damped).
    bands_hz : sequence of float, optional
        Centre frequencies of the modified filter's band resonators, Hz; None:
        :data:`MODIFIED_BANDS_HZ` (the default head's; :func:`head_bands_hz` gives
        another head's).

    Returns
    -------
    FilterDesign
    """
    if kind not in ("original", "modified"):
        raise ValueError(f"kind must be 'original' or 'modified', got {kind!r}")
    fs = float(sample_rate_hz)
    if not (math.isfinite(fs) and fs > 0):
        raise ValueError(f"sample_rate_hz must be positive, got {sample_rate_hz!r}")
    bands = MODIFIED_BANDS_HZ if bands_hz is None else tuple(float(f) for f in bands_hz)
    if kind == "modified" and (not bands or min(bands) <= 0 or fs <= 2 * max(bands)):
        raise ValueError(
            f"sample_rate_hz must exceed twice the highest band ({2 * max(bands, default=0.0):.0f} Hz) "
            f"for the modified filter, and the bands must be positive; got {fs:g} Hz and bands {bands!r}"
        )
    params = InkChannelParams() if params is None else params
    Ad, Cb, lam = _balanced_dt_model(params, fs)
    dt = 1.0 / fs
    # observer error poles: the model's poles with their decay rates tripled
    obs_poles = np.exp((3.0 * lam.real + 1j * lam.imag) * dt)
    L = scipy.signal.place_poles(Ad.T, Cb.T, obs_poles).gain_matrix.T  # (3, 1)
    if kind == "original":
        A_f = Ad - L @ Cb
        B_f = L
        C_f = -Cb
        D_f = np.ones((1, 1))
        loop_ss = (Ad, L, Cb, np.zeros((1, 1)))
    else:
        # PI output injection: u = Kp e + Ki sum(e) (see _pi_observer)
        Kp, Ki = L, _pi_integral_gain(Ad, Cb, L)
        A_f, B_f, C_f, D_f = _pi_observer(Ad, Cb, Kp, Ki)
        loop_ss = _pi_loop(Ad, Cb, Kp, Ki)
        # band emphasis r_mod = (1 + sum g_i H_i) r, in series after the observer
        sum_ss = None
        for f_band in bands:
            Ab_, Bb_, Cb_, Db_ = _bandpass(f_band, band_zeta, fs)
            Cb_, Db_ = band_gain * Cb_, band_gain * Db_
            sum_ss = (Ab_, Bb_, Cb_, Db_) if sum_ss is None else _parallel(sum_ss, (Ab_, Bb_, Cb_, Db_))
        emph = _parallel((np.zeros((0, 0)), np.zeros((0, 1)), np.zeros((1, 0)), np.ones((1, 1))), sum_ss)
        A_f, B_f, C_f, D_f = _series((A_f, B_f, C_f, D_f), emph)
    b, a = scipy.signal.ss2tf(A_f, B_f, C_f, D_f)
    loop = scipy.signal.ss2tf(*loop_ss)
    return FilterDesign(kind=kind, A=A_f, B=B_f, C=C_f, D=D_f, b=b[0], a=a,
                        loop=(loop[0][0], loop[1]), dt=dt, observer_state_dim=3)


def _pi_integral_gain(Ad, Cb, Kp, target_pm_deg: float = 45.0):
    """Integral gain along Kp's direction: the largest of a sweep that keeps the PI
    observer stable with a phase margin >= ``target_pm_deg`` (loop shaping)."""
    direction = Kp / np.linalg.norm(Kp)
    best = np.zeros_like(Kp)
    for scale in np.geomspace(1e-4, 1.0, 25) * np.linalg.norm(Kp):
        Ki = scale * direction
        A_o = _pi_observer(Ad, Cb, Kp, Ki)[0]
        if np.max(np.abs(np.linalg.eigvals(A_o))) >= 1.0 - 1e-9:
            continue
        num, den = scipy.signal.ss2tf(*_pi_loop(Ad, Cb, Kp, Ki))
        probe = FilterDesign("probe", A_o, Kp, Cb, np.zeros((1, 1)), num[0], den, (num[0], den), 1.0, 3)
        if probe.margins(4000)["phase_margin_deg"] < target_pm_deg:
            break
        best = Ki
    return best


def _pi_observer(Ad, Cb, Kp, Ki):
    """Observer with PI output injection as a system from y to r.

    States ``[x_hat (3), q]`` with ``e = y - C x_hat``, ``q[k+1] = q[k] + e[k]`` and
    ``x_hat[k+1] = A_d x_hat[k] + Kp e[k] + Ki q[k+1]``; output ``r = e``.
    """
    n = Ad.shape[0]
    A = np.zeros((n + 1, n + 1))
    A[:n, :n] = Ad - (Kp + Ki) @ Cb
    A[:n, n:] = Ki
    A[n:, :n] = -Cb
    A[n, n] = 1.0
    B = np.vstack([Kp + Ki, [[1.0]]])
    return A, B, np.hstack([-Cb, [[0.0]]]), np.ones((1, 1))


def _pi_loop(Ad, Cb, Kp, Ki):
    """Open observer loop from the output error e to y_hat (for margins)."""
    n = Ad.shape[0]
    A = np.zeros((n + 1, n + 1))
    A[:n, :n] = Ad
    A[:n, n:] = Ki
    A[n, n] = 1.0
    B = np.vstack([Kp + Ki, [[1.0]]])
    return A, B, np.hstack([Cb, [[0.0]]]), np.zeros((1, 1))


def _series(first, second):
    """State space of ``second(first(u))``."""
    A1, B1, C1, D1 = first
    A2, B2, C2, D2 = second
    n1, n2 = A1.shape[0], A2.shape[0]
    A = np.zeros((n1 + n2, n1 + n2))
    A[:n1, :n1] = A1
    A[n1:, :n1] = B2 @ C1
    A[n1:, n1:] = A2
    B = np.vstack([B1, B2 @ D1])
    C = np.hstack([D2 @ C1, C2])
    D = D2 @ D1
    return A, B, C, D


def _parallel(s1, s2):
    """State space of ``s1(u) + s2(u)``."""
    A1, B1, C1, D1 = s1
    A2, B2, C2, D2 = s2
    A = scipy.linalg.block_diag(A1, A2) if A1.size or A2.size else np.zeros((0, 0))
    B = np.vstack([B1, B2])
    C = np.hstack([C1, C2])
    return A, B, C, D1 + D2


class ResidualFilter(TransformerMixin, BaseEstimator):
    """Traces -> residual traces of the healthy model (a scikit-learn transformer).

    Parameters
    ----------
    kind : {"original", "modified"}
        The thesis's original residual filter (KPI_R) or the modified one (KPI_R_Modified).
    sample_rate_hz : float
        Trace sample rate, Hz.
    params : InkChannelParams or None
        Healthy channel; ``None`` is the nominal one (the default head's).
    bands_hz : sequence of float or None
        Band centres of the modified filter, Hz; ``None``: :data:`MODIFIED_BANDS_HZ`
        (the default head's; :func:`head_bands_hz` for another head).
    healthy_labels : tuple
        Labels (as given to ``fit``) of the healthy reference rows whose initial
        states are averaged. Without labels, or with no healthy row, all rows are used.

    Attributes
    ----------
    design_ : FilterDesign
    x0_ : ndarray, shape (3,)
        Averaged reference initial state (balanced coordinates, trace units).
    free_response_ : ndarray, shape (n_samples,)
        The residual's zero-input part from the reference initial state.
    n_features_in_ : int
        Samples per trace.
    """

    def __init__(self, kind="original", sample_rate_hz=10e6, params=None,
                 healthy_labels=(*HEALTHY_VALUES, 0), bands_hz=None):
        self.kind = kind
        self.sample_rate_hz = sample_rate_hz
        self.params = params
        self.healthy_labels = healthy_labels
        self.bands_hz = bands_hz

    def __setstate__(self, state):  # files pickled before bands_hz existed: the default bands
        state.setdefault("bands_hz", None)
        super().__setstate__(state)

    def fit(self, X, y=None):
        X = validate_data(self, X, dtype=[np.float64, np.float32], ensure_min_samples=1,
                          ensure_min_features=MIN_KPI_SAMPLES)
        self.design_ = design_residual_filter(self.kind, params=self.params,
                                              sample_rate_hz=self.sample_rate_hz, bands_hz=self.bands_hz)
        rows = X
        if y is not None:
            y = np.asarray(y)
            mask = np.isin(y.astype(object), np.asarray(self.healthy_labels, dtype=object))
            if mask.any():
                rows = X[mask]
        self.x0_ = self._reference_state(rows)
        self.free_response_ = self._zero_input(self.x0_, X.shape[1])
        return self

    def _reference_state(self, rows):
        """Initial state reconstructed from the KPIs of each reference row, averaged."""
        n_samples = rows.shape[1]
        fs = float(self.sample_rate_hz)
        kpis = extract_kpis(rows, fs)
        clean = reconstruct(kpis, n_samples, fs) - kpis[:, :1]  # the KPIs' damped sinusoid, no DC
        Ad, Cb, _ = _balanced_dt_model(self.params or InkChannelParams(), fs)
        M = np.empty((n_samples, 3))
        row = Cb[0].copy()
        for k in range(n_samples):  # 3 x n_samples design matrix, computed once per fit
            M[k] = row
            row = row @ Ad
        scale = np.linalg.norm(M, axis=0)
        coef, *_ = np.linalg.lstsq(M / scale, clean.T, rcond=None)
        x0s = (coef / scale[:, None]).T  # (n_ref, 3)
        return np.median(x0s, axis=0) if x0s.shape[0] > 2 else x0s.mean(axis=0)

    def _zero_input(self, x0, n_samples):
        """Residual contribution of the observer's initial state (x_hat(0) = x0)."""
        d = self.design_
        x = np.zeros(d.A.shape[0])
        x[: d.observer_state_dim] = x0
        out = np.empty(n_samples)
        for k in range(n_samples):  # one fixed vector per fit
            out[k] = d.C[0] @ x
            x = d.A @ x
        return out

    def transform(self, X):
        """Residual traces, float64 (n, n_samples)."""
        check_is_fitted(self, "design_")
        X = validate_data(self, X, dtype=[np.float64, np.float32], reset=False)
        r = scipy.signal.lfilter(self.design_.b, self.design_.a, X, axis=1)
        r += self.free_response_[: X.shape[1]]
        return r
