"""Training rows of a baseline branch from a simulation: each trace with its simulated nozzle's baseline.

The simulator is imported only when these are called.
"""

from __future__ import annotations

import numpy as np

from .features import baseline_kpis, with_baseline

__all__ = ["baseline_training_kpis", "baseline_training_rows"]


def baseline_training_kpis(sim, seed, *, n_frames: int = 8) -> np.ndarray:
    """Each simulated trace's nozzle baseline, for training a baseline branch.

    Each trace of ``sim`` (a :func:`inkdiag_core.simulate` result drawn with ``seed``)
    gets its own nozzle's baseline: the median KPIs of ``n_frames`` healthy frames of
    the same simulated nozzle (:func:`inkdiag_core.healthy_twin_frames`: nominal ink
    temperature, its own sensor noise), as a printer records them after a purge.

    Returns
    -------
    ndarray of float64, shape (n, 7)
        :func:`baseline_kpis` of each trace's nozzle (the ``baseline_kpis`` of
        :meth:`inkdiag_core.FaultDetector.fit`).
    """
    from ..simulation import healthy_twin_frames

    _, frames = healthy_twin_frames(len(sim), seed=seed, n_frames=n_frames, noise_std_v=sim.noise_std_v,
                                    sample_rate_hz=sim.sample_rate_hz, n_samples=sim.traces.shape[1])
    return baseline_kpis(frames, sim.sample_rate_hz)


def baseline_training_rows(sim, seed, *, n_frames: int = 8) -> np.ndarray:
    """Training rows of a ``"kpi_y+baseline"`` pipeline from a simulation.

    ``with_baseline(sim.traces, baseline_training_kpis(sim, seed, n_frames=n_frames))``
    (:func:`baseline_training_kpis`).

    Returns
    -------
    ndarray, shape (n, n_samples + 7)
        :func:`with_baseline` rows.
    """
    return with_baseline(sim.traces, baseline_training_kpis(sim, seed, n_frames=n_frames))
