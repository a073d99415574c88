"""Former home of the linear simulator, kept as an import path.

The simulator now lives in :mod:`inkdiag_core.simulation` (the linear one in
:mod:`inkdiag_core.simulation.linear`, the shared pieces in
:mod:`inkdiag_core.simulation.channels`); this module re-exports its public
names so that ``from inkdiag_core.simulator import DriveWaveform, Spreads``
keeps working.
"""

from .simulation.channels import PHYSICAL_CONSTANTS, DriveWaveform, Spreads
from .simulation.datasets import healthy_twin_frames
from .simulation.linear import simulate, simulate_nozzles
from .simulation.result import SimulationResult

__all__ = [
    "healthy_twin_frames",
    "simulate_nozzles",
    "DriveWaveform",
    "Spreads",
    "SimulationResult",
    "simulate",
    "PHYSICAL_CONSTANTS",
]
