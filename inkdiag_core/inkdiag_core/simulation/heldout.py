"""Held-out fault conditions (issue 16): for evaluation only, never for training.

Six conditions that none of the 12 classes of :mod:`inkdiag_core.faults` covers. They
exist to measure how a trained detector behaves on faults it has never seen (an open-set
``unknown`` layer, a healthy gate). **They are never used in training**: nothing in
:mod:`inkdiag_core.training`, :mod:`inkdiag_core.fdi`, :mod:`inkdiag_core.simulation.datasets`
or :mod:`inkdiag_core.fe_datasets` imports this module (``tests/core/test_heldout.py``
checks it), and :func:`simulate_heldout` returns no class label, only the condition.

Every trace starts as a healthy jetting trace (``healthy_nozzle``) of the head: the same
channel draw (:func:`~.channels.draw_channels`: ink temperature, geometry, piezo and
drive tolerances), the same sense gain and offset (:func:`~.sensor.draw_sensor`), the
same white noise level and the same ADC (quantisation, clipping) as
``profile.simulate({"healthy_nozzle": n}, seed=seed)``; with one ``seed`` the healthy
draws are identical to that call's (the condition's own draws come from a separate
stream, ``Generator.spawn``), so a held-out trace differs from its healthy twin only
by the condition. The condition's physics is applied at the stage where it acts.

``severity`` in [0, 1] runs the condition's primary parameter from the mild end (0) of
its range to the severe end (1); reports call ``severity <= 0.2`` "the mild end". The
secondary parameters are drawn uniformly over their ranges, independently of it.

Conditions
----------
poor_contact
    A corroded or loose contact between the sense amplifier and the piezo electrode
    (flex cable, wire bond) adds a series resistance that divides the sensed signal
    and adds its own (contact, thermal and 1/f-like) noise. Acts on the sensed voltage
    before the sensor noise and the ADC: ``v = gain y / cut + offset + noise + extra``.
    ``cut`` (primary, log-uniform) 5 -> 20; ``extra_noise_rel`` (std of the extra
    white noise relative to the sensor's noise std) 0.5-2.0. The channel is healthy.
crosstalk
    A firing neighbour couples its ring-down into this channel's sense line (shared
    ground, electrical and acoustic coupling through the nozzle plate). The neighbour fires
    in another firing group (a delay) and the coupling path shifts the phase, so its
    ring-down comes with a random phase (uniform, ``phase``, rad). The neighbour is
    a second healthy channel draw of the same head (its own tolerances), detuned by a
    relative frequency offset ``detune`` (its eigenvalues scaled by ``1 + detune``:
    same damping ratio, frequency shifted; a neighbour at another ink temperature or
    with its own geometry, beyond the spreads). Its sensed ring-down is scaled to
    ``amplitude`` times this channel's main ring-down amplitude (the envelope at the
    first sample) and added before the sensor noise.
    ``amplitude`` (primary) 0.30 -> 1.00; ``|detune|`` 0.03-0.12, sign random.
    The offset is relative, so it scales with the head's modes.
double_fault
    Drying and a chamber bubble at once: the nozzle viscosity factor ``k`` (as the
    dried classes, ``R_n`` times ``k``) and a free gas bubble of radius ``r_b`` in the
    chamber adding its compliance to ``B_t`` (as ``small_air_bubble``). Built from the
    ``small_air_bubble`` channel draw with ``d_n = R_n / I_n`` times ``k``.
    ``k`` (primary) 3 -> 6; ``r_b`` 4.6-6.0 um (``small_air_bubble``'s range).
actuator_damage
    A cracked or partially depolarised piezo: the cracked part no longer drives, so the
    coupling ``b`` (m^3/V, the volume displaced per volt) drops, and the cracked
    ceramic is softer, so the actuator
    compliance ``B_act`` grows (``B_t`` grows by ``B_act`` times the increase: a lower
    resonance). As in the rest of the simulator the sense gain is a fixed V per
    (m^3/s) of outflow, so ``b`` acts on the drive side only. ``coupling_div`` (primary, log-uniform) 3 -> 10 (``b / coupling_div``);
    ``compliance_rel`` 0.20-0.50 (``B_act (1 + compliance_rel)``).
truncated_pulse
    A driver fault (supply droop tripping the driver IC, a timing error) cuts the
    pulse's flat top short: the dwell is ``dwell_frac`` of the nominal dwell, rise and
    fall unchanged. The sense switch-over is timed by the waveform controller from the
    pulse start, so the first sample stays at the nominal time and the channel rings
    freely for ``switch_delay_s + (1 - dwell_frac) dwell_s`` before it. The channel is
    healthy; the ring-down's amplitude and phase change.
    ``dwell_frac`` (primary) 0.40 -> 0.10.
foreign_body
    A foreign body (fibre, paper dust, a dried ink flake) stuck to the nozzle plate at
    the nozzle adds a lightly damped mechanical mode that the actuator's pulse excites:
    an extra damped sinusoid of frequency ``f_fb``, damping ratio ``zeta_fb`` and a
    random phase, with ``amplitude`` times the main ring-down's amplitude (envelope at
    the first sample), added to the sensed outflow before the sensor noise.
    ``amplitude`` (primary) 0.20 -> 0.50; ``f_fb`` 600-1200 kHz on the default head;
    ``zeta_fb`` 0.01-0.03. ``f_fb`` is scaled with ``profile.frequency_scale()``: the
    body's mode is a fixed multiple (2.5-5x) of the head's healthy mode, a choice that
    keeps the condition the same kind of test on every head and below every head's
    Nyquist frequency (a physical body's mode would not follow the channel; on the
    default head the scale is 1 and the band is exactly 600-1200 kHz).

``params`` names these draws (float64 (n,) each): ``cut``, ``extra_noise_rel``;
``amplitude``, ``detune``, ``phase``; ``k``, ``r_b``; ``coupling_div``, ``compliance_rel``;
``dwell_frac``; ``amplitude``, ``f_fb``, ``zeta_fb``, ``phase``. Every condition also
returns ``temperature_k`` (the healthy draw's ink temperature, K).
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from typing import NamedTuple

import numpy as np

from ..faults import MECHANISMS, FaultClass
from .channels import draw_channels
from .linear import synthesize_chunk
from .modal import cubic_roots, nominal_rms, ramp_response
from .sensor import adc_quantiser, draw_sensor, noise_std_for_snr, white_noise

__all__ = ["HELDOUT_CONDITIONS", "HeldoutTraces", "simulate_heldout"]

HELDOUT_CONDITIONS = ("poor_contact", "crosstalk", "double_fault", "actuator_damage", "truncated_pulse",
                      "foreign_body")
"""The held-out conditions (evaluation only, never training), in a fixed order."""

_BUBBLE = MECHANISMS[FaultClass.SMALL_AIR_BUBBLE]
_FB_BAND_HZ = (600e3, 1200e3)  # on the default head; scaled by profile.frequency_scale()


class HeldoutTraces(NamedTuple):
    """Traces of one held-out condition.

    Attributes
    ----------
    traces : ndarray of float32, shape (n, n_samples)
        Sensed voltage, V (the profile's sampling, sensor and ADC).
    severity : ndarray of float64, shape (n,)
        In [0, 1]: 0 the mild end of the condition's range, 1 the severe end.
    params : dict of str -> ndarray of float64, shape (n,)
        The condition's physical draws (module docstring), SI units or ratios.
    """

    traces: np.ndarray
    severity: np.ndarray
    params: dict


def _check_severity(severity):
    if severity is None:
        return 0.0, 1.0
    if isinstance(severity, numbers.Real) and not isinstance(severity, bool):
        lo = hi = float(severity)
    else:
        try:
            lo, hi = (float(v) for v in severity)
        except (TypeError, ValueError):
            raise ValueError(f"severity must be None, a number in [0, 1] or a pair (lo, hi), got {severity!r}") from None
    if not (0.0 <= lo <= hi <= 1.0):
        raise ValueError(f"severity must lie in [0, 1] with lo <= hi, got {severity!r}")
    return lo, hi


def _lerp(lo, hi, s):
    return lo + (hi - lo) * s


def _loglerp(lo, hi, s):
    return lo * (hi / lo) ** s


def _modal(ch, rise, dwell, fall, delay, amplitude):
    """Eigenvalues and output coefficients, as :func:`~.modal.modal_solution` with a per-trace dwell and delay (s, (n,))."""
    k_r, k_n, d_r, d_n, b_r, b_n = ch.k_r, ch.k_n, ch.d_r, ch.d_n, ch.b_r, ch.b_n
    p2 = d_r + d_n
    p1 = d_r * d_n + k_r + k_n
    p0 = k_r * d_n + k_n * d_r
    lam = cubic_roots(p2, p1, p0)
    M = b_r[:, None] * (lam + d_n[:, None]) + b_n[:, None] * (lam + d_r[:, None])
    Dp = (3.0 * lam + 2.0 * p2[:, None]) * lam + p1[:, None]
    dwell = np.broadcast_to(np.asarray(dwell, dtype=float), k_r.shape)[:, None]
    t1, t2 = rise, rise + dwell
    t3 = t2 + fall
    ts = t3 + np.broadcast_to(np.asarray(delay, dtype=float), k_r.shape)[:, None]
    g = (ramp_response(lam, ts) - ramp_response(lam, ts - t1)) / rise - (
        ramp_response(lam, ts - t2) - ramp_response(lam, ts - t3)) / fall
    return lam, lam * (g * amplitude[:, None] * M / Dp)


def _envelope(coef):
    """Ring-down amplitude at the first sample (m^3/s, (n,)): twice the pair's modal coefficient."""
    return 2.0 * np.abs(coef[:, 0])


def simulate_heldout(condition, n, *, profile=None, seed=None, severity=None, sample_rate_hz=None,
                     n_samples=None) -> HeldoutTraces:
    """Simulate ``n`` traces of one held-out condition (evaluation only, never training).

    Parameters
    ----------
    condition : str
        One of :data:`HELDOUT_CONDITIONS`.
    n : int
        Number of traces (>= 0).
    profile : HeadProfile, optional
        The head (complete profile); default ``HeadProfile.default()``.
    seed : int, numpy.random.SeedSequence or numpy.random.Generator, optional
        Same seed, same arguments: bit-identical output. The healthy part of every
        trace is that of ``profile.simulate({"healthy_nozzle": n}, seed=seed)``.
    severity : float or (float, float), optional
        ``None``: uniform over [0, 1] (the whole range); a number in [0, 1]: that
        severity; a pair ``(lo, hi)``: uniform over it. 0 is the mild end of the
        condition's range, 1 the severe end (module docstring).
    sample_rate_hz : float, optional
        Sample rate, Hz (default the profile's).
    n_samples : int, optional
        Samples per trace (default the profile's).

    Returns
    -------
    HeldoutTraces
        ``traces`` float32 (n, n_samples) V, ``severity`` float64 (n,), ``params``.

    Raises
    ------
    ValueError
        Unknown ``condition``; ``n`` not a non-negative int; ``severity`` outside
        [0, 1]; ``sample_rate_hz`` or ``n_samples`` not positive; a ``profile`` that
        is not a HeadProfile; a sample rate whose Nyquist frequency is below the
        condition's highest mode (the message names the argument).
    """
    from ..head_profile import HeadProfile  # the profile module imports the simulation package

    if not isinstance(condition, str) or condition not in HELDOUT_CONDITIONS:
        raise ValueError(f"condition must be one of {HELDOUT_CONDITIONS}, got {condition!r}")
    if isinstance(n, bool) or not isinstance(n, numbers.Integral) or n < 0:
        raise ValueError(f"n must be a non-negative int, got {n!r}")
    n = int(n)
    s_lo, s_hi = _check_severity(severity)
    if profile is None:
        profile = HeadProfile.default()
    elif not isinstance(profile, HeadProfile):
        raise ValueError(f"profile must be a HeadProfile, got {type(profile).__name__}")
    fs = profile.sample_rate_hz if sample_rate_hz is None else sample_rate_hz
    if isinstance(fs, bool) or not isinstance(fs, numbers.Real) or not math.isfinite(fs) or fs <= 0:
        raise ValueError(f"sample_rate_hz must be a positive finite number of Hz, got {sample_rate_hz!r}")
    fs = float(fs)
    ns = profile.n_samples if n_samples is None else n_samples
    if isinstance(ns, bool) or not isinstance(ns, numbers.Integral) or ns <= 0:
        raise ValueError(f"n_samples must be a positive int, got {n_samples!r}")
    ns = int(ns)

    base = profile.channel_params()
    drive = profile.drive
    spreads = profile.spreads()
    scale = profile.frequency_scale()
    if condition == "foreign_body" and _FB_BAND_HZ[1] * scale >= fs / 2:
        raise ValueError(f"sample_rate_hz {fs:g} Hz is too low for foreign_body: its mode reaches "
                         f"{_FB_BAND_HZ[1] * scale:g} Hz (Nyquist {fs / 2:g} Hz)")

    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    crng = rng.spawn(1)[0]  # the condition's own stream: does not advance rng
    sev = _lerp(s_lo, s_hi, crng.random(n))

    # the healthy draws, in simulate()'s order: channels, then sensor gain and offset
    cls = FaultClass.SMALL_AIR_BUBBLE if condition == "double_fault" else FaultClass.HEALTHY_NOZZLE
    bubble_u = crng.random(n)  # drawn for every condition: one stream layout
    r_b = _lerp(_BUBBLE.low, _BUBBLE.high, bubble_u)
    ch = draw_channels([(cls, n)], base, spreads, rng,
                       {cls: r_b} if condition == "double_fault" else None)
    nominal_gain = profile.sensor_gain_v_per_m3s
    gain, offset = draw_sensor(rng, n, spreads, nominal_gain)
    offset = offset + profile.sensor_offset_v
    amplitude = drive.amplitude_v * ch.drive
    noise_std = noise_std_for_snr(spreads, nominal_rms(base, drive, ns, fs) * nominal_gain)
    lsb, quant = adc_quantiser(spreads)

    params = {"temperature_k": np.asarray(ch.params["temperature_k"], dtype=float)}
    extra_std = np.zeros(n)
    dwell = drive.dwell_s
    sig_scale = gain / lsb
    added = None  # (lam, coef) of an extra signal in m^3/s

    if condition == "poor_contact":
        cut = _loglerp(5.0, 20.0, sev)
        rel = _lerp(0.5, 2.0, crng.random(n))
        sig_scale = sig_scale / cut
        extra_std = rel * noise_std
        params.update(cut=cut, extra_noise_rel=rel)
    elif condition == "double_fault":
        k = _lerp(3.0, 6.0, sev)
        ch = dataclasses.replace(ch, d_n=ch.d_n * k, mu_nozzle=ch.mu_nozzle * k)
        params.update(k=k, r_b=r_b)
    elif condition == "actuator_damage":
        div = _loglerp(3.0, 10.0, sev)
        rel = _lerp(0.20, 0.50, crng.random(n))
        p = ch.params
        B_t = p["B_t"] + p["B_act"] * rel
        b = p["b"] / div
        k_r = 1.0 / (p["I_r"] * B_t)
        k_n = 1.0 / (p["I_n"] * B_t)
        ch = dataclasses.replace(ch, k_r=k_r, k_n=k_n, b_r=b * k_r, b_n=b * k_n)
        params.update(coupling_div=div, compliance_rel=rel)
    elif condition == "truncated_pulse":
        frac = _lerp(0.40, 0.10, sev)
        dwell = drive.dwell_s * frac
        params.update(dwell_frac=frac)

    # the sensing switch-over is timed by the waveform controller from the pulse start: a pulse cut
    # short leaves a longer free ring-down before the first sample
    delay = drive.switch_delay_s + (drive.dwell_s - dwell)
    lam, coef = _modal(ch, drive.rise_s, dwell, drive.fall_s, delay, amplitude)

    if condition == "crosstalk":
        amp = _lerp(0.30, 1.00, sev)
        det = _lerp(0.03, 0.12, crng.random(n)) * np.where(crng.random(n) < 0.5, -1.0, 1.0)
        nb = draw_channels([(FaultClass.HEALTHY_NOZZLE, n)], base, spreads, crng)
        nlam, ncoef = _modal(nb, drive.rise_s, drive.dwell_s, drive.fall_s, drive.switch_delay_s,
                             drive.amplitude_v * nb.drive)
        phase = 2 * np.pi * crng.random(n)
        nlam = nlam * (1.0 + det)[:, None]
        rot = np.stack([np.exp(1j * phase), np.exp(-1j * phase), np.ones(n)], axis=1)
        ncoef = ncoef * rot * (amp * _envelope(coef) / _envelope(ncoef))[:, None]
        added = (nlam, ncoef)
        params.update(amplitude=amp, detune=det, phase=phase)
    elif condition == "foreign_body":
        amp = _lerp(0.20, 0.50, sev)
        f = _lerp(*_FB_BAND_HZ, crng.random(n)) * scale
        zeta = _lerp(0.01, 0.03, crng.random(n))
        phase = 2 * np.pi * crng.random(n)
        w = 2 * np.pi * f
        pole = -zeta * w + 1j * w * np.sqrt(1.0 - zeta**2)
        flam = np.stack([pole, np.conj(pole), np.full(n, -w)], axis=1)
        c = 0.5 * amp * _envelope(coef) * np.exp(1j * phase)
        fcoef = np.stack([c, np.conj(c), np.zeros(n, dtype=complex)], axis=1)
        added = (flam, fcoef)
        params.update(amplitude=amp, f_fb=f, zeta_fb=zeta, phase=phase)

    traces = np.empty((n, ns), dtype=np.float32)
    if n == 0:
        return HeldoutTraces(traces, sev, {k: np.asarray(v, dtype=float) for k, v in params.items()})
    # the noise-free sensed signal (LSB units when quantising), then the sensor chain as in simulate()
    synthesize_chunk(lam, coef, sig_scale, offset / lsb, ns, fs, traces, 0.0, rng, None)
    if added is not None:
        extra = np.empty_like(traces)
        synthesize_chunk(added[0], added[1], sig_scale, np.zeros(n), ns, fs, extra, 0.0, rng, None)
        traces += extra
    if noise_std > 0:
        traces += white_noise(rng, (n, ns), noise_std / lsb)
    if condition == "poor_contact":
        traces += white_noise(crng, (n, ns), 1.0) * (extra_std / lsb).astype(np.float32)[:, None]
    if quant is not None:
        np.rint(traces, out=traces)
        np.clip(traces, quant[0], quant[1], out=traces)
        traces *= np.float32(lsb)
    return HeldoutTraces(traces, sev, {k: np.asarray(v, dtype=float) for k, v in params.items()})
