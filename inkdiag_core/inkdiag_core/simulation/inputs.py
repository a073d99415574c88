"""Input checks of the simulators, shared so that both validate alike."""

from __future__ import annotations

import numbers

import numpy as np

from ..checks import positive_float, positive_int
from ..faults import MECHANISMS, FaultClass, as_fault_class
from ..model import InkChannelParams
from .channels import DriveWaveform, Spreads
from .modal import class_max_frequency

__all__ = [
    "check_counts",
    "check_severity",
    "check_positive_int",
    "check_positive_float",
    "prepare_run",
]


def check_counts(counts):
    """Validate ``counts`` (mapping FaultClass or value -> int); returns [(FaultClass, count)] in declaration order."""
    if not hasattr(counts, "items"):
        raise ValueError(
            f"counts must be a mapping FaultClass -> number of traces, got {type(counts).__name__}"
        )
    merged = {}
    for key, value in counts.items():
        cls = as_fault_class(key, name="counts")
        if isinstance(value, bool) or not isinstance(value, numbers.Integral):
            if isinstance(value, float) and value.is_integer():
                pass
            else:
                raise ValueError(
                    f"counts[{cls.value!r}] must be a non-negative integer, got {value!r}"
                )
        if value < 0:
            raise ValueError(f"counts[{cls.value!r}] must be a non-negative integer, got {value!r}")
        merged[cls] = merged.get(cls, 0) + int(value)
    # canonical order: FaultClass declaration order
    return [(c, merged[c]) for c in FaultClass if merged.get(c, 0) > 0]


def check_severity(severity, classes):
    """Validate a severity override: {FaultClass: (count,) array}, physical bounds."""
    if severity is None:
        return None
    if not hasattr(severity, "items"):
        raise ValueError(f"severity must be a mapping FaultClass -> values, got {type(severity).__name__}")
    counts = dict(classes)
    out = {}
    for key, values in severity.items():
        cls = as_fault_class(key, name="severity")
        mech = MECHANISMS[cls]
        if not mech.severity:
            raise ValueError(f"severity[{cls.value!r}]: this class has no severity variable")
        v = np.asarray(values, dtype=float).reshape(-1)
        if v.size != counts.get(cls, 0):
            raise ValueError(
                f"severity[{cls.value!r}] has {v.size} values, counts asks for {counts.get(cls, 0)}"
            )
        upper = 1.0 if mech.kind in ("nozzle_bubble", "particle") else np.inf
        lower = 0.0
        if not (np.isfinite(v).all() and (v >= lower).all() and (v < upper).all()):
            raise ValueError(
                f"severity[{cls.value!r}] must be finite and in [{lower}, {upper}) "
                f"({mech.severity}), got min {v.min()!r}, max {v.max()!r}"
            )
        if mech.kind in ("dried", "particle", "chamber_bubble") and (v <= 0).any():
            raise ValueError(f"severity[{cls.value!r}] must be > 0 ({mech.severity})")
        out[cls] = v
    return out


# The one positive-number checkers of the core (typed InputError, a ValueError), under the names
# the simulators use.
check_positive_int = positive_int
check_positive_float = positive_float


def prepare_run(classes, fs, spreads, drive, base, seed, extra=()):
    """Defaults, type checks, the Nyquist check, the generator and the labels.

    Shared by :func:`simulate` and :func:`inkdiag_core.simulate_nonlinear`, so
    both validate alike and draw identically. ``extra`` holds further
    ``(name, object, type)`` triples to type-check.
    """
    spreads = Spreads() if spreads is None else spreads
    drive = DriveWaveform() if drive is None else drive
    base = InkChannelParams() if base is None else base
    for name, obj, typ in (("spreads", spreads, Spreads), ("drive", drive, DriveWaveform),
                           ("base_params", base, InkChannelParams), *extra):
        if not isinstance(obj, typ):
            raise ValueError(f"{name} must be a {typ.__name__}, got {type(obj).__name__}")
    for cls, _ in classes:
        f_max = class_max_frequency(cls, base)
        if fs < 2.0 * f_max:
            raise ValueError(
                f"sample_rate_hz={fs:g} is below twice the highest mode of class "
                f"{cls.value!r} ({f_max:.4g} Hz): need at least {2 * f_max:.4g} Hz"
            )
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    labels = np.empty(sum(k for _, k in classes), dtype=object)
    i = 0
    for cls, k in classes:
        labels[i:i + k] = cls
        i += k
    return spreads, drive, base, rng, labels
