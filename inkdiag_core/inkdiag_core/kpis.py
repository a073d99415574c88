"""Key performance indicators (KPIs) of self-sensing traces (thesis sections 3.3-3.4).

Each trace is modelled as one exponentially damped sinusoid on a DC level,

    y[k] = dc + A * exp(-zeta * w0 * t_k) * cos(w_d * t_k + phi),
    w_d = w0 * sqrt(1 - zeta**2),   t_k = k / sample_rate_hz,   k = 0 .. n_samples - 1,

and :func:`extract_kpis` returns, per trace, the seven KPIs of :data:`KPI_NAMES`.
:func:`reconstruct` rebuilds the model trace from them (thesis Figure 8).
:class:`KpiExtractor` wraps :func:`extract_kpis` as a scikit-learn transformer so that a
whole fault classifier is one ``Pipeline``.

Method
------
The fit is a least-squares fit done in the frequency domain, batched over traces:

1. one real FFT of every trace (``scipy.fft.rfft``, in the input precision);
2. the dominant FFT bin (largest ``|Y[m]|``, ``m >= 1``) selects a window of
   ``WINDOW_BINS`` consecutive bins;
3. the DFT of a damped sinusoid has a closed form (a finite geometric series),
   ``Y[m] = (C G_m(z) + conj(C) G_m(conj(z))) / 2`` with ``z = exp(-sigma + i omega)``
   (per-sample units), ``C = A exp(i phi)`` and
   ``G_m(z) = (1 - z**N) / (1 - z exp(-2 pi i m / N))``; the DC level only enters bin 0;
4. multiplying by the denominator makes the window bins linear in the unknowns
   (a frequency-domain Prony / equation-error fit), which gives the initial ``(omega, sigma)``;
5. Gauss-Newton steps of variable projection (``C`` solved by linear least squares for
   each ``(omega, sigma)``) refine the exact, not linearised, model on the window bins
   (``N_ITER``, one by default);
6. the DC level follows from bin 0 minus the fitted sinusoid's contribution.

Restricting the fit to the bins around the dominant peak makes the cost of each iteration
independent of the trace length, keeps other modes and out-of-band noise out of the
fit, and means that on a multi-mode trace the KPIs describe the mode with the largest FFT
peak. The FFT is one batched ``rfft``; every step after it runs compiled, one trace at a time
in one call (:func:`inkdiag_core._kernels.kpis_of_spectra`, numba; :func:`_fit_spectra_numpy`,
batched numpy, is its reference), the window fit
(:func:`inkdiag_core._kernels.fit_windows`) with :func:`inkdiag_core.spectral_fit.fit_windows`
(numpy, batched) as its reference: the two agree to
~1e-11 relative on the simulator's traces (an ill-conditioned fit, such as a step's, moves as
much in either under a 1e-15 change of its input), and a trace's KPIs never depend on its batch.
"""

import numbers

import numpy as np
import scipy.fft
from sklearn.base import BaseEstimator, TransformerMixin
from sklearn.utils.validation import check_is_fitted, validate_data

from . import checks
from .spectral_fit import WINDOW_BINS
from .checks import InputError

__all__ = [
    "KPI_NAMES",
    "MIN_KPI_SAMPLES",
    "MIN_SAMPLES",
    "InvalidTraceError",
    "KpiExtractor",
    "extract_kpis",
    "kpis_of_checked",
    "reconstruct",
]

KPI_NAMES = (
    "dc_offset",
    "dominant_frequency_hz",
    "damping_ratio",
    "amplitude",
    "phase_rad",
    "energy",
    "magnitude",
)
"""Names of the columns returned by :func:`extract_kpis`, in order."""

MIN_KPI_SAMPLES = 2
"""Fewest samples per trace that :func:`extract_kpis` accepts.

Not to be confused with ``inkdiag_core.estimation.MIN_FM_SAMPLES`` (16), the fewest samples
the f_m estimators (``estimate_fm``, ``estimate_fm_batch``) accept: a separate limit of a
different computation, not a second spelling of this one.

Two samples are the least that have a non-DC FFT bin. This is a floor for robustness, not a
recommendation: the model has 5 parameters, fewer than 5 samples leave the fit
under-determined (the KPIs are then finite but arbitrary) and below about 16 samples the
bin window around the peak is too narrow for a reliable damping estimate. It is this low
so that :class:`KpiExtractor` passes scikit-learn's estimator checks, which use 2 to 10
columns.
"""

