"""Datasets built from the simulators: a simulation's nozzles seen healthy."""

from __future__ import annotations

import dataclasses

import numpy as np

from ..faults import FaultClass
from .channels import Spreads
from .linear import simulate

__all__ = ["healthy_twin_chunks", "healthy_twin_frames"]


def healthy_twin_frames(n_traces: int, *, seed, n_frames: int, noise_std_v: float,
                        spreads: Spreads | None = None, simulate_fn=None, **kwargs):
    """The same nozzles as an earlier simulation, healthy: what a monitor saw of them before.

    The simulator draws every trace's physical spreads in one fixed order,
    whatever its class, so ``simulate_fn({HEALTHY_NOZZLE: n_traces}, seed=seed)``
    gives row ``i`` the nozzle geometry, piezo, drive and sensor of row ``i`` of
    any ``simulate_fn(counts, seed=seed)`` with ``n_traces`` rows in all. This
    returns those nozzles healthy, at the nominal ink temperature (the head
    heater's set point: the temperature is not shared with the original
    traces), in ``n_frames`` frames, each with its own white sensor noise of
    ``noise_std_v`` drawn from a stream independent of the original traces'.

    Parameters
    ----------
    n_traces : int
        Rows of the original simulation.
    seed : int
        Its seed.
    n_frames : int
        Healthy frames per nozzle, >= 1.
    noise_std_v : float
        Sensor noise standard deviation, V (the original's ``noise_std_v``).
    spreads : Spreads, optional
        The original's spreads (default :class:`Spreads`); its temperature
        spread, noise and ADC are switched off for the twins.
    simulate_fn : callable, optional
        :func:`simulate` (default) or :func:`inkdiag_core.simulate_nonlinear`.
    **kwargs
        Further options of the original call (``sample_rate_hz``, ``n_samples``, ...).

    Returns
    -------
    twins : SimulationResult
        The noise-free healthy twins (one row per original row).
    frames : ndarray of float32, shape (n_traces, n_frames, n_samples)
        Noisy healthy frames, V.
    """
    twins = _twins(n_traces, seed, n_frames, noise_std_v, spreads, simulate_fn, kwargs)
    n, n_samples = twins.traces.shape
    rng = np.random.default_rng([int(seed), 7])
    blocks = [f for _, f in _chunks(twins.traces, rng, int(n_frames), noise_std_v, max(n, 1))]  # one block
    return twins, blocks[0] if blocks else np.zeros((0, int(n_frames), n_samples), np.float32)


def healthy_twin_chunks(n_traces: int, *, seed, n_frames: int, noise_std_v: float, spreads: Spreads | None = None,
                        simulate_fn=None, chunk_rows: int = 2048, **kwargs):
    """:func:`healthy_twin_frames`' frames a block of rows at a time: the same numbers, in bounded memory.

    Every frame of every row at once is ``n_traces x n_frames x n_samples`` float64 noise
    (60,000 rows of 8 frames of 1,024 samples: 3.9 GB); this draws the same noise stream
    block by block (a generator fills its draws in order), so a block's frames equal those
    rows of :func:`healthy_twin_frames`' bit for bit.

    Parameters
    ----------
    n_traces, seed, n_frames, noise_std_v, spreads, simulate_fn, **kwargs
        As :func:`healthy_twin_frames`.
    chunk_rows : int
        Rows per block, >= 1.

    Returns
    -------
    iterator of (start, frames)
        ``start`` (int) the block's first row; ``frames`` (k, n_frames, n_samples) float32, the
        noisy healthy frames of rows ``start .. start + k - 1``, V. The arguments are checked and
        the twins simulated on the call; the noise is drawn block by block as it is iterated.
    """
    if isinstance(chunk_rows, bool) or not isinstance(chunk_rows, (int, np.integer)) or chunk_rows < 1:
        raise ValueError(f"chunk_rows must be an integer >= 1, got {chunk_rows!r}")
    twins = _twins(n_traces, seed, n_frames, noise_std_v, spreads, simulate_fn, kwargs)  # checked here, not later
    return _chunks(twins.traces, np.random.default_rng([int(seed), 7]), int(n_frames), noise_std_v, int(chunk_rows))


def _chunks(twins, rng, n_frames, noise_std_v, chunk_rows):
    n, n_samples = twins.shape
    for a in range(0, n, chunk_rows):
        b = min(a + chunk_rows, n)
        noise = rng.standard_normal((b - a, n_frames, n_samples))
        yield a, (twins[a:b, None, :] + noise_std_v * noise).astype(np.float32)


def _twins(n_traces, seed, n_frames, noise_std_v, spreads, simulate_fn, kwargs):
    """The noise-free healthy twins of :func:`healthy_twin_frames`, its arguments checked."""
    if n_frames < 1:
        raise ValueError(f"n_frames must be >= 1, got {n_frames}")
    if not np.isfinite(noise_std_v) or noise_std_v < 0:
        raise ValueError(f"noise_std_v must be finite and >= 0, got {noise_std_v!r}")
    fn = simulate if simulate_fn is None else simulate_fn
    base = Spreads() if spreads is None else spreads
    quiet = dataclasses.replace(base, temperature_std_k=0.0, snr_db=np.inf, adc_bits=None)
    return fn({FaultClass.HEALTHY_NOZZLE: int(n_traces)}, seed=seed, spreads=quiet, **kwargs)
