"""inkdiag_core: the pure-Python numerical core of inkdiag.

Ink-channel model, fault simulator, KPIs, residual filters, classifiers and
fault estimators. numpy, scipy, scikit-learn and joblib only: this package
never imports rclpy or any message package (a test checks it).
"""

from .faults import FaultClass
from .model import (
    InkChannelModel,
    InkChannelParams,
    alpha,
    fault_fm,
    fm_to_viscosity,
    viscosity_to_fm,
)
from .nonlinear import simulate_nonlinear
from .simulator import SimulationResult, simulate

__version__ = "0.1.0"

__all__ = [
    "FaultClass",
    "SimulationResult",
    "simulate",
    "simulate_nonlinear",
    "InkChannelModel",
    "InkChannelParams",
    "__version__",
    "alpha",
    "fault_fm",
    "fm_to_viscosity",
    "viscosity_to_fm",
]