MIN_SAMPLES = MIN_KPI_SAMPLES
"""Former name of :data:`MIN_KPI_SAMPLES`, kept for existing imports."""

# Traces per chunk in extract_kpis: large enough to amortise numpy's per-call overhead,
# small enough for a chunk's spectra and (n, 5, K) fit arrays to stay in cache.
_CHUNK = 2048
# A trace whose AC power is at most this fraction of its total power counts as flat.
_FLAT_RTOL = 1e-12
# A trace whose AC power sum (Parseval) exceeds _POWER_MAX or whose peak magnitude is below
# _MAGNITUDE_MIN for its precision is refitted scaled to a unit peak (see _extract_chunk):
# the limits keep |Y|**2 and the fit's Gram matrices well inside the floating-point range.
_POWER_MAX = 1e300
_MAGNITUDE_MIN = {np.float32: 1e-12, np.float64: 1e-140}


class InvalidTraceError(InputError):
    """Traces or a sample rate that :func:`extract_kpis` cannot use (a ``ValueError``).

    Raised by the :mod:`inkdiag_core.checks` checkers on the KPI path."""


def extract_kpis(traces, sample_rate_hz):
    """Extract the seven KPIs of every trace in a batch.

    Each trace is fitted with ``y[k] = dc + A exp(-zeta w0 t_k) cos(w_d t_k + phi)``,
    ``w_d = w0 sqrt(1 - zeta**2)``, ``t_k = k / sample_rate_hz`` counted from the first
    sample, by least squares on the FFT bins around the dominant spectral peak (see the
    module docstring). One batched FFT; the steps after it compiled, one trace at a time.

    Parameters
    ----------
    traces : array_like, shape (n_traces, n_samples) or (n_samples,)
        Self-sensing traces in signal units (V, or whatever the sensor reports), at least
        :data:`MIN_KPI_SAMPLES` samples each. A 1-D array is one trace: a batch of one.
        float32 input is transformed in single precision (as it is sent); other real
        dtypes in double precision. An empty batch gives an empty (0, 7) result.
    sample_rate_hz : float
        Sampling rate in Hz, positive and finite.

    Returns
    -------
    kpis : ndarray of float64, shape (n_traces, 7)
        Columns in the order of :data:`KPI_NAMES`:

        - ``dc_offset``: ``dc``, signal units.
        - ``dominant_frequency_hz``: damped frequency ``w_d / (2 pi)``, Hz, in
          ``(fs / (4 N), fs / 2)`` for an oscillating trace.
        - ``damping_ratio``: ``zeta``, dimensionless, in ``[0, 1)``; values below about
          ``1e-9 fs / w_d`` are not resolved (the decay rate is floored at ``1e-9 fs``).
        - ``amplitude``: ``A`` at ``t = 0``, signal units, ``>= 0``.
        - ``phase_rad``: ``phi`` at ``t = 0``, rad, wrapped to ``(-pi, pi]``.
        - ``energy``: ``sum_k (y[k] - mean(y))**2 / sample_rate_hz``, signal**2 * s: the
          energy of the mean-removed trace (model-free, computed by Parseval from the FFT).
        - ``magnitude``: single-sided amplitude spectrum at the FFT peak,
          ``2 |Y[m*]| / N`` with ``Y = rfft(y)`` and ``m* = argmax_{m >= 1} |Y[m]|``
          (``|Y[m*]| / N`` if ``m*`` is the Nyquist bin); signal units. It equals ``A``
          for an undamped sinusoid on a bin frequency.

    Raises
    ------
    InvalidTraceError
        (a ``ValueError``) for ndim other than 1 or 2, fewer than :data:`MIN_KPI_SAMPLES`
        samples, complex or non-numeric data, NaN / Inf values, or a non-positive or
        non-finite ``sample_rate_hz``.

    Notes
    -----
    - Multi-mode traces: the KPIs describe the mode with the largest FFT peak; the other
      modes are kept out of the fit by the bin window, and only bias it through their
      spectral leakage into that window.
    - Flat traces (AC power at most ``1e-12`` of the total power, e.g. a constant or an
      all-zero trace) give ``dc_offset = mean``, and ``0`` for frequency, damping ratio,
      amplitude, phase, energy and magnitude: finite values, so classifiers never see NaN.
    - Every output is finite for every accepted input, at any amplitude the input dtype
      can hold: the KPIs scale with the trace (frequency, damping ratio and phase not at
      all), and ``energy`` saturates at the largest float64 where ``sum y**2`` exceeds
      it (or underflows to 0 below its smallest). A trace that is not a damped
      sinusoid (noise, a step, an overdamped decay) still gets the least-squares best single
      damped sinusoid near its FFT peak, which may be meaningless.
    - Very heavy damping (the envelope falling by ``1/e`` within a few samples) leaves
      little information in the trace; the fit then relies on the exactness of the model
      and degrades quickly with noise.

    Examples
    --------
    >>> import numpy as np
    >>> fs, t = 10e6, np.arange(512) / 10e6
    >>> w_d, zeta = 2 * np.pi * 237e3, 0.07
    >>> w0 = w_d / np.sqrt(1 - zeta**2)
    >>> y = 0.1 + 2.0 * np.exp(-zeta * w0 * t) * np.cos(w_d * t + 0.5)
    >>> np.round(extract_kpis(y, fs)[0, :5], 4)
    array([1.00e-01, 2.37e+05, 7.00e-02, 2.00e+00, 5.00e-01])
    """
    fs = checks.sample_rate(sample_rate_hz, error=InvalidTraceError)
    y = checks.traces_2d(traces, min_samples=MIN_KPI_SAMPLES, error=InvalidTraceError)
    return kpis_of_checked(y, fs)


