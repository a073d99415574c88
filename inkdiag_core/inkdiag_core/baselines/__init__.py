"""Per-nozzle healthy baselines: each nozzle compared with itself.

A nozzle's trace depends on its fault and on its own build: nozzle radius and
length, piezo compliance and coupling, drive and sense-amplifier tolerances
(:class:`inkdiag_core.simulator.Spreads`). Those tolerances blur the classes of
any classifier that sees one trace alone (``reports/fdi.md``: a Random Forest
on each trace's *true* dominant mode reaches only ~88 %). They are properties
of the nozzle, not of the moment, so a monitor that has seen the nozzle healthy
(after a purge or at commissioning) can divide them out: the trace's KPIs
relative to the nozzle's own healthy KPIs.

One module per job:

- :mod:`.features`: :func:`baseline_kpis` (a nozzle's baseline, the median KPIs over a
  few healthy frames), :func:`with_baseline` (the input rows of a baseline pipeline,
  ``[trace, baseline]``), :class:`BaselineKpis` (transformer from those rows to KPI_Y
  plus the relative features :data:`RELATIVE_NAMES`);
- :mod:`.training`: :func:`baseline_training_kpis`, :func:`baseline_training_rows`
  (training rows from a simulation; imports the simulator when called);
- :mod:`.recorder`: :class:`BaselineRecorder`, a head's baselines from its frames as
  they arrive (nozzle ranges of any size, in any order), as a printer records them
  after a purge;
- :mod:`.store`: :class:`NozzleBaselines`, the recorded baselines by nozzle id, saved
  to and loaded from a checked ``.npz`` file (:class:`BaselineFileError` says what is
  wrong).
"""

from .features import N_KPIS, RELATIVE_NAMES, BaselineKpis, baseline_kpis, with_baseline
from .recorder import DEFAULT_MAX_NOZZLES, FM_METHOD, BaselineRecorder
from .store import (BASELINE_FORMAT, BASELINE_FORMAT_VERSION, GAIN_MISMATCH_LOG, PHASE_MISMATCH_RAD, BaselineFileError,
                    NozzleBaselines)
from .training import baseline_training_kpis, baseline_training_rows

__all__ = ["BASELINE_FORMAT", "BASELINE_FORMAT_VERSION", "DEFAULT_MAX_NOZZLES", "FM_METHOD", "GAIN_MISMATCH_LOG", "N_KPIS",
           "PHASE_MISMATCH_RAD", "RELATIVE_NAMES", "BaselineFileError", "BaselineKpis", "BaselineRecorder", "NozzleBaselines", "baseline_kpis",
           "baseline_training_kpis", "baseline_training_rows", "with_baseline"]
