"""The sensor chain shared by both simulators: gain, offset, noise and the ADC.

The sense amplifier maps the outflow ``y`` (m^3/s) to volts,
``v = gain * y + offset``, with a per-channel gain and offset
(:func:`draw_sensor`); white noise of a fixed level in volts
(:func:`noise_std_for_snr`, :func:`white_noise`) is added and an ADC
quantises and clips (:func:`adc_quantiser`).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.special import ndtri

from .channels import Spreads

__all__ = ["draw_sensor", "noise_std_for_snr", "adc_quantiser", "white_noise", "snr_db"]


def draw_sensor(rng, n: int, spreads: Spreads, nominal_gain: float, perm=None):
    """Each channel's sense-amplifier gain and offset, drawn in that order from ``rng``.

    Parameters
    ----------
    rng : numpy.random.Generator
    n : int
        Number of traces.
    spreads : Spreads
        ``gain_rel`` (log-normal) and ``offset_std_v`` (normal, V).
    nominal_gain : float
        Nominal gain, V per (m^3/s).
    perm : ndarray of int, shape (n,), optional
        Row ``r`` takes draw ``perm[r]`` (default: its own).

    Returns
    -------
    gain : ndarray, shape (n,)
        V per (m^3/s).
    offset : ndarray, shape (n,)
        V.
    """
    gain = nominal_gain * (
        np.exp(spreads.gain_rel * rng.standard_normal(n)) if spreads.gain_rel > 0 else 1.0
    ) * np.ones(n)
    offset = spreads.offset_std_v * rng.standard_normal(n) if spreads.offset_std_v > 0 else np.zeros(n)
    if perm is not None:
        gain, offset = gain[perm], offset[perm]
    return gain, offset


def noise_std_for_snr(spreads: Spreads, nominal_rms_v: float) -> float:
    """White-noise standard deviation (V) giving ``spreads.snr_db`` on a trace of RMS ``nominal_rms_v`` (V); 0 if the SNR is infinite."""
    return 0.0 if math.isinf(spreads.snr_db) else nominal_rms_v / 10 ** (spreads.snr_db / 20)


def adc_quantiser(spreads: Spreads):
    """The ADC's step and code range: ``(lsb_v, (qlo, qhi))``, or ``(1.0, None)`` without ADC.

    ``lsb_v = 2 adc_range_v / 2**adc_bits`` (V); codes run from
    ``-2**(adc_bits-1)`` to ``2**(adc_bits-1) - 1``.
    """
    if spreads.adc_bits is None:
        return 1.0, None
    lsb = 2.0 * spreads.adc_range_v / 2**spreads.adc_bits
    return lsb, (-(2 ** (spreads.adc_bits - 1)), 2 ** (spreads.adc_bits - 1) - 1)


def snr_db(sig_rms, noise_std: float) -> np.ndarray:
    """Per-trace SNR, dB: ``20 log10(sig_rms / noise_std)`` ((n,) in, (n,) out); ``inf`` without noise."""
    with np.errstate(divide="ignore"):
        return 20 * np.log10(sig_rms / noise_std) if noise_std > 0 else np.full(sig_rms.shape[0], np.inf)


# Gaussian quantile table for fast white noise: 2^16 equiprobable levels,
# unit variance, truncated at about +-4.2 sigma.
_NOISE_TABLE = ndtri((np.arange(65536) + 0.5) / 65536.0)
_NOISE_TABLE = (_NOISE_TABLE / _NOISE_TABLE.std()).astype(np.float32)


def white_noise(rng, shape, std):
    """Gaussian white noise via inverse-CDF table lookup of uniform 16-bit draws."""
    u = np.frombuffer(rng.bytes(2 * math.prod(shape)), dtype="<u2").reshape(shape)
    return (_NOISE_TABLE * np.float32(std))[u]