def kpis_of_checked(y, fs):
    """:func:`extract_kpis` of traces its checks already passed: the same result, without them.

    For a hot path whose input was validated once at its boundary (the FDI detector's
    :meth:`~inkdiag_core.FaultDetector.label`): the checks cost about as much as the fit
    of a few traces.

    Parameters
    ----------
    y : ndarray of float32 or float64, shape (n_traces, n_samples)
        Finite traces, ``n_samples >= MIN_KPI_SAMPLES``; float32 is fitted in single
        precision, float64 in double (as :func:`extract_kpis`); any memory layout.
    fs : float
        Sample rate, Hz, positive and finite.

    Returns
    -------
    kpis : ndarray of float64, shape (n_traces, 7)
    """
    y = np.ascontiguousarray(y)  # what the checks return: the fit's FFT sees the same layout
    n_traces = y.shape[0]
    out = np.zeros((n_traces, len(KPI_NAMES)))
    # Chunks of traces keep the spectra and the fit's temporaries in cache; every step is
    # per trace, so the chunking does not change any result.
    for i in range(0, n_traces, _CHUNK):
        _extract_chunk(y[i : i + _CHUNK], fs, out[i : i + _CHUNK])
    return out


def _peak_spectrum(y):
    """The spectrum pass shared by every FFT-peak method: rfft, power, peak bin, Parseval.

    Parameters
    ----------
    y : ndarray, shape (n, N)
        Validated traces (float32 or float64).

    Returns
    -------
    spec : ndarray of complex, shape (n, N // 2 + 1)
        ``rfft(y)`` in the input precision.
    m_peak, peak_power, ac_sumsq
        :func:`_spectrum_peaks` of ``spec``.
    """
    spec = scipy.fft.rfft(y, axis=-1)
    return (spec, *_spectrum_peaks(spec, y.shape[1]))


def _spectrum_peaks(spec, n_samples):
    """Peak bin, its power and the AC energy of traces of ``n_samples`` from their rfft ``spec``.

    Returns
    -------
    m_peak : ndarray of int, shape (n,)
        Index of the largest ``|Y[m]|``, ``m >= 1``.
    peak_power : ndarray of float64, shape (n,)
        ``|Y[m_peak]|**2``.
    ac_sumsq : ndarray of float64, shape (n,)
        ``sum_k (y[k] - mean(y))**2`` by Parseval.
    """
    # |Y[m]|^2 for m = 1 .. N/2 (the mean only enters bin 0).
    ac = spec[:, 1:]
    power = ac.real**2 + ac.imag**2
    m_peak = np.argmax(power, axis=1) + 1
    peak_power = np.take_along_axis(power, (m_peak - 1)[:, None], axis=1)[:, 0].astype(
        np.float64
    )
    # Parseval: sum_k (y_k - mean)^2 = (2 sum_{m=1}^{N/2} |Y_m|^2 - [N even] |Y_{N/2}|^2) / N.
    ac_sumsq = 2.0 * power.sum(axis=1, dtype=np.float64)
    if n_samples % 2 == 0:
        ac_sumsq -= power[:, -1]
    ac_sumsq /= n_samples
    return m_peak, peak_power, ac_sumsq


