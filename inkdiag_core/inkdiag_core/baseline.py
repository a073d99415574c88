"""The former single baselines module, kept as an import path: everything is in
:mod:`inkdiag_core.baselines` now (``features``, ``training``, ``recorder``, ``store``).
"""

from .baselines import (  # noqa: F401
    BASELINE_FORMAT,
    BASELINE_FORMAT_VERSION,
    DEFAULT_MAX_NOZZLES,
    FM_METHOD,
    GAIN_MISMATCH_LOG,
    N_KPIS,
    PHASE_MISMATCH_RAD,
    RELATIVE_NAMES,
    BaselineFileError,
    BaselineKpis,
    BaselineRecorder,
    NozzleBaselines,
    baseline_kpis,
    baseline_training_kpis,
    baseline_training_rows,
    with_baseline,
)

__all__ = ["BASELINE_FORMAT", "BASELINE_FORMAT_VERSION", "DEFAULT_MAX_NOZZLES", "FM_METHOD", "GAIN_MISMATCH_LOG", "N_KPIS",
           "PHASE_MISMATCH_RAD", "RELATIVE_NAMES", "BaselineFileError", "BaselineKpis", "BaselineRecorder", "NozzleBaselines", "baseline_kpis",
           "baseline_training_kpis", "baseline_training_rows", "with_baseline"]
