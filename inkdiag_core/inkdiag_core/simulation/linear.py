"""The linear fault simulator: self-sensing traces of the 12 classes from the linear model.

What one trace is
-----------------
1. The channel starts at rest. The piezo is driven by a trapezoidal pulse
   (:class:`DriveWaveform`: rise, dwell, fall; volts), which displaces
   ``b u(t)`` into the chamber (:mod:`inkdiag_core.model`).
2. The piezo cannot sense while it actuates: sensing starts after the pulse
   ends plus a switching delay. The first sample of the trace is at that
   instant, ``t = 0`` of the trace; sample ``k`` is at ``k / sample_rate_hz``.
3. The self-sensing signal is proportional to the total outflow of the chamber
   ``y = V_r' + V_n' = C x`` (m^3/s). The sense amplifier maps it to volts,
   ``v = gain * y + offset``, white noise is added and an ADC quantises it.

How it is computed: exactly, vectorised, no ODE solver (the modal solution of
:mod:`inkdiag_core.simulation.modal`, whose docstring gives the derivation).

The per-trace physical spreads (all from physics, none from the label) are
described in :mod:`inkdiag_core.simulation.channels`; the sensor chain in
:mod:`inkdiag_core.simulation.sensor`.
"""

from __future__ import annotations

import numpy as np

from ..faults import DRIED_CLASSES, MECHANISMS, FaultClass, as_fault_class
from ..model import InkChannelParams
from .channels import PHYSICAL_CONSTANTS, DriveWaveform, Spreads, draw_channels, observable_A
from .inputs import check_counts, check_positive_float, check_positive_int, check_severity, prepare_run
from .modal import dominant_mode, modal_solution, nominal_rms
from .result import SimulationResult, empty_result
from .sensor import adc_quantiser, draw_sensor, noise_std_for_snr, snr_db, white_noise

__all__ = ["simulate", "simulate_nozzles"]