def _extract_chunk(y, fs, out):
    """KPIs of the validated traces ``y`` (n, N), written into ``out`` (n, 7)."""
    with np.errstate(over="ignore", under="ignore", invalid="ignore", divide="ignore"):
        _fit_spectra(scipy.fft.rfft(y, axis=-1), y.shape[1], fs, out)
    # Traces whose power spectrum leaves the floating-point range (float32 amplitudes
    # above ~1e16 overflow |Y|^2 and below ~1e-12 lose it to underflow; float64 amplitudes
    # above ~1e150 overflow it) are fitted again in float64, scaled to a unit peak. The
    # KPIs are scale-equivariant: frequency, damping ratio and phase do not change; dc,
    # amplitude and magnitude scale with the trace and the energy with its square, all
    # saturating at the largest float64.
    rescale = ~(out[:, 5] * fs <= _POWER_MAX) | (out[:, 6] < _MAGNITUDE_MIN[y.dtype.type])
    if rescale.any():
        rows = np.flatnonzero(rescale)
        y_big = y[rows].astype(np.float64)
        scale = np.abs(y_big).max(axis=1)
        scale[scale == 0.0] = 1.0  # an all-zero trace: flat, nothing to rescale
        y_big /= scale[:, None]
        sub = np.empty((rows.size, out.shape[1]))
        _fit_spectra(scipy.fft.rfft(y_big, axis=-1), y_big.shape[1], fs, sub)
        big = np.finfo(np.float64).max
        with np.errstate(over="ignore", under="ignore"):
            sub[:, [0, 3, 6]] = np.clip(sub[:, [0, 3, 6]] * scale[:, None], -big, big)
            sub[:, 5] = np.minimum(sub[:, 5] * scale * scale, big)  # 0 stays 0 (no 0 * inf)
        out[rows] = sub


def _fit_spectra(spec, n_samples, fs, out):
    """KPIs into ``out`` (n, 7) of traces of ``n_samples`` from their rfft ``spec``, compiled
    (:func:`inkdiag_core._kernels.kpis_of_spectra`: :func:`_fit_spectra_numpy`'s steps one row
    at a time, instead of ~60 numpy calls per chunk: the fixed cost of the few rows the gate leaves)."""
    from ._kernels import kpis_of_spectra  # numba: imported when a kernel is first needed

    kpis_of_spectra(spec, n_samples, fs, _FLAT_RTOL, out)


def _fit_spectra_numpy(spec, n_samples, fs, out):
    """:func:`_fit_spectra` in numpy: its reference in the tests and in ``scripts/bench fdi``."""
    _fit_chunk(n_samples, fs, out, spec, *_spectrum_peaks(spec, n_samples))


