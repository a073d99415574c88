"""Screening of trace rows before classification: which rows can be judged at all.

A printer controller's frame can hold rows that carry no information about the
nozzle: a dead sensing channel (flat), an overdriven one (clipped at the ADC
rails), a transfer fault (NaN / Inf), or a corrupted one (a finite sample far
beyond what the sensor's ADC can produce, e.g. 1e30 V). Such rows are labelled *invalid* with
a reason instead of being classified; the rest of the frame is unaffected.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["CLIP_S", "INVALID_REASONS", "RINGING_MIN_SAMPLES_PER_PERIOD", "RINGING_MIN_SNR",
           "clip_run_samples", "rings_above_noise", "screen_traces",
           "screening_codes", "screening_settings", "verdicts"]

#: Shortest plateau at a row's extreme that reads as ADC clipping, s (5 samples at 10 MHz).
CLIP_S = 0.5e-6
#: A clipped run is never shorter than this many samples, whatever the sample rate. With 3, a
#: 5 MHz head's 10-bit ADC repeated one code three times at the peak of 1.0 % of its healthy
#: traces (tests/foreign_head.py's h5, 3000 healthy traces, seed 2; helper-87): 0.05 % with 4.
MIN_CLIP_RUN = 4

#: Reason codes of invalid rows. The first four are :func:`screen_traces`'s, in the order
#: of precedence used when several apply; ``"non_finite_features"`` is a row that passed
#: screening but whose features came out NaN or Inf (:func:`inkdiag_core.label_traces`).
INVALID_REASONS = ("non_finite", "out_of_range", "flat", "clipped", "non_finite_features")


#: A trace whose AC rms is at most this many times its own white-noise level does not ring (:func:`rings_above_noise`).
#: White noise reads at most 1.53 (20,000 rows of 64 samples; 1.17 of 512); healthy jetting traces of the five heads
#: of ``tests/foreign_head.py`` 18 and more, OK-check ones 14 and more (30 dB).
RINGING_MIN_SNR = 2.0
#: :func:`rings_above_noise` checks heads sampled at this many samples or more per period of their healthy mode:
#: the second differences of a ringing sampled more sparsely are its own, not noise's (a noise-free ringing of 10
#: samples a period reads 6.4, of 6 samples 2.4).
RINGING_MIN_SAMPLES_PER_PERIOD = 10

#: A screened row's reason by its code (0: valid).
_REASONS = np.array(("",) + INVALID_REASONS[:4], dtype=object)


def rings_above_noise(traces, *, sample_rate_hz: float, mode_hz: float | None = None,
                      min_snr: float = RINGING_MIN_SNR) -> np.ndarray:
    """Rows that ring above their own noise: AC rms more than ``min_snr`` times their white-noise level.

    The noise level is the standard deviation of a row's second differences over sqrt(6), white
    noise's own; a ringing at a twentieth of the sample rate or below adds a few per cent of its rms to
    it. A head sampled at fewer than :data:`RINGING_MIN_SAMPLES_PER_PERIOD` samples a period of
    ``mode_hz`` is not checked (every row rings). Not part of :func:`screen_traces`: a nozzle that does
    not ring (an empty channel's weak ringing, a dead actuator) is a finding for fdi; calibration and
    baselines, which take rows as healthy, leave such rows out (a nozzle that did not fire).

    Parameters
    ----------
    traces : array_like, shape (n, n_samples)
        V; finite (screen first).
    sample_rate_hz : float
        Hz.
    mode_hz : float, optional
        The head's healthy mode, Hz; None: the median spectral peak of the rows that pass the test
        (none passes: not checked).
    min_snr : float

    Returns
    -------
    ndarray of bool, shape (n,)
    """
    y = np.asarray(traces, dtype=np.float64)
    every = np.ones(y.shape[0], bool)
    if mode_hz is not None and not mode_hz * RINGING_MIN_SAMPLES_PER_PERIOD <= sample_rate_hz:
        return every
    noise = np.std(np.diff(y, n=2, axis=1), axis=1) / math.sqrt(6.0)
    rings = np.std(y, axis=1) > min_snr * noise
    if mode_hz is None:
        if not rings.any():
            return every
        spec = np.abs(np.fft.rfft(y[rings] - y[rings].mean(axis=1, keepdims=True), axis=1))
        mode_hz = float(np.median(np.argmax(spec[:, 1:], axis=1) + 1)) * sample_rate_hz / y.shape[1]
        if not mode_hz * RINGING_MIN_SAMPLES_PER_PERIOD <= sample_rate_hz:
            return every
    return rings


def clip_run_samples(sample_rate_hz: float = 10e6, clip_s: float = CLIP_S) -> int:
    """The clipped-run length in samples at a sample rate: ``max(MIN_CLIP_RUN, ceil(clip_s * sample_rate_hz))``.

    5 samples at 10 MHz (the length tuned there), 10 at 20 MHz, 4 at 5 MHz
    (never fewer than :data:`MIN_CLIP_RUN`, 4: with fewer, a quantised healthy
    peak repeating one ADC code reads as clipped).

    Parameters
    ----------
    sample_rate_hz : float
        Hz.
    clip_s : float
        Plateau duration, s.

    Returns
    -------
    int
    """
    fs, d = float(sample_rate_hz), float(clip_s)
    if not (math.isfinite(fs) and fs > 0 and math.isfinite(d) and d > 0):
        raise ValueError(f"sample_rate_hz and clip_s must be positive, got {sample_rate_hz!r} Hz, {clip_s!r} s")
    return max(MIN_CLIP_RUN, math.ceil(d * fs - 1e-9))


def screen_traces(traces, *, flat_tol: float = 1e-6, clip_run: int | None = None, max_abs_v: float | None = None,
                  sample_rate_hz: float = 10e6, clip_s: float = CLIP_S):
    """Find the rows of a frame that cannot be classified, and why.

    Parameters
    ----------
    traces : array_like, shape (n, n_samples)
        Sensor samples, V.
    flat_tol : float
        A row whose peak-to-peak range is at most this (V) is *flat*.
    clip_run : int, optional
        A row with ``clip_run`` or more consecutive samples exactly at its
        maximum (or minimum) value, sitting on a plateau, is *clipped*: an ADC
        saturates there, a damped oscillation does not. None (default):
        :func:`clip_run_samples` of ``sample_rate_hz`` and ``clip_s``, i.e. a
        duration: 0.5 us, 5 samples at 10 MHz (with 3 there, 12-bit quantisation
        flagged 0.2 % of simulated healthy and faulty traces whose flat peak
        repeats one ADC code). An explicit count of samples overrides.
    max_abs_v : float, optional
        The largest sample magnitude a sensor can produce, V (above its ADC's
        range). A finite row with any ``|sample| > max_abs_v`` is
        *out_of_range*: no sensor produced it, and its features could overflow.
        None: no such check.
    sample_rate_hz : float
        Sample rate of the traces, Hz (for the clipped-run duration).
    clip_s : float
        Clipped-run duration, s.

    Returns
    -------
    valid : ndarray of bool, shape (n,)
    reasons : ndarray of str (object), shape (n,)
        ``""`` for valid rows, else one of :data:`INVALID_REASONS`.
    """
    return verdicts(screening_codes(traces, flat_tol=flat_tol, clip_run=clip_run, max_abs_v=max_abs_v,
                                    sample_rate_hz=sample_rate_hz, clip_s=clip_s))


def screening_codes(traces, *, flat_tol: float = 1e-6, clip_run: int | None = None, max_abs_v: float | None = None,
                    sample_rate_hz: float = 10e6, clip_s: float = CLIP_S):
    """:func:`screen_traces`' verdicts as codes: uint8 (n,), 0 valid, else 1 + the reason's index in
    :data:`INVALID_REASONS` (:func:`verdicts` turns them into ``(valid, reasons)``). Same parameters."""
    x = np.asarray(traces)
    if x.ndim != 2:
        raise ValueError(f"traces must be 2-D (n, n_samples), got shape {x.shape}")
    clip_run = screening_settings(flat_tol=flat_tol, clip_run=clip_run, max_abs_v=max_abs_v,
                                  sample_rate_hz=sample_rate_hz, clip_s=clip_s)[2]
    if x.shape[0] == 0 or x.shape[1] == 0:
        return np.zeros(x.shape[0], np.uint8)
    return _screen_codes(x, flat_tol, max_abs_v, clip_run)


def screening_settings(*, flat_tol: float = 1e-6, clip_run: int | None = None, max_abs_v: float | None = None,
                       sample_rate_hz: float = 10e6, clip_s: float = CLIP_S) -> tuple:
    """:func:`screen_traces`'s settings checked, in the order the screening kernel takes them
    (:func:`inkdiag_core._kernels.screen_codes`).

    Parameters are :func:`screen_traces`'s.

    Returns
    -------
    flat_tol : float
        V.
    max_abs_v : float
        V; ``inf`` for no range check.
    clip_run : int
        Samples.
    """
    if clip_run is None:
        clip_run = clip_run_samples(sample_rate_hz, clip_s)
    if clip_run < 2:
        raise ValueError(f"clip_run must be >= 2, got {clip_run}")
    if max_abs_v is not None and not max_abs_v > 0:
        raise ValueError(f"max_abs_v must be > 0 V or None, got {max_abs_v!r}")
    return float(flat_tol), math.inf if max_abs_v is None else float(max_abs_v), int(clip_run)


def verdicts(code):
    """``(valid, reasons)`` of :func:`screen_traces` from the rows' screening codes (uint8, (n,))."""
    return code == 0, _REASONS[code]


def _screen_codes(x, flat_tol, max_abs_v, clip_run):
    """Each row's reason code (0 valid, else 1 + its index in :data:`INVALID_REASONS`).

    The compiled kernel (:func:`inkdiag_core._kernels.screen_codes`: two loops per row) for
    float32/float64 rows, :func:`_screen_codes_numpy` (numpy passes) for any other dtype
    (ADC counts); the same codes.
    """
    if x.dtype in (np.float32, np.float64):
        from ._kernels import screen_codes

        return screen_codes(x, flat_tol, np.inf if max_abs_v is None else max_abs_v, clip_run)
    return _screen_codes_numpy(x, flat_tol, max_abs_v, clip_run)


def _screen_codes_numpy(x, flat_tol, max_abs_v, clip_run):
    """:func:`_screen_codes` in numpy passes, for any numeric dtype of a non-empty ``x`` (n, m >= 1)."""
    # One max and one min pass find the non-finite rows too: NaN propagates through both,
    # +Inf is a row's max and -Inf its min.
    hi = x.max(axis=1)
    lo = x.min(axis=1)
    finite = np.isfinite(hi) & np.isfinite(lo)
    # The range in float64: an integer dtype wraps (int16 32767 - -32768 is -1, "flat") and
    # float32 overflows (3.4e38 - -3.4e38); inf - inf in non-finite rows is NaN, not flat.
    hi64, lo64 = hi.astype(np.float64), lo.astype(np.float64)
    with np.errstate(invalid="ignore", over="ignore"):
        flat = finite & ((hi64 - lo64) <= flat_tol)
    out = np.zeros(x.shape[0], bool)
    if max_abs_v is not None:
        out = finite & ((hi64 > max_abs_v) | (lo64 < -max_abs_v))
    if not finite.all():
        hi, lo = np.where(finite, hi, np.nan), np.where(finite, lo, np.nan)  # matches no sample
    at_hi, at_lo = x == hi[:, None], x == lo[:, None]
    # Only rows with clip_run samples at an extreme can hold such a run (few do); bytes
    # summed into uint16 count them fastest where a row is too short to overflow it.
    count = np.uint16 if x.shape[1] < 2**16 else np.intp
    cand = np.flatnonzero((np.add.reduce(at_hi.view(np.uint8), axis=1, dtype=count) >= clip_run)
                          | (np.add.reduce(at_lo.view(np.uint8), axis=1, dtype=count) >= clip_run))
    clipped = np.zeros(x.shape[0], bool)
    clipped[cand] = _has_run(at_hi[cand], clip_run) | _has_run(at_lo[cand], clip_run)
    # each row's first reason in INVALID_REASONS' order of precedence
    return np.where(~finite, 1, np.where(out, 2, np.where(flat, 3, np.where(clipped, 4, 0)))).astype(np.uint8)


def _has_run(mask: np.ndarray, run: int) -> np.ndarray:
    """Rows of a boolean (n, m) mask holding ``run`` consecutive True values."""
    if mask.shape[1] < run:
        return np.zeros(mask.shape[0], bool)
    acc = mask[:, : mask.shape[1] - run + 1].copy()
    for k in range(1, run):  # a few whole-array ANDs, not a loop over rows
        acc &= mask[:, k : mask.shape[1] - run + 1 + k]
    return acc.any(axis=1)
