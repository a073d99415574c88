"""Nonlinear "physics-based" variant of the simulator (for the estimation work, thesis 4.5).

Same channels, same classes, same sensor chain and the same :class:`SimulationResult` as
:func:`inkdiag_core.simulate` (for the same ``seed`` and ``counts`` the per-trace physical
parameters are drawn identically), but the ink channel is integrated with
``scipy.integrate.solve_ivp`` (DOP853, tight tolerances) with these nonlinear terms
(:class:`NonlinearTerms`):

1. Quadratic nozzle entrance/exit loss (vena contracta, Borda-Carnot): a pressure drop
   ``K rho / (2 A_n^2) |Q_n| Q_n`` on the nozzle branch, ``A_n = pi r_n^2``, with
   ``K = K_in = 0.5`` while ink flows from the chamber into the sharp-edged nozzle inlet
   and ``K = K_out = 1.0`` while it flows back and expands into the chamber. It grows with
   the flow amplitude (the damping depends on the drive amplitude) and is asymmetric
   (it rectifies a little: even harmonics and a small drift of ``V_n``).
2. Meniscus surface tension: the ink volume ``V_n`` pushed out of (or drawn into) the
   nozzle bulges the meniscus into a spherical cap of height ``h`` with
   ``V_n = pi h (3 r_n^2 + h^2) / 6``; its Laplace pressure ``4 sigma h / (r_n^2 + h^2)``
   opposes the nozzle flow. For small ``V_n`` this is the stiffness
   ``k_m = 8 sigma / (pi r_n^4)`` (about 1.3 % of the chamber's ``1 / B_t``), which
   raises the frequency by about 0.5 %; for larger ``V_n`` it softens.
3. Temperature-dependent viscosity: every trace's ink viscosity follows its ink
   temperature (Andrade's law, as in the linear simulator), so ``R_n`` and ``R_r`` differ
   from the nominal model's even for a healthy nozzle.

The 4-state nonlinear model, ``x = [V_r, V_n, Q_r, Q_n]`` (m^3, m^3, m^3/s, m^3/s)::

    p    = (b u(t) - V_r - V_n) / B_t
    Q_r' = (p - R_r Q_r) / I_r
    Q_n' = (p - R_n Q_n - K rho / (2 A_n^2) |Q_n| Q_n - p_m(V_n)) / I_n

The meniscus term applies where the meniscus sits at the nozzle exit (healthy, dried,
partially blocked, chamber bubble); the entrance loss wherever ink flows through the
nozzle. A closed nozzle (fully blocked) has ``Q_n = 0``; empty channels are the linear
actuator resonance. With both terms switched off the variant reproduces the linear
simulator (a test checks it).

Amplitude. Nonlinear terms need physical amplitudes: this variant uses a coupling of
``DEFAULT_COUPLING_M3_PER_V`` (1.5e-16 m^3/V: 3 pL displaced at 20 V, a jetting-size
pulse; nozzle velocities of a few m/s in the sensing window), and scales the sense gain by
``InkChannelParams().b / b`` so that the traces have the linear simulator's volt range.

Truth. ``fm`` is the *linear-model* Appendix F fault of the nozzle-viscosity change,
``-alpha (mu_nozzle - mu)`` (the quantity the estimators are scored against);
``frequency_hz``, ``damping_ratio`` and ``A`` are those of the linear model of the same
channel (no meniscus stiffness, no entrance loss). Because the entrance loss adds an
amplitude-dependent damping that looks like a small extra ``R_n``, and the meniscus
stiffness shifts the frequency, a linear-model estimate of ``f_m`` on these traces is only
approximately identifiable: expect a bias of a few percent of the healthy ``R_n / I_n``.
``x0`` is the true (nonlinear) observable-form state at the first sample.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.integrate import solve_ivp

from ..model import InkChannelParams
from .channels import PHYSICAL_CONSTANTS, ChannelDraw, DriveWaveform, Spreads, draw_channels, observable_A
from .inputs import check_counts, check_positive_float, check_positive_int, check_severity, prepare_run
from .modal import dominant_mode, modal_solution, nominal_rms
from .result import SimulationResult, empty_result
from .sensor import adc_quantiser, draw_sensor, noise_std_for_snr, snr_db, white_noise

__all__ = ["NonlinearTerms", "simulate_nonlinear", "DEFAULT_COUPLING_M3_PER_V"]

DEFAULT_COUPLING_M3_PER_V = 1.5e-16
"""Actuator coupling used by the nonlinear variant, m^3/V (3 pL at 20 V)."""

_MENISCUS_KINDS = ("healthy", "dried", "particle", "chamber_bubble")
_NOZZLE_FLOW_KINDS = ("healthy", "dried", "particle", "chamber_bubble", "nozzle_bubble")


@dataclass(frozen=True)
class NonlinearTerms:
    """Switches and coefficients of the nonlinear terms.

    Parameters
    ----------
    entrance_loss_k : float
        Loss coefficient ``K_in`` for flow from the chamber into the nozzle (0 = off).
    exit_loss_k : float
        Loss coefficient ``K_out`` for flow from the nozzle back into the chamber.
    meniscus : bool
        Include the meniscus Laplace pressure ``p_m(V_n)``.
    """

    entrance_loss_k: float = 0.5
    exit_loss_k: float = 1.0
    meniscus: bool = True

    def __post_init__(self):
        for name in ("entrance_loss_k", "exit_loss_k"):
            k = getattr(self, name)
            if not (isinstance(k, (int, float)) and math.isfinite(k) and k >= 0):
                raise ValueError(f"terms.{name} must be a finite number >= 0, got {k!r}")

    @classmethod
    def off(cls) -> "NonlinearTerms":
        """All terms off: the linear model (for checks)."""
        return cls(0.0, 0.0, False)


def _meniscus_pressure(V, r, sigma):
    """Laplace pressure (Pa) of a pinned spherical-cap meniscus of bulge volume V (m^3)."""
    # h^3 + 3 r^2 h - 6 V / pi = 0 has one real root (Cardano)
    q = 3.0 * V / np.pi
    s = np.sqrt(q * q + r**6)
    h = np.cbrt(q + s) + np.cbrt(q - s)
    return 4.0 * sigma * h / (r * r + h * h)


def _integrate_batch(ch: ChannelDraw, idx, drive, amplitude, terms, t_eval, rtol, method):
    """Integrate the traces ``idx`` together; returns the states at t_eval, (4, m, n_t)."""
    P = ch.params
    m = len(idx)
    B_t = P["B_t"][idx]
    inv_Ir = 1.0 / P["I_r"][idx]
    inv_In = 1.0 / P["I_n"][idx]
    R_r = np.nan_to_num(P["R_r"][idx])
    R_n = P["R_n"][idx]
    bU = P["b"][idx] * amplitude[idx]
    kinds = ch.kinds[idx]
    flow = np.isin(kinds, _NOZZLE_FLOW_KINDS)
    loss0 = np.where(flow, P["rho"][idx] / (2.0 * (np.pi * P["r_n"][idx] ** 2) ** 2), 0.0)
    loss_in = terms.entrance_loss_k * loss0
    loss_out = terms.exit_loss_k * loss0
    men = np.isin(kinds, _MENISCUS_KINDS) & terms.meniscus
    r_men = P["r_n"][idx]
    sigma = PHYSICAL_CONSTANTS["sigma_n_per_m"]
    any_men = bool(men.any())

    # scaled states: volumes by V0, flows by V0 * w0 (conditioning only)
    V0 = np.abs(bU).max()
    w0 = 2 * np.pi * 237e3
    scale = np.concatenate([np.full(2 * m, V0), np.full(2 * m, V0 * w0)])

    def rhs(t, xs, u):
        x = xs * scale
        Vr, Vn, Qr, Qn = x[:m], x[m:2 * m], x[2 * m:3 * m], x[3 * m:]
        p = (bU * u(t) - Vr - Vn) / B_t
        dQr = inv_Ir * (p - R_r * Qr)
        drop = p - R_n * Qn - np.where(Qn > 0, loss_in, loss_out) * np.abs(Qn) * Qn
        if any_men:
            drop = drop - np.where(men, _meniscus_pressure(Vn, r_men, sigma), 0.0)
        dQn = inv_In * drop
        return np.concatenate([Qr, Qn, dQr, dQn]) / scale

    t1 = drive.rise_s
    t2 = t1 + drive.dwell_s
    t3 = drive.end_s
    segments = [
        (0.0, t1, lambda t: t / t1),
        (t1, t2, lambda t: 1.0),
        (t2, t3, lambda t: (t3 - t) / drive.fall_s),
        (t3, t_eval[-1], lambda t: 0.0),
    ]
    x = np.zeros(4 * m)
    # the error norm is an RMS over all 4 m components: tighten so that one trace's
    # error cannot hide behind the others'
    rtol_eff = rtol / math.sqrt(m)
    atol = rtol_eff * 1e-3
    for k, (ta, tb, u) in enumerate(segments):
        last = k == len(segments) - 1
        sol = solve_ivp(
            rhs, (ta, tb), x, method=method, rtol=rtol_eff, atol=atol, args=(u,),
            t_eval=t_eval if last else None, max_step=drive.rise_s / 4,
        )
        if not sol.success:
            raise RuntimeError(f"solve_ivp failed: {sol.message}")
        x = sol.y[:, -1]
    return (sol.y * scale[:, None]).reshape(4, m, -1)


def simulate_nonlinear(
    counts,
    *,
    sample_rate_hz: float = 10e6,
    n_samples: int = 512,
    seed=0,
    spreads: Spreads | None = None,
    drive: DriveWaveform | None = None,
    base_params: InkChannelParams | None = None,
    terms: NonlinearTerms | None = None,
    severity=None,
    rtol: float = 1e-10,
    method: str = "DOP853",
    batch_size: int = 32,
) -> SimulationResult:
    """Simulate traces with the nonlinear ink-channel model (see the module docstring).

    Parameters
    ----------
    counts, sample_rate_hz, n_samples, seed, spreads, drive, severity
        As :func:`inkdiag_core.simulate`.
    base_params : InkChannelParams, optional
        Nominal channel; default ``InkChannelParams(b=DEFAULT_COUPLING_M3_PER_V)``.
    terms : NonlinearTerms, optional
        Nonlinear terms; default ``NonlinearTerms()`` (K_in 0.5, K_out 1.0, meniscus on).
    rtol : float
        Relative tolerance per trace (default 1e-10).
    method : str
        ``solve_ivp`` method (default "DOP853").
    batch_size : int
        Traces integrated together as one ODE system (speed only).

    Returns
    -------
    SimulationResult
        Same format as :func:`inkdiag_core.simulate`.
    """
    classes = check_counts(counts)
    fs = check_positive_float("sample_rate_hz", sample_rate_hz)
    n_samples = check_positive_int("n_samples", n_samples)
    batch_size = check_positive_int("batch_size", batch_size)
    rtol = check_positive_float("rtol", rtol)
    terms = NonlinearTerms() if terms is None else terms
    base = InkChannelParams(b=DEFAULT_COUPLING_M3_PER_V) if base_params is None else base_params
    spreads, drive, base, rng, labels = prepare_run(classes, fs, spreads, drive, base, seed,
                                                 extra=(("terms", terms, NonlinearTerms),))
    n = labels.size
    if n == 0:
        return empty_result(labels, fs, n_samples)

    # identical draws to simulate(): channels, then gain and offset, then noise
    ch = draw_channels(classes, base, spreads, rng, check_severity(severity, classes))
    amplitude = drive.amplitude_v * ch.drive
    gain_nominal = PHYSICAL_CONSTANTS["sensor_gain_v_per_m3s"] * InkChannelParams().b / base.b
    gain, offset = draw_sensor(rng, n, spreads, gain_nominal)
    lam, _, _ = modal_solution(ch, drive, amplitude)
    freq, zeta = dominant_mode(lam)

    t_eval = drive.window_start_s + np.arange(n_samples) / fs
    y = np.empty((n, n_samples))
    x0 = np.empty((n, 3))
    for start in range(0, n, batch_size):
        idx = np.arange(start, min(n, start + batch_size))
        X = _integrate_batch(ch, idx, drive, amplitude, terms, t_eval, rtol, method)
        y[idx] = X[2] + X[3]
        x0[idx] = np.stack([X[0, :, 0] + X[1, :, 0], X[2, :, 0], X[3, :, 0]], axis=1)

    nominal_rms_v = nominal_rms(base, drive, n_samples, fs) * gain_nominal
    noise_std = noise_std_for_snr(spreads, nominal_rms_v)
    v = gain[:, None] * y
    sig_rms = v.std(axis=1)
    v += offset[:, None]
    if noise_std > 0:
        v += white_noise(rng, (n, n_samples), noise_std)
    lsb, quant = adc_quantiser(spreads)
    if quant is not None:
        v = np.clip(np.rint(v / lsb), quant[0], quant[1]) * lsb
    snr = snr_db(sig_rms, noise_std)
    params = {k: v_ for k, v_ in ch.params.items()}
    params["drive_v"] = amplitude
    return SimulationResult(
        traces=v.astype(np.float32), labels=labels, sample_rate_hz=fs,
        mu_nozzle=ch.mu_nozzle, mu=ch.mu, fm=ch.fm, frequency_hz=freq,
        damping_ratio=zeta, x0=x0, A=observable_A(ch.k_r, ch.k_n, ch.d_r, ch.d_n),
        sensor_gain=gain, sensor_offset=offset, snr_db=snr, params=params,
        noise_std_v=noise_std,
    )

