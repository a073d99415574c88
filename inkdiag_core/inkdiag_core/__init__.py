"""inkdiag_core: the pure-Python numerical core of inkdiag.

Ink-channel model, fault simulator, KPIs, residual filters, classifiers and
fault estimators. numpy, scipy, scikit-learn and joblib only: this package
never imports rclpy or any message package (a test checks it).
"""

from .estimation import FmBatchEstimate, FmEstimate, estimate_fm, estimate_fm_batch
from .faults import FaultClass
from .model import (
    InkChannelModel,
    InkChannelParams,
    alpha,
    fault_fm,
    fm_to_viscosity,
    viscosity_to_fm,
)
from .observer import UIODesign, design_uio

from .fdi import FEATURE_SETS, fd_labels, make_fdi_pipeline
from .kpis import KPI_NAMES, KpiExtractor, extract_kpis, reconstruct
from .residual import ResidualFilter, design_residual_filter
from .persistence import ModelFileError, load_model, save_model
from .screening import INVALID_REASONS, screen_traces
from .nonlinear import simulate_nonlinear
from .simulator import SimulationResult, simulate

__version__ = "0.1.0"

__all__ = [
    "FEATURE_SETS",
    "KPI_NAMES",
    "KpiExtractor",
    "ResidualFilter",
    "design_residual_filter",
    "extract_kpis",
    "fd_labels",
    "make_fdi_pipeline",
    "reconstruct",
    "INVALID_REASONS",
    "ModelFileError",
    "load_model",
    "save_model",
    "screen_traces",
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
    "FmEstimate",
    "FmBatchEstimate",
    "estimate_fm",
    "estimate_fm_batch",
    "UIODesign",
    "design_uio",
]
