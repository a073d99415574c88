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
   ``_WINDOW_BINS`` consecutive bins;
3. the DFT of a damped sinusoid has a closed form (a finite geometric series),
   ``Y[m] = (C G_m(z) + conj(C) G_m(conj(z))) / 2`` with ``z = exp(-sigma + i omega)``
   (per-sample units), ``C = A exp(i phi)`` and
   ``G_m(z) = (1 - z**N) / (1 - z exp(-2 pi i m / N))``; the DC level only enters bin 0;
4. multiplying by the denominator makes the window bins linear in the unknowns
   (a frequency-domain Prony / equation-error fit), which gives the initial ``(omega, sigma)``;
5. Gauss-Newton steps of variable projection (``C`` solved by linear least squares for
   each ``(omega, sigma)``) refine the exact, not linearised, model on the window bins
   (``_N_ITER``, one by default);
6. the DC level follows from bin 0 minus the fitted sinusoid's contribution.

Restricting the fit to the bins around the dominant peak makes the cost of each iteration
independent of the trace length, keeps other modes and out-of-band noise out of the
fit, and means that on a multi-mode trace the KPIs describe the mode with the largest FFT
peak. Every step is vectorised over the batch: there is no loop over traces.
"""

import functools
import numbers

import numpy as np
import scipy.fft
from sklearn.base import BaseEstimator, TransformerMixin
from sklearn.utils.validation import check_is_fitted, validate_data

from . import checks
from .checks import InputError

__all__ = [
    "KPI_NAMES",
    "MIN_KPI_SAMPLES",
    "MIN_SAMPLES",
    "InvalidTraceError",
    "KpiExtractor",
    "extract_kpis",
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

# Number of FFT bins around the dominant peak used by the fit.
_WINDOW_BINS = 16
# Gauss-Newton (variable projection) steps after the equation-error initialisation. The
# initialisation is exact on noise-free traces; one step brings the 95th-percentile damping
# error at 30 dB SNR from about 1.1% to 0.6%, and further steps changed nothing measurable
# (seeded sweep over K = 8, 12, 16 bins and 1 to 3 steps) while each costs ~25% of the run.
_N_ITER = 1
# Traces per chunk in extract_kpis: large enough to amortise numpy's per-call overhead,
# small enough for a chunk's spectra and (n, 5, K) fit arrays to stay in cache.
_CHUNK = 2048
# Bounds on the per-sample decay rate sigma = zeta * w0 / fs.
_SIGMA_MIN = 1e-9
_SIGMA_MAX = 5.0
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


def _solve2(a11, a12, a22, b1, b2):
    """Solve the batched symmetric 2x2 systems ``[[a11, a12], [a12, a22]] x = b``.

    Singular or non-finite systems give ``x = 0``.
    """
    det = a11 * a22 - a12 * a12
    ok = det > 1e-14 * np.abs(a11 * a22)
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    return (a22 * b1 - a12 * b2) * inv, (a11 * b2 - a12 * b1) * inv


@functools.lru_cache(maxsize=16)
def _window_projector(n_bins, n_samples):
    """Constants for projecting out ``span{1, u}`` on ``K`` consecutive bins.

    On bins ``m = s .. s+K-1``, ``u_m = exp(-2 pi i m / N) = e_s w_j`` with a per-trace phase
    ``e_s`` and ``w_j = exp(-2 pi i j / N)``, so ``span{1, u} = span{1, w}`` for every
    trace. Returns ``w`` (K,), ``M = (B^H B)^+`` (2, 2) for ``B = [1, w]`` and two real
    (2K, 8) and (2K, 6) matrices for :func:`_prony_init`: on the interleaved
    ``(Re Y_j, Im Y_j)`` of a window they give ``(Re, Im) sum_j w_j**p Y_j``,
    p = -1 .. 2, and on its squares ``(Re, Im) sum_j w_j**p |Y_j|**2``, p = 0 .. 2.
    Cached per ``(K, N)`` and read-only.
    """
    w = np.exp(-2j * np.pi * np.arange(n_bins) / n_samples)
    B = np.stack([np.ones(n_bins), w], axis=1)
    M = np.linalg.pinv(B.conj().T @ B)  # pinv: for K <= 2 the complement is empty
    powers = np.stack([w**p for p in (-1, 0, 1, 2)], axis=1)  # (K, 4)
    r_t = np.empty((2 * n_bins, 8))
    r_t[0::2, :4], r_t[1::2, :4] = powers.real, -powers.imag
    r_t[0::2, 4:], r_t[1::2, 4:] = powers.imag, powers.real
    r_s = np.repeat(np.concatenate([powers[:, 1:].real, powers[:, 1:].imag], axis=1), 2, axis=0)
    for arr in (w, M, r_t, r_s):
        arr.flags.writeable = False
    return w, M, r_t, r_s


def _prony_init(Yw, e_s, M, r_t, r_s):
    """Equation-error (frequency-domain Prony) estimate of ``(omega, sigma)``.

    On the window bins, ``Y[m] (1 + a1 u_m + a2 u_m**2) = alpha + beta u_m`` holds exactly
    for a noise-free damped sinusoid, with ``a1 = -2 Re z`` and ``a2 = |z|**2``. ``alpha``
    and ``beta`` are projected out, then the real ``a1, a2`` solve a 2x2 least-squares
    problem. All inner products come from a few sums over the window: the Hermitian
    products of ``v_p = w**p Y`` (p = 0, 1, 2) are ``sum_j w_j**(q-p) |Y_j|**2``, and their
    components along ``B = [1, w]`` are ``sum_j w_j**p Y_j`` and ``sum_j w_j**(p-1) Y_j``.
    Returns ``omega, sigma`` and a boolean mask of the traces where it succeeded.
    """
    # einsum rather than a BLAS matrix product: BLAS may sum a lone row (gemv) in another
    # order than a batch (gemm), and the KPIs of a trace must not depend on its batch.
    # Real einsums on the interleaved (Re, Im) parts: a few times faster than complex ones.
    yr = Yw.view(np.float64)
    t = np.einsum("nk,kp->np", yr, r_t)
    t = t[:, :4] + 1j * t[:, 4:]  # t[:, p + 1] = sum_j w_j^p Y_j
    s = np.einsum("nk,kp->np", yr * yr, r_s)
    s = s[:, :3] + 1j * s[:, 3:]  # s[:, k] = sum_j w_j^k |Y_j|^2

    def h(p, q):  # <P v_p, P v_q>, P the projector onto the complement of span{1, w}
        k = q - p
        raw = s[:, k] if k >= 0 else np.conj(s[:, -k])
        bp0, bp1 = np.conj(t[:, p + 1]), np.conj(t[:, p])
        bq0, bq1 = t[:, q + 1], t[:, q]
        return raw - (bp0 * (M[0, 0] * bq0 + M[0, 1] * bq1) + bp1 * (M[1, 0] * bq0 + M[1, 1] * bq1))

    # c1 = u Y = e_s v_1, c2 = u^2 Y = e_s^2 v_2, and the projector commutes with e_s.
    a1, a2 = _solve2(
        h(1, 1).real, (e_s * h(1, 2)).real, h(2, 2).real,
        -(np.conj(e_s) * h(1, 0)).real, -(np.conj(e_s) ** 2 * h(2, 0)).real,
    )
    re_z = -0.5 * a1
    im2 = a2 - re_z * re_z
    ok = (a2 > 0.0) & (im2 > 0.0)
    omega = np.arctan2(np.sqrt(np.where(ok, im2, 1.0)), re_z)
    sigma = -0.5 * np.log(np.where(ok, a2, 1.0))
    return omega, sigma, ok


def _fit_windows(Yw, start, m_peak, n_samples):
    """Fit one damped sinusoid to ``K`` window bins per trace, bins ``start .. start+K-1``.

    Returns ``omega`` (rad/sample), ``sigma`` (1/sample) and the complex amplitude
    ``C = A exp(i phi)``, each (n,).

    The model on bin ``m`` is ``(C G_m + conj(C) H_m) / 2`` with ``G_m = alpha D_m``,
    ``H_m = conj(alpha) E_m``, ``alpha = 1 - z**N``, ``D = 1 / (1 - z u)`` and
    ``E = 1 / (1 - conj(z) u)``; its derivatives with respect to ``omega`` and ``sigma``
    are combinations of ``D, E, D**2, E**2`` (``z u D = D - 1``). So every vector the
    Gauss-Newton step needs has per-trace coefficients in the basis
    ``[D, E, Y, D**2, E**2]``, and all inner products come from that basis' (n, 5, 5)
    Hermitian Gram matrix (one batched matrix product): the only work on (n, K) arrays is
    building the basis, and the rest is closed-form algebra on (n,) arrays.
    """
    n, n_bins = Yw.shape
    e_s = np.exp((-2j * np.pi / n_samples) * start)
    w, M, r_t, r_s = _window_projector(n_bins, n_samples)
    n_iter = _N_ITER
    if n_bins >= 3:
        omega, sigma, ok = _prony_init(Yw, e_s, M, r_t, r_s)
    else:
        # Fewer than 3 bins (traces of < 6 samples) under-determine (omega, sigma): take
        # them from the FFT peak and fit only C, rather than decide on rounding noise.
        omega = sigma = np.zeros(n)
        ok = np.zeros(n, dtype=bool)
        n_iter = 0
    bin_w = 2.0 * np.pi / n_samples
    omega = np.where(ok, omega, bin_w * m_peak)
    sigma = np.where(ok, sigma, bin_w)
    omega_lo, omega_hi = 0.5 * bin_w, np.pi - 0.5 * bin_w
    omega = np.clip(omega, omega_lo, omega_hi)
    sigma = np.clip(sigma, _SIGMA_MIN, _SIGMA_MAX)

    # Basis rows: 0 = D, 1 = E, 2 = Y, 3 = D**2, 4 = E**2; h[i][j] = <V_i, V_j>.
    V = np.empty((n, 5, n_bins), dtype=np.complex128)
    V[:, 2] = Yw
    tmp = np.empty((n, n_bins), dtype=np.complex128)
    best = None
    for it in range(n_iter + 1):
        lam = -sigma + 1j * omega
        z = np.exp(lam)
        zn = np.exp(n_samples * lam)
        last = it == n_iter
        k = 3 if last else 5  # the final pass only needs C: no derivative terms
        for row, zeta in ((0, z * e_s), (1, np.conj(z) * e_s)):
            # D (or E) = 1 / (1 - zeta w), built contiguous, then stored with its square.
            d = np.multiply.outer(zeta, w, out=tmp)
            np.subtract(1.0, d, out=d)
            np.reciprocal(d, out=d)
            V[:, row] = d
            if not last:
                np.multiply(d, d, out=V[:, row + 3])
        Vk = V[:, :k]
        H = np.matmul(np.conj(Vk), Vk.transpose(0, 2, 1))  # (n, k, k)
        h00, h11, h22 = H[:, 0, 0].real, H[:, 1, 1].real, H[:, 2, 2].real
        h01, h02, h12 = H[:, 0, 1], H[:, 0, 2], H[:, 1, 2]

        # Linear least squares for C = c1 + i c2 with P = (G + H)/2, Q = i (G - H)/2:
        # <G, G> = |alpha|^2 h00, <H, H> = |alpha|^2 h11, <G, H> = conj(alpha)^2 h01,
        # <G, Y> = conj(alpha) h02, <H, Y> = alpha h12.
        alpha = 1.0 - zn
        ca = np.conj(alpha)
        aa = alpha.real**2 + alpha.imag**2
        gg = aa * h00
        hh = aa * h11
        gh = ca * ca * h01
        gy = ca * h02
        hy = alpha * h12
        pp = 0.25 * (gg + hh + 2.0 * gh.real)
        qq = 0.25 * (gg + hh - 2.0 * gh.real)
        pq = 0.5 * gh.imag
        c1, c2 = _solve2(pp, pq, qq, 0.5 * (gy + hy).real, 0.5 * (gy - hy).imag)
        C = c1 + 1j * c2
        # ||Y - (C G + conj(C) H)/2||^2 = ||Y||^2 - Re<c1 P + c2 Q, Y> at the least-squares C.
        # It cancels to ~1e-16 of ||Y||^2: only used to rank iterates, where that is enough.
        rss = h22 - (c1 * 0.5 * (gy + hy).real + c2 * 0.5 * (gy - hy).imag)
        if best is None:
            best = [omega, sigma, C, rss]
        else:
            better = rss < best[3]
            best = [np.where(better, new, old) for new, old in zip((omega, sigma, C, rss), best)]
        if last:
            break
        # Jacobian columns (variable projection, Kaufman's form):
        # dG/domega = i (alpha D^2 - (alpha + N z^N) D), dG/dsigma = i dG/domega,
        # dH/domega = -i (beta E^2 - (beta + N conj(z^N)) E), dH/dsigma = -i dH/domega,
        # so J_omega = a + b and J_sigma = i (a - b) with a = u1 D + u2 D^2 and
        # b = v1 E + v2 E^2.
        h03, h04, h13, h14, h34 = H[:, 0, 3], H[:, 0, 4], H[:, 1, 3], H[:, 1, 4], H[:, 3, 4]
        h32, h42 = H[:, 3, 2], H[:, 4, 2]
        h33, h44 = H[:, 3, 3].real, H[:, 4, 4].real
        gamma = n_samples * zn
        cC = np.conj(C)
        u1 = -0.5j * C * (alpha + gamma)
        u2 = 0.5j * C * alpha
        v1 = 0.5j * cC * (ca + np.conj(gamma))
        v2 = -0.5j * cC * ca
        cu1, cu2, cv1, cv2 = np.conj(u1), np.conj(u2), np.conj(v1), np.conj(v2)
        # <a, a>, <b, b> (real) and <a, b>.
        na = (u1.real**2 + u1.imag**2) * h00 + (u2.real**2 + u2.imag**2) * h33 \
            + 2.0 * (cu1 * u2 * h03).real
        nb = (v1.real**2 + v1.imag**2) * h11 + (v2.real**2 + v2.imag**2) * h44 \
            + 2.0 * (cv1 * v2 * h14).real
        nab = cu1 * (v1 * h01 + v2 * h04) + cu2 * (v1 * np.conj(h13) + v2 * h34)
        # <G, a>, <H, a>, <G, b>, <H, b>.
        g_a = ca * (u1 * h00 + u2 * h03)
        h_a = alpha * (u1 * np.conj(h01) + u2 * h13)
        g_b = ca * (v1 * h01 + v2 * h04)
        h_b = alpha * (v1 * h11 + v2 * h14)
        # <a, r>, <b, r> with r = Y - (C G + conj(C) H) / 2.
        a_r = cu1 * h02 + cu2 * h32 - 0.5 * (C * np.conj(g_a) + cC * np.conj(h_a))
        b_r = cv1 * h12 + cv2 * h42 - 0.5 * (C * np.conj(g_b) + cC * np.conj(h_b))
        # Re<P, x> = Re(<G, x> + <H, x>) / 2 and Re<Q, x> = Im(<G, x> - <H, x>) / 2.
        gj, hj = g_a + g_b, h_a + h_b
        gw = (0.5 * (gj + hj).real, 0.5 * (gj - hj).imag)
        gj, hj = 1j * (g_a - g_b), 1j * (h_a - h_b)
        gs = (0.5 * (gj + hj).real, 0.5 * (gj - hj).imag)
        # Normal matrix of the projected Jacobian: <J_i, J_j> - g_i^T Gram^-1 g_j.
        iw = _solve2(pp, pq, qq, *gw)
        i_s = _solve2(pp, pq, qq, *gs)
        nww = na + nb + 2.0 * nab.real - (gw[0] * iw[0] + gw[1] * iw[1])
        nws = 2.0 * nab.imag - (gw[0] * i_s[0] + gw[1] * i_s[1])
        nss = na + nb - 2.0 * nab.real - (gs[0] * i_s[0] + gs[1] * i_s[1])
        d_omega, d_sigma = _solve2(nww, nws, nss, (a_r + b_r).real, (a_r - b_r).imag)
        # Keep steps within two bins so that a poor start cannot jump to another peak.
        d_omega = np.clip(d_omega, -2 * bin_w, 2 * bin_w)
        d_sigma = np.clip(d_sigma, -2 * bin_w - 0.5 * sigma, 2 * bin_w + sigma)
        # A step from a point worse than the best one restarts halfway from the best.
        worse = rss > best[3]
        omega = np.where(worse, 0.5 * (omega + best[0]), omega + d_omega)
        sigma = np.where(worse, 0.5 * (sigma + best[1]), sigma + d_sigma)
        omega = np.clip(omega, omega_lo, omega_hi)
        sigma = np.clip(sigma, _SIGMA_MIN, _SIGMA_MAX)
    omega, sigma, C, _ = best
    return omega, sigma, C


def extract_kpis(traces, sample_rate_hz):
    """Extract the seven KPIs of every trace in a batch.

    Each trace is fitted with ``y[k] = dc + A exp(-zeta w0 t_k) cos(w_d t_k + phi)``,
    ``w_d = w0 sqrt(1 - zeta**2)``, ``t_k = k / sample_rate_hz`` counted from the first
    sample, by least squares on the FFT bins around the dominant spectral peak (see the
    module docstring). Fully vectorised over the batch.

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
    m_peak : ndarray of int, shape (n,)
        Index of the largest ``|Y[m]|``, ``m >= 1``.
    peak_power : ndarray of float64, shape (n,)
        ``|Y[m_peak]|**2``.
    ac_sumsq : ndarray of float64, shape (n,)
        ``sum_k (y[k] - mean(y))**2`` by Parseval.
    """
    n_samples = y.shape[1]
    spec = scipy.fft.rfft(y, axis=-1)
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
    return spec, m_peak, peak_power, ac_sumsq


def _extract_chunk(y, fs, out):
    """KPIs of the validated traces ``y`` (n, N), written into ``out`` (n, 7)."""
    with np.errstate(over="ignore", under="ignore", invalid="ignore", divide="ignore"):
        _fit_chunk(y, fs, out, *_peak_spectrum(y))
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
        _fit_chunk(y_big, fs, sub, *_peak_spectrum(y_big))
        big = np.finfo(np.float64).max
        with np.errstate(over="ignore", under="ignore"):
            sub[:, [0, 3, 6]] = np.clip(sub[:, [0, 3, 6]] * scale[:, None], -big, big)
            sub[:, 5] = np.minimum(sub[:, 5] * scale * scale, big)  # 0 stays 0 (no 0 * inf)
        out[rows] = sub


def _fit_chunk(y, fs, out, spec, m_peak, peak_power, ac_sumsq):
    """Fit the traces ``y`` (n, N) from their spectrum pass; KPIs into ``out`` (n, 7)."""
    n_traces, n_samples = y.shape
    half = n_samples // 2
    nyq_scale = np.full(n_traces, 2.0)
    if n_samples % 2 == 0:
        nyq_scale[m_peak == half] = 1.0
    mean = spec[:, 0].real.astype(np.float64) / n_samples

    # Window of K consecutive bins around the peak, inside 1 .. N/2.
    n_bins = min(_WINDOW_BINS, half)
    start = np.clip(m_peak - n_bins // 2, 1, half - n_bins + 1)
    idx = start[:, None] + np.arange(n_bins)
    Yw = np.take_along_axis(spec, idx, axis=1).astype(np.complex128)
    # Fit a window scaled by a power of two near its peak (exact, so the KPIs do not
    # change) to keep the fit's products inside the float64 range at any amplitude.
    _, exponent = np.frexp(np.sqrt(peak_power))
    exponent = exponent[:, None]
    Yw = np.ldexp(Yw.view(np.float64), -exponent).view(np.complex128)
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