def _fit_chunk(n_samples, fs, out, spec, m_peak, peak_power, ac_sumsq):
    """Fit traces of ``n_samples`` from their spectrum pass; KPIs into ``out`` (n, 7)."""
    n_traces = spec.shape[0]
    half = n_samples // 2
    nyq_scale = np.full(n_traces, 2.0)
    if n_samples % 2 == 0:
        nyq_scale[m_peak == half] = 1.0
    mean = spec[:, 0].real.astype(np.float64) / n_samples

    Yw, start, exponent = _fit_window_inputs(spec, m_peak, peak_power, n_samples)
    omega, sigma, C = _fit_windows(Yw, start, m_peak, n_samples)
    C = np.ldexp(np.stack([C.real, C.imag], axis=1), exponent).view(np.complex128)[:, 0]

    # DC from bin 0: Y_0 = N dc + Re(C G_0), G_0 = (1 - z^N) / (1 - z).
    lam = -sigma + 1j * omega
    g0 = (1.0 - np.exp(n_samples * lam)) / (1.0 - np.exp(lam))
    dc = (spec[:, 0].real - (C * g0).real) / n_samples

    w0 = np.hypot(omega, sigma)
    phase = np.angle(C)
    phase = np.where(phase <= -np.pi, phase + 2.0 * np.pi, phase)
    out[:, 0] = dc
    out[:, 1] = omega * fs / (2.0 * np.pi)
    out[:, 2] = sigma / w0
    out[:, 3] = np.abs(C)
    out[:, 4] = phase
    out[:, 5] = ac_sumsq / fs
    out[:, 6] = nyq_scale * np.sqrt(peak_power) / n_samples

    flat = ac_sumsq <= _FLAT_RTOL * (ac_sumsq + n_samples * mean**2)
    bad = ~np.isfinite(out).all(axis=1)
    if flat.any() or bad.any():
        out[flat, 1:] = 0.0
        out[flat, 0] = mean[flat]
        # Should not happen; if it does, fall back to the FFT peak rather than emit NaN.
        bad &= ~flat
        out[bad, 0] = mean[bad]
        out[bad, 1] = m_peak[bad] * fs / n_samples
        out[bad, 2] = 0.0
        out[bad, 3] = out[bad, 6]
        out[bad, 4] = 0.0


