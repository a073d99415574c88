"""The simulators' output: traces and their per-trace ground truth."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

__all__ = ["SimulationResult", "empty_result"]


@dataclass(frozen=True)
class SimulationResult:
    """Simulated traces and their ground truth.

    Attributes
    ----------
    traces : ndarray of float32, shape (n, n_samples)
        Sensor output, V.
    labels : ndarray of object, shape (n,)
        :class:`FaultClass` per row.
    sample_rate_hz : float
    mu_nozzle : ndarray, shape (n,)
        Viscosity of the ink in the nozzle, Pa s.
    mu : ndarray, shape (n,)
        Viscosity of the ink in the channel (temperature dependent), Pa s.
    fm : ndarray, shape (n,)
        Appendix F fault ``-(R_n(mu_nozzle) - R_n(mu)) / I_n = -alpha (mu_nozzle - mu)``
        of the trace's own nozzle against the same nozzle with undried ink, 1/s.
        Non-zero only for the dried classes.
    frequency_hz, damping_ratio : ndarray, shape (n,)
        Damped frequency and damping ratio of the true oscillatory mode
        (0 and 1 if a trace had none).
    x0 : ndarray, shape (n, 3)
        Observable-form state ``[V_r + V_n, V_r', V_n']`` at the first sample
        (m^3, m^3/s, m^3/s). For empty channels the third entry is the
        actuator's volume rate and the second is 0.
    A : ndarray, shape (n, 3, 3)
        Each trace's observable-form matrix (1/s, 1/s^2).
    sensor_gain : ndarray, shape (n,)
        V per (m^3/s).
    sensor_offset : ndarray, shape (n,)
        V.
    snr_db : ndarray, shape (n,)
        RMS of the noise-free window (without offset) over the noise std, dB.
    params : dict of str -> ndarray, shape (n,)
        Per-trace physical values (SI): temperature_k, drive_v, rho, r_n,
        L_n, r_r, L_r, B_act, b, B_t, I_n, I_r, R_n, R_r, severity
        (NaN where a class has none; ``inf`` inertance for a closed branch).
    noise_std_v : float
        Standard deviation of the white noise, V.
    """

    traces: np.ndarray
    labels: np.ndarray
    sample_rate_hz: float
    mu_nozzle: np.ndarray
    mu: np.ndarray
    fm: np.ndarray
    frequency_hz: np.ndarray
    damping_ratio: np.ndarray
    x0: np.ndarray
    A: np.ndarray
    sensor_gain: np.ndarray
    sensor_offset: np.ndarray
    snr_db: np.ndarray
    params: dict = field(default_factory=dict)
    noise_std_v: float = 0.0

    def __len__(self) -> int:
        return self.traces.shape[0]

    def y_si(self) -> np.ndarray:
        """Traces converted back to the model output ``y = C x`` (m^3/s), float64.

        ``(trace - sensor_offset) / sensor_gain``; exact up to float32 rounding
        when there is no noise and no quantisation.
        """
        return (self.traces.astype(np.float64) - self.sensor_offset[:, None]) / self.sensor_gain[
            :, None
        ]

    def label_values(self) -> np.ndarray:
        """Labels as their snake_case strings, shape (n,)."""
        return np.array([c.value for c in self.labels])

    def take(self, index) -> "SimulationResult":
        """The rows ``index`` (an integer index array), every per-trace field alike."""
        index = np.asarray(index, dtype=np.intp)
        per_row = {
            f.name: getattr(self, f.name)[index]
            for f in dataclasses.fields(self)
            if isinstance(getattr(self, f.name), np.ndarray)
        }
        params = {k: np.asarray(v)[index] for k, v in self.params.items()}
        return dataclasses.replace(self, params=params, **per_row)


def empty_result(labels, fs, n_samples):
    """A :class:`SimulationResult` with no traces (``labels`` of shape (0,), ``n_samples`` columns)."""
    e = np.empty(0)
    return SimulationResult(np.empty((0, n_samples), np.float32), labels, fs, e, e, e, e, e,
                            np.empty((0, 3)), np.empty((0, 3, 3)), e, e, e, {}, 0.0)