def simulate(
    counts,
    *,
    sample_rate_hz: float = 10e6,
    n_samples: int = 512,
    seed=0,
    spreads: Spreads | None = None,
    drive: DriveWaveform | None = None,
    base_params: InkChannelParams | None = None,
    severity=None,
    chunk_size: int = 4000,
    frame_seed=None,
    draw_order=None,
    sensor_gain_v_per_m3s: float | None = None,
    sensor_offset_v: float = 0.0,
) -> SimulationResult:
    """Simulate self-sensing traces of the requested fault classes.

    Parameters
    ----------
    counts : mapping of FaultClass (or its string value) -> int
        Number of traces per class. Rows come out grouped by class in
        :class:`FaultClass` declaration order.
    sample_rate_hz : float
        ADC sample rate, Hz. Must exceed twice the highest mode of the
        requested classes (nominal channel, over the severity range).
    n_samples : int
        Samples per trace.
    seed : int or numpy.random.Generator
        Seed of ``numpy.random.default_rng``; the same seed, counts and
        options give bit-identical results.
    spreads : Spreads, optional
        Physical variation; default :class:`Spreads` (calibrated).
    drive : DriveWaveform, optional
        Actuation pulse; default :class:`DriveWaveform`.
    base_params : InkChannelParams, optional
        Nominal channel (default: the 237 kHz channel).
    severity : mapping of FaultClass -> array_like, optional
        Fixed severities instead of uniform draws, one per trace of that class
        (for instance nozzle viscosity factors of a drying sweep, for the
        estimation work). Units and meaning as in ``MECHANISMS[cls].severity``;
        values outside the class's range are allowed (physical bounds apply).
        The random draws are made all the same, so the other traces do not change.
    chunk_size : int
        Traces synthesised per block (memory/speed only; the results do not
        depend on it when ``n_samples`` is a multiple of 4).
    frame_seed : int or numpy.random.Generator, optional
        Stream of what changes from one measurement of the same nozzles to the
        next: the ink temperature and the sensor noise. ``None`` (default) draws
        them from ``seed``'s stream with everything else; given, ``seed`` alone
        fixes the nozzles (geometry, piezo, drive, sensor gain and offset, fault
        severity), so calls with one ``seed`` and different ``frame_seed`` are
        successive frames of the same head.
    draw_order : array_like of int, shape (n,), optional
        A permutation of the rows: row ``r`` takes the per-trace draws at
        position ``draw_order[r]`` of ``seed``'s stream (default: its own).
        :func:`simulate_nozzles` passes its nozzle order, so that a nozzle's
        tolerances follow the nozzle rather than its place among its class's
        rows.
    sensor_gain_v_per_m3s : float, optional
        Nominal sense gain, V per (m^3/s) (default: the default head's,
        ``PHYSICAL_CONSTANTS["sensor_gain_v_per_m3s"]``); each channel's gain
        spreads around it.
    sensor_offset_v : float
        Mean sense offset, V; each channel's offset spreads around it.

    Returns
    -------
    SimulationResult
        ``traces`` float32 (n, n_samples) in volts, ``labels``, and per-trace truth.

    Raises
    ------
    ValueError
        Bad ``counts`` (not a mapping, unknown class, negative or non-integer
        count), non-positive ``n_samples`` or ``sample_rate_hz``, a sample rate
        below twice the highest mode, non-positive physical parameters, or a
        ``draw_order`` that is not a permutation of the rows.
    """
    classes = check_counts(counts)
    fs = check_positive_float("sample_rate_hz", sample_rate_hz)
    n_samples = check_positive_int("n_samples", n_samples)
    chunk_size = check_positive_int("chunk_size", chunk_size)
    spreads, drive, base, rng, labels = prepare_run(classes, fs, spreads, drive, base_params, seed)
    n = labels.size
    if n == 0:
        return empty_result(labels, fs, n_samples)

    if frame_seed is None:
        frame_rng = rng
    else:
        frame_rng = frame_seed if isinstance(frame_seed, np.random.Generator) else np.random.default_rng(frame_seed)
    perm = None
    if draw_order is not None:
        perm = np.asarray(draw_order)
        if perm.shape != (n,) or perm.dtype.kind not in "iu" or not np.array_equal(np.sort(perm), np.arange(n)):
            raise ValueError(f"draw_order must be a permutation of range({n}), got shape {perm.shape}")
    ch = draw_channels(classes, base, spreads, rng, check_severity(severity, classes),
                        frame_rng=frame_rng, perm=perm)
    amplitude = drive.amplitude_v * ch.drive
    nominal_gain = (PHYSICAL_CONSTANTS["sensor_gain_v_per_m3s"] if sensor_gain_v_per_m3s is None
                    else check_positive_float("sensor_gain_v_per_m3s", sensor_gain_v_per_m3s))
    gain, offset = draw_sensor(rng, n, spreads, nominal_gain, perm)
    if not np.isfinite(sensor_offset_v):
        raise ValueError(f"sensor_offset_v must be a finite number of volts, got {sensor_offset_v!r}")
    if sensor_offset_v:
        offset = offset + float(sensor_offset_v)

    lam, coef, x0 = modal_solution(ch, drive, amplitude)
    freq, zeta = dominant_mode(lam)

    nominal_rms_v = nominal_rms(base, drive, n_samples, fs) * nominal_gain
    noise_std = noise_std_for_snr(spreads, nominal_rms_v)

    traces = np.empty((n, n_samples), dtype=np.float32)
    lsb, quant = adc_quantiser(spreads)
    sig_rms = np.empty(n)
    for start in range(0, n, chunk_size):
        sl = slice(start, min(n, start + chunk_size))
        sig_rms[sl] = synthesize_chunk(
            lam[sl], coef[sl], gain[sl] / lsb, offset[sl] / lsb, n_samples, fs, traces[sl],
            noise_std / lsb, frame_rng, quant,
        )
    if quant is not None:
        traces *= np.float32(lsb)
    sig_rms *= lsb

    snr = snr_db(sig_rms, noise_std)

    params = dict(ch.params)
    params["drive_v"] = amplitude
    return SimulationResult(
        traces=traces, labels=labels, sample_rate_hz=fs, mu_nozzle=ch.mu_nozzle, mu=ch.mu,
        fm=ch.fm, frequency_hz=freq, damping_ratio=zeta, x0=x0,
        A=observable_A(ch.k_r, ch.k_n, ch.d_r, ch.d_n),
        sensor_gain=gain, sensor_offset=offset, snr_db=snr, params=params,
        noise_std_v=noise_std,
    )