def _fit_window_inputs(spec, m_peak, peak_power, n_samples):
    """The window fit's bins: ``K`` consecutive bins around each peak, inside ``1 .. N/2``, scaled.

    Parameters
    ----------
    spec, m_peak, peak_power
        :func:`_peak_spectrum`'s.
    n_samples : int

    Returns
    -------
    Yw : ndarray of complex128, shape (n, K)
        The window, scaled by a power of two near its peak (exact, so the KPIs do not
        change) to keep the fit's products inside the float64 range at any amplitude.
    start : ndarray of int, shape (n,)
        First bin of each window.
    exponent : ndarray of int, shape (n, 1)
        The scale: ``Yw = window * 2**-exponent``.
    """
    half = n_samples // 2
    n_bins = min(WINDOW_BINS, half)
    start = np.clip(m_peak - n_bins // 2, 1, half - n_bins + 1)
    Yw = np.take_along_axis(spec, start[:, None] + np.arange(n_bins), axis=1).astype(np.complex128)
    _, exponent = np.frexp(np.sqrt(peak_power))
    exponent = exponent[:, None]
    return np.ldexp(Yw.view(np.float64), -exponent).view(np.complex128), start, exponent


def _fit_windows(Yw, start, m_peak, n_samples):
    """The window fit, compiled: :func:`inkdiag_core._kernels.fit_windows` (one row at a time; the
    numpy :func:`inkdiag_core.spectral_fit.fit_windows` is its reference, within float64 rounding)."""
    from ._kernels import fit_windows as compiled

    return compiled(Yw, start, m_peak, n_samples)


def reconstruct(kpis, n_samples, sample_rate_hz):
    """Rebuild the fitted damped sinusoids from their KPIs (thesis Figure 8).

    Parameters
    ----------
    kpis : array_like, shape (n_traces, 7) or (7,)
        KPIs in the order of :data:`KPI_NAMES`, as returned by :func:`extract_kpis`;
        ``energy`` and ``magnitude`` are not used.
    n_samples : int
        Samples per rebuilt trace, ``>= 1``.
    sample_rate_hz : float
        Sampling rate in Hz, positive and finite.

    Returns
    -------
    y : ndarray of float64, shape (n_traces, n_samples)
        ``dc + A exp(-zeta w0 t_k) cos(w_d t_k + phi)``, ``w_d = 2 pi f``,
        ``w0 = w_d / sqrt(1 - zeta**2)``, ``t_k = k / sample_rate_hz``.

    Raises
    ------
    InvalidTraceError
        (a ``ValueError``) for a wrong shape, non-finite KPIs, a damping ratio outside
        ``[0, 1)``, a bad ``n_samples`` or a bad ``sample_rate_hz``.
    """
    fs = checks.sample_rate(sample_rate_hz, error=InvalidTraceError)
    k = np.asarray(kpis, dtype=np.float64)
    if k.ndim == 1:
        k = k[np.newaxis, :]
    if k.ndim != 2 or k.shape[1] != len(KPI_NAMES):
        raise InvalidTraceError(
            f"kpis must have shape (n_traces, {len(KPI_NAMES)}) or ({len(KPI_NAMES)},), "
            f"found shape {np.shape(kpis)}"
        )
    if not np.isfinite(k).all():
        raise InvalidTraceError("kpis must be finite, found NaN or Inf")
    if isinstance(n_samples, (bool, np.bool_)) or not isinstance(n_samples, numbers.Integral):
        raise InvalidTraceError(f"n_samples must be an integer, found {n_samples!r}")
    if n_samples < 1:
        raise InvalidTraceError(f"n_samples must be at least 1, found {n_samples}")
    zeta = k[:, 2]
    if np.any((zeta < 0.0) | (zeta >= 1.0)):
        raise InvalidTraceError(
            f"damping_ratio must be in [0, 1), found values in [{zeta.min()}, {zeta.max()}]"
        )
    t = np.arange(n_samples) / fs
    w_d = 2.0 * np.pi * k[:, 1]
    decay = zeta * w_d / np.sqrt(1.0 - zeta**2)
    return k[:, [0]] + k[:, [3]] * np.exp(-decay[:, None] * t) * np.cos(
        w_d[:, None] * t + k[:, [4]]
    )


class KpiExtractor(TransformerMixin, BaseEstimator):
    """scikit-learn transformer from traces to the seven KPIs of :func:`extract_kpis`.

    Stateless apart from the input width: ``fit`` only validates. Use it as the first step
    of a ``Pipeline`` (KPIs, scaler, classifier) that joblib saves and loads whole.

    Parameters
    ----------
    sample_rate_hz : float, default=10e6
        Sampling rate of the traces in Hz.

    Attributes
    ----------
    n_features_in_ : int
        Samples per trace seen in ``fit``; ``transform`` requires the same.
    feature_names_in_ : ndarray of str, shape (n_features_in_,)
        Column names, set only when ``X`` in ``fit`` has string column names.

    Examples
    --------
    >>> import numpy as np
    >>> t = np.arange(512) / 10e6
    >>> X = np.cos(2 * np.pi * 2e5 * t)[None, :].repeat(3, axis=0)
    >>> KpiExtractor().fit_transform(X).shape
    (3, 7)
    """

    def __init__(self, sample_rate_hz=10e6):
        self.sample_rate_hz = sample_rate_hz

    def _validate(self, X, reset):
        X = validate_data(self, X, reset=reset, dtype=[np.float64, np.float32])
        if X.shape[1] < MIN_KPI_SAMPLES:
            raise InvalidTraceError(
                f"X has {X.shape[1]} feature(s) (samples per trace), but "
                f"{type(self).__name__} needs at least {MIN_KPI_SAMPLES}"
            )
        return X

    def fit(self, X, y=None):
        """Validate the traces and the sample rate.

        Parameters
        ----------
        X : array_like, shape (n_traces, n_samples)
            Traces, one per row.
        y : None
            Ignored.

        Returns
        -------
        self : KpiExtractor
        """
        checks.sample_rate(self.sample_rate_hz, error=InvalidTraceError)
        self._validate(X, reset=True)
        return self

    def transform(self, X):
        """Extract the KPIs of every trace.

        Parameters
        ----------
        X : array_like, shape (n_traces, n_samples)
            Traces, one per row, with ``n_samples == n_features_in_``.

        Returns
        -------
        kpis : ndarray of float64, shape (n_traces, 7)
            Columns in the order of :data:`KPI_NAMES`.
        """
        check_is_fitted(self)
        X = self._validate(X, reset=False)
        return extract_kpis(X, self.sample_rate_hz)

    def _transform_checked(self, X):
        """:meth:`transform` of rows already validated against this fitted step (finite float32/64 ndarray,
        ``n_features_in_`` columns): the same result without scikit-learn's checks (the detector's hot path)."""
        return kpis_of_checked(X, float(self.sample_rate_hz))

    def get_feature_names_out(self, input_features=None):
        """Names of the output columns: :data:`KPI_NAMES`.

        Parameters
        ----------
        input_features : None
            Ignored; the output columns do not depend on the input names.

        Returns
        -------
        names : ndarray of object, shape (7,)
        """
        check_is_fitted(self)
        return np.asarray(KPI_NAMES, dtype=object)
