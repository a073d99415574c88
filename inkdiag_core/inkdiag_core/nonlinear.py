"""Former home of the nonlinear simulator, kept as an import path.

It now lives in :mod:`inkdiag_core.simulation.nonlinear`; this module
re-exports its public names.
"""

from .simulation.nonlinear import DEFAULT_COUPLING_M3_PER_V, NonlinearTerms, simulate_nonlinear

__all__ = ["NonlinearTerms", "simulate_nonlinear", "DEFAULT_COUPLING_M3_PER_V"]