def simulate_nozzles(classes, *, mu_nozzle=None, sample_rate_hz: float = 10e6, n_samples: int = 512,
                     seed=0, spreads: Spreads | None = None, drive: DriveWaveform | None = None,
                     base_params: InkChannelParams | None = None, frame_seed=None,
                     sensor_gain_v_per_m3s: float | None = None, sensor_offset_v: float = 0.0) -> SimulationResult:
    """One trace per nozzle, in the nozzles' order: a frame of a printhead.

    Nozzle ``i``'s own draws (geometry, piezo, drive, sensor gain and offset,
    and where its fault's severity falls in the class's range) depend only on
    ``seed`` and ``i``, not on the other nozzles' classes: with one ``seed``
    and a new ``frame_seed`` per call, successive calls are successive frames
    of one head whose nozzles keep their tolerances while their conditions
    change (a nozzle drying from slightly to deeply dried stays the same
    nozzle).

    Parameters
    ----------
    classes : sequence of FaultClass (or their string values), length n
        The condition of each nozzle.
    mu_nozzle : array_like, shape (n,), optional
        Nozzle ink viscosity (Pa s, at the nominal ink temperature) of the
        dried nozzles, for a drying that progresses over time; it enters as
        the factor ``mu_nozzle / base_params.mu``, which each trace's ink
        temperature then scales like the channel's ink. ``NaN`` (or no array)
        draws it from the class's range as :func:`simulate` does. Ignored for
        the other classes.
    sample_rate_hz, n_samples, seed, spreads, drive, base_params, frame_seed
        As in :func:`simulate` (``seed``: the head; ``frame_seed``: the
        measurement's ink temperature and sensor noise).
    sensor_gain_v_per_m3s, sensor_offset_v
        As in :func:`simulate`: the head's nominal sense gain, V per (m^3/s)
        (default: the default head's), and mean sense offset, V.

    Returns
    -------
    SimulationResult
        Row ``i`` is nozzle ``i``.
    """
    classes = [as_fault_class(c, "classes") for c in classes]
    n = len(classes)
    if n == 0:
        raise ValueError("classes must name at least one nozzle")
    base = InkChannelParams() if base_params is None else base_params
    mu = np.full(n, np.nan) if mu_nozzle is None else np.asarray(mu_nozzle, dtype=float).reshape(-1)
    if mu.shape != (n,):
        raise ValueError(f"mu_nozzle must have one value per nozzle ({n}), got shape {np.shape(mu_nozzle)}")
    if np.any(mu[np.isfinite(mu)] <= 0):
        raise ValueError("mu_nozzle must be positive (Pa s) where given")
    labels = np.array([c.value for c in classes])
    rng = np.random.default_rng(seed)
    # one quantile per nozzle for a dried class's drawn viscosity, whatever the classes
    u_dried = np.random.default_rng(rng.integers(2**63)).random(n)
    order, counts, severity = [], {}, {}
    for c in FaultClass:  # simulate() returns rows grouped in declaration order
        rows = np.flatnonzero(labels == c.value)
        if rows.size == 0:
            continue
        order.append(rows)
        counts[c] = rows.size
        if c in DRIED_CLASSES and np.isfinite(mu[rows]).any():
            m = MECHANISMS[c]
            k = mu[rows] / base.mu
            drawn = m.low + (m.high - m.low) * u_dried[rows]
            severity[c] = np.where(np.isfinite(k), k, drawn)
    perm = np.concatenate(order)
    # grouped row r is nozzle perm[r]: it takes the nozzle's own position in the draws
    res = simulate(counts, sample_rate_hz=sample_rate_hz, n_samples=n_samples, seed=rng,
                   spreads=spreads, drive=drive, base_params=base, severity=severity or None,
                   frame_seed=frame_seed, draw_order=perm, sensor_gain_v_per_m3s=sensor_gain_v_per_m3s,
                   sensor_offset_v=sensor_offset_v)
    inverse = np.empty(n, dtype=np.intp)
    inverse[perm] = np.arange(n)
    return res.take(inverse)


def synthesize_chunk(lam, coef, scale, offset, n_samples, fs, out, noise_std, rng, quant):
    """Write one chunk of traces into ``out`` (m, n_samples), float32.

    The noise-free signal is ``scale * y`` with ``y[k] = s[k] + q[k]``: the
    pair (columns 0, 1 of ``lam``) by the exact second-order recurrence
    ``s[k+1] = P s[k] - Q s[k-1]`` with ``P = z0 + z1``, ``Q = z0 z1`` (real
    for a conjugate or a real pair), the real mode by ``q[k+1] = z2 q[k]``;
    float64, vectorised over the chunk. Then ``offset`` and white noise of
    std ``noise_std`` are added and, if ``quant = (qlo, qhi)``, the result is
    rounded and clipped (all in the caller's units, LSB when quantising).

    Returns
    -------
    rms : ndarray, shape (m,)
        RMS of the zero-mean part of the noise-free ``scale * y``.
    """
    z = np.exp(lam / fs)
    c = coef * scale[:, None]
    P = (z[:, 0] + z[:, 1]).real
    Q = (z[:, 0] * z[:, 1]).real
    z2 = z[:, 2].real
    m = lam.shape[0]
    # time-major buffer; a row length that is not a multiple of a cache way
    # keeps the final transpose fast
    width = m + 1 if m % 16 == 0 else m
    buf = np.empty((n_samples, width))[:, :m]
    s_prev = (c[:, 0] + c[:, 1]).real
    s_cur = (c[:, 0] * z[:, 0] + c[:, 1] * z[:, 1]).real
    q = c[:, 2].real.copy()
    buf[0] = s_prev + q
    tmp = np.empty(m)
    for k in range(1, n_samples):
        np.multiply(q, z2, out=q)
        np.add(s_cur, q, out=buf[k])
        # s_next = P s_cur - Q s_prev, computed into s_prev's storage
        np.multiply(Q, s_prev, out=tmp)
        np.multiply(P, s_cur, out=s_prev)
        np.subtract(s_prev, tmp, out=s_prev)
        s_prev, s_cur = s_cur, s_prev
    mean = buf.sum(axis=0) / n_samples
    rms = np.sqrt(np.maximum(np.einsum("ij,ij->j", buf, buf) / n_samples - mean**2, 0.0))
    buf += offset
    out[...] = buf.T
    if noise_std > 0:
        out += white_noise(rng, (m, n_samples), noise_std)
    if quant is not None:
        np.rint(out, out=out)
        np.clip(out, quant[0], quant[1], out=out)
    return rms
