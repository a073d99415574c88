"""inkdiag_core: the pure-Python numerical core of inkdiag.

Ink-channel model, fault simulator, KPIs, residual filters, classifiers and
fault estimators. numpy, scipy, scikit-learn and joblib only: this package
never imports rclpy or any message package (a test checks it).
"""

from .checks import InputError, OptionError
from .estimation import (
    CtOptions,
    DtExactOptions,
    DtOptions,
    FmBatchEstimate,
    FmEstimate,
    VpOptions,
    estimate_fm,
    estimate_fm_batch,
)
from .faults import FaultClass
from .fdi import FEATURE_SETS, fd_labels, make_fdi_pipeline
from .kpis import KPI_NAMES, KpiExtractor, extract_kpis, reconstruct
from .model import (
    InkChannelModel,
    InkChannelParams,
    alpha,
    fault_fm,
    fm_to_viscosity,
    viscosity_to_fm,
)
from .observer import UIODesign, design_uio
from .persistence import ModelFileError, load_detector, load_model, save_detector, save_model
from .residual import ResidualFilter, design_residual_filter
from .screening import INVALID_REASONS, screen_traces
from .simulation import SimulationResult, healthy_twin_frames, simulate, simulate_nonlinear, simulate_nozzles
from .simulation import HELDOUT_CONDITIONS, HeldoutTraces, simulate_heldout

from ._version import __version__

__all__ = [
    "CtOptions",
    "DtExactOptions",
    "DtOptions",
    "InputError",
    "OptionError",
    "VpOptions",
    "FEATURE_SETS",
    "INVALID_REASONS",
    "KPI_NAMES",
    "FaultClass",
    "FmBatchEstimate",
    "FmEstimate",
    "InkChannelModel",
    "InkChannelParams",
    "KpiExtractor",
    "ModelFileError",
    "ResidualFilter",
    "SimulationResult",
    "UIODesign",
    "__version__",
    "alpha",
    "design_residual_filter",
    "design_uio",
    "estimate_fm",
    "estimate_fm_batch",
    "extract_kpis",
    "fault_fm",
    "fd_labels",
    "fm_to_viscosity",
    "load_detector",
    "load_model",
    "make_fdi_pipeline",
    "reconstruct",
    "save_detector",
    "save_model",
    "screen_traces",
    "simulate",
    "simulate_nonlinear",
    "simulate_nozzles",
    "HELDOUT_CONDITIONS",
    "HeldoutTraces",
    "simulate_heldout",
    "healthy_twin_frames",
    "viscosity_to_fm",
]

from .trend import FmTrend, FmTrendBank, deeply_dried_fm  # noqa: E402

__all__ += ["FmTrend", "FmTrendBank", "deeply_dried_fm"]

from .labelling import BaselineModel, FrameLabels, label_frames, label_frames_isolated, label_traces  # noqa: E402

__all__ += ["BaselineModel", "FrameLabels", "label_frames", "label_frames_isolated", "label_traces"]

from .baselines import (  # noqa: E402
    BaselineFileError,
    BaselineKpis,
    BaselineRecorder,
    NozzleBaselines,
    baseline_kpis,
    baseline_training_kpis,
    baseline_training_rows,
    with_baseline,
)

__all__ += ["BaselineFileError", "BaselineKpis", "BaselineRecorder", "NozzleBaselines", "baseline_kpis",
            "baseline_training_kpis", "baseline_training_rows", "with_baseline"]

from .drying_tracker import ESTIMATE_COLUMNS, DryingTracker, RangeEstimates, RowEstimates  # noqa: E402

__all__ += ["ESTIMATE_COLUMNS", "DryingTracker", "RangeEstimates", "RowEstimates"]

from .openset import UNKNOWN, ConformalOpenSet  # noqa: E402

__all__ += ["UNKNOWN", "ConformalOpenSet"]

from .detector import DetectorLabels, FaultDetector  # noqa: E402

__all__ += ["DetectorLabels", "FaultDetector"]

from .training import train_detector  # noqa: E402

__all__ += ["train_detector"]

from .frame_labeller import FrameFailure, FrameInputError, FrameLabeller, LabellerConfigError, load_labeller  # noqa: E402

__all__ += ["FrameFailure", "FrameInputError", "FrameLabeller", "LabellerConfigError", "load_labeller"]

from .head_profile import HeadProfile, ProfileError  # noqa: E402

__all__ += ["HeadProfile", "ProfileError"]

from .recording import (  # noqa: E402
    LabelTable,
    Recording,
    RecordingError,
    labels_from_csv,
    load_recording,
    read_labels_csv,
    save_recording,
)

__all__ += ["LabelTable", "Recording", "RecordingError", "labels_from_csv", "load_recording", "read_labels_csv",
            "save_recording"]

from ._fileio import refuse_to_replace  # noqa: E402

__all__ += ["refuse_to_replace"]

from .gate import GateResult, HealthyGate  # noqa: E402

__all__ += ["GateResult", "HealthyGate"]
