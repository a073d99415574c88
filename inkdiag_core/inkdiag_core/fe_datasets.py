"""Synthetic datasets for fault estimation (thesis section 4.4.1 and 4.5).

* :func:`fault_levels` -- the 49 fault levels: nozzle viscosity increases from
  +0.2 mu to +10 mu (equally spaced), converted to f_m with eq. (37).
* :func:`synthetic_set` -- one trace per level (or several), generated either
  by the thesis's DT model eq. (25) (``kind="dt"``: ``x(k+1) = (expm(A_H dt) +
  f_m dt e3 e3^T) x(k)``) or by the exact continuous-time model eq. (26)
  integrated with ``scipy.integrate.solve_ivp`` RK45 at ``rtol=1e-10``
  (``kind="ct"``), from one common initial state (as in 4.4.1) or from random
  ones, with optional white Gaussian noise at a stated SNR.
* :func:`nonlinear_set` -- the physics-based set of 4.5 from the simulator's
  nonlinear variant :func:`inkdiag_core.simulate_nonlinear` (dried classes, the
  simulator's drive, spreads and default sensor noise), converted to ``y = C x``.

Both generators are independent of the estimators' code paths (no ``expm``
of the faulty matrix, no UIO).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
from scipy.integrate import solve_ivp

from .model import InkChannelModel, viscosity_to_fm

__all__ = [
    "FeDataset",
    "common_x0",
    "fault_levels",
    "random_x0",
    "synthetic_set",
    "nonlinear_set",
    "add_noise",
]

#: actuator stroke used for the common initial state, V
PULSE_V = 20.0


@dataclass(frozen=True)
class FeDataset:
    """Traces with their truth.

    Attributes
    ----------
    y : ndarray, shape (n, n_samples)
        Outputs in m^3/s (noisy if ``snr_db`` is set).
    y_clean : ndarray, shape (n, n_samples)
    fm : ndarray, shape (n,)
        True f_m, 1/s.
    mu_nozzle : ndarray, shape (n,)
        True nozzle viscosity, Pa s.
    level : ndarray of int, shape (n,)
        Fault level index 0..n_levels-1.
    x0 : ndarray, shape (n, 3)
        True initial states (eq. 12 coordinates, SI).
    sample_rate_hz : float
    snr_db : float or None
    kind : str
    y_healthy : ndarray, shape (n, n_frames, n_samples), optional
        Physics-based set only: the same nozzles (same geometry and piezo draws),
        healthy, at the nominal ink temperature, each in ``n_frames`` frames with
        independent sensor noise: what a monitor sees of a nozzle before it dries.
    """

    y: np.ndarray
    y_clean: np.ndarray
    fm: np.ndarray
    mu_nozzle: np.ndarray
    level: np.ndarray
    x0: np.ndarray
    sample_rate_hz: float
    snr_db: float | None
    kind: str
    y_healthy: np.ndarray | None = None


def fault_levels(model: InkChannelModel, n_levels: int = 49, rel_increase=(0.2, 10.0)):
    """Nozzle viscosities and f_m of the fault levels.

    Returns
    -------
    mu : ndarray, shape (n_levels,)
        ``mu_n (1 + linspace(*rel_increase, n_levels))``, Pa s.
    fm : ndarray, shape (n_levels,)
        Eq. (37), 1/s (negative).
    """
    p = model.params
    mu = p.mu_n * (1.0 + np.linspace(rel_increase[0], rel_increase[1], int(n_levels)))
    return mu, viscosity_to_fm(p, mu)


def common_x0(model: InkChannelModel) -> np.ndarray:
    """The common initial state: right after a fast actuator stroke of ``PULSE_V``.

    The actuator has displaced ``b u`` into the chamber before the necks had time
    to move: in eq. (12) coordinates relative to the new equilibrium the state is
    ``[-b u, 0, 0]`` (m^3, m^3/s, m^3/s); ``y(0) = 0`` and the ring-down follows.
    """
    return np.array([-model.params.b * PULSE_V, 0.0, 0.0])


def random_x0(model: InkChannelModel, n: int, rng) -> np.ndarray:
    """Random initial states of the same scale as :func:`common_x0`.

    Volume ``-b u (0.5..1.5)``; neck flows ``N(0, 0.5) * b u w0`` each (w0 the
    healthy angular frequency), so amplitude and phase of the ring-down vary.
    """
    p = model.params
    f0, _ = model.dominant_mode()
    w0 = 2 * np.pi * f0
    v = p.b * PULSE_V
    x0 = np.empty((n, 3))
    x0[:, 0] = -v * rng.uniform(0.5, 1.5, n)
    x0[:, 1:] = v * w0 * rng.normal(0.0, 0.5, (n, 2))
    return x0


def add_noise(y, snr_db, rng):
    """White Gaussian noise at ``snr_db`` = 10 log10(mean(y^2) / sigma^2) per trace."""
    if snr_db is None:
        return y.copy()
    p = np.mean(y * y, axis=1, keepdims=True)
    sigma = np.sqrt(p / 10 ** (snr_db / 10))
    return y + sigma * rng.standard_normal(y.shape)


def _simulate_dt(model, fm, x0, sample_rate_hz, n_samples):
    """Eq. (25) recursion, vectorised over traces."""
    n = fm.shape[0]
    AdH = model.discretize_appendix_e(sample_rate_hz, 0.0)
    dt = 1.0 / sample_rate_hz
    x = x0.copy()
    y = np.empty((n, n_samples))
    for k in range(n_samples):
        y[:, k] = x[:, 1] + x[:, 2]
        x3 = x[:, 2].copy()
        x = x @ AdH.T
        x[:, 2] += fm * x3 * dt
    return y


def _transition_ct(model, fm, sample_rate_hz, n_samples, rtol=1e-10):
    """C Phi(t_k) for the faulty CT model by solve_ivp RK45 on the 3x3 state-transition matrix.

    Time in microseconds and a diagonal state scaling keep the integrator in O(1)
    numbers; the result is mapped back to SI. Returns (n_samples, 3).
    """
    A, C, _ = model.observable(fm)
    T0 = 1e-6
    s = np.array([1.0, 1e6, 1e6])  # x = diag(s) xs: volumes in m^3, flows in m^3/us
    As = (A * T0) / s[:, None] * s[None, :]
    t = np.arange(n_samples) / (sample_rate_hz * T0)

    def rhs(_t, phi):
        return (As @ phi.reshape(3, 3)).ravel()

    sol = solve_ivp(rhs, (0.0, t[-1]), np.eye(3).ravel(), method="RK45", t_eval=t,
                    rtol=rtol, atol=1e-13)
    if not sol.success:  # pragma: no cover - defensive
        raise RuntimeError(sol.message)
    Phi = sol.y.T.reshape(-1, 3, 3)  # xs(t) = Phi xs0
    Cs = C.ravel() * s
    return np.einsum("i,kij->kj", Cs, Phi) / s[None, :]


def synthetic_set(model: InkChannelModel | None = None, *, kind="ct", x0="common",
                  n_levels=49, n_per_level=1, snr_db=None, sample_rate_hz=10e6,
                  n_samples=512, seed=0) -> FeDataset:
    """The thesis's synthetic set (4.4.1): one trace per fault level and initial state.

    Parameters
    ----------
    kind : {"ct", "dt"}
        "ct": exact continuous-time model (eq. 26) by solve_ivp RK45, rtol 1e-10;
        "dt": the thesis's DT model eq. (25).
    x0 : "common", "random" or array (3,)
    snr_db : float, optional
        Additive white Gaussian noise per trace.
    """
    model = InkChannelModel() if model is None else model
    if kind not in ("ct", "dt"):
        raise ValueError(f"kind must be 'ct' or 'dt', got {kind!r}")
    rng = np.random.default_rng(seed)
    mu_l, fm_l = fault_levels(model, n_levels)
    level = np.repeat(np.arange(n_levels), n_per_level)
    fm = fm_l[level]
    mu = mu_l[level]
    n = level.size
    if isinstance(x0, str) and x0 == "common":
        X0 = np.broadcast_to(common_x0(model), (n, 3)).copy()
    elif isinstance(x0, str) and x0 == "random":
        X0 = random_x0(model, n, rng)
    else:
        X0 = np.broadcast_to(np.asarray(x0, dtype=float), (n, 3)).copy()
    if kind == "dt":
        y = _simulate_dt(model, fm, X0, sample_rate_hz, n_samples)
    else:
        y = np.empty((n, n_samples))
        for j in range(n_levels):
            rows = level == j
            CPhi = _transition_ct(model, float(fm_l[j]), sample_rate_hz, n_samples)
            y[rows] = X0[rows] @ CPhi.T
    return FeDataset(y=add_noise(y, snr_db, rng), y_clean=y, fm=fm, mu_nozzle=mu,
                     level=level, x0=X0, sample_rate_hz=float(sample_rate_hz),
                     snr_db=snr_db, kind=kind)


def nonlinear_set(n_per_class=100, *, seed=0, sample_rate_hz=10e6, n_samples=512,
                  healthy_frames=0, profile=None, clean=True):
    """Physics-based dried-nozzle traces from :func:`inkdiag_core.simulate_nonlinear`.

    Classes slightly / intermediately / deeply dried (``level`` 0, 1, 2), each with the
    simulator's severity ranges, per-trace spreads (temperature, geometry, piezo,
    drive, gain, offset), its drive waveform (so the initial state at the first sensed
    sample is whatever the pulse left, different per trace) and its default sensor
    noise and 12-bit ADC. The traces (V) are converted to ``y = C x`` (m^3/s) with each
    trace's true sense gain and offset (a calibrated front end; the thesis's
    estimators have no offset state). ``y_clean`` is the same draw without noise and
    ADC (same seed: the noise is drawn last). Truth: ``fm`` = the simulator's linear-
    model Appendix F fault ``-alpha (mu_nozzle - mu)``; ``x0`` = the true nonlinear
    state at the first sample. ``snr_db`` is the median per-trace SNR.

    ``healthy_frames > 0`` adds ``y_healthy``: each nozzle healthy, before it
    dried. The simulator draws every trace's spreads in a fixed order whatever
    its class, so the same seed and row count give the same nozzles (geometry,
    piezo, drive, gain); the ink is at the nominal temperature (the head
    heater's set point; the dried traces' temperatures are random), and each
    frame gets its own sensor noise (the simulator's noise level, drawn from an
    independent stream), so neither the temperature nor the noise is shared with
    the dried trace.

    ``profile`` (a complete :class:`~inkdiag_core.HeadProfile`): the same set on
    that head: its channel as the nominal channel, its drive, its spreads and
    noise, and its sampling (``sample_rate_hz`` and ``n_samples`` are ignored).
    None: the simulator's defaults, as before. ``clean=False`` skips the
    noise-free draw (``y_clean`` is None; half the time).
    """
    from .faults import FaultClass
    from .simulation.nonlinear import simulate_nonlinear
    from .simulation import Spreads, healthy_twin_frames

    classes = (FaultClass.SLIGHTLY_DRIED, FaultClass.INTERMEDIATELY_DRIED,
               FaultClass.DEEPLY_DRIED)
    counts = {c: int(n_per_class) for c in classes}
    kw = dict(sample_rate_hz=sample_rate_hz, n_samples=n_samples, seed=seed)
    spreads = Spreads()
    if profile is not None:
        sample_rate_hz, n_samples = profile.sample_rate_hz, profile.n_samples
        spreads = profile.spreads()
        kw = dict(sample_rate_hz=sample_rate_hz, n_samples=n_samples, seed=seed,
                  base_params=profile.channel_params(), drive=profile.drive)
        r = simulate_nonlinear(counts, spreads=spreads, **kw)
    else:
        r = simulate_nonlinear(counts, **kw)
    rc = simulate_nonlinear(counts, spreads=dataclasses.replace(spreads, snr_db=np.inf, adc_bits=None), **kw) \
        if clean else r
    if not np.array_equal(r.fm, rc.fm):  # pragma: no cover - defensive
        raise RuntimeError("clean and noisy nonlinear draws differ")

    def to_si(res):
        return (res.traces.astype(float) - res.sensor_offset[:, None]) / res.sensor_gain[:, None]

    level = np.array([classes.index(c) for c in r.labels])
    y_healthy = None
    if healthy_frames > 0:
        twin_kw = {k: v for k, v in kw.items() if k != "seed"}
        h, volts = healthy_twin_frames(len(r.fm), seed=seed, n_frames=int(healthy_frames),
                                       noise_std_v=r.noise_std_v, simulate_fn=simulate_nonlinear,
                                       **({} if profile is None else {"spreads": spreads}), **twin_kw)
        for name in ("r_n", "L_n", "r_r", "B_act", "b"):
            if not np.array_equal(h.params[name], r.params[name]):  # pragma: no cover - defensive
                raise RuntimeError(f"healthy and dried draws differ in {name}")
        y_healthy = (volts.astype(float) - h.sensor_offset[:, None, None]) / h.sensor_gain[:, None, None]
    return FeDataset(y=to_si(r), y_clean=to_si(rc) if clean else None, fm=np.asarray(r.fm, float),
                     mu_nozzle=np.asarray(r.mu_nozzle, float), level=level,
                     x0=np.asarray(r.x0, float), sample_rate_hz=float(sample_rate_hz),
                     snr_db=float(np.median(r.snr_db)), kind="nonlinear", y_healthy=y_healthy)
