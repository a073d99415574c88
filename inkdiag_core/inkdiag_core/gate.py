"""A cheap healthy gate in front of the full model: :class:`HealthyGate` (issue 17).

Nearly every nozzle of a working head is healthy nearly all the time, and after
commissioning every nozzle has a recorded healthy reference trace
(:attr:`inkdiag_core.NozzleBaselines.reference`: the sample-wise median of its
recorded healthy jetting-pulse rows). A trace ``x`` (n_samples) of such a nozzle is
fitted to its nozzle's mean-removed reference ``r`` by least squares,
``x ~ g r + c``, from three row-wise dot products (``x.r``, ``x.1``, ``x.x``; ``r.r``
is precomputed, ``r.1`` is 0):

- ``g = x.r / r.r``, the gain (1 for a healthy jetting trace of that nozzle; about
  :data:`inkdiag_core.faults.OK_SIGNAL_DRIVE_FACTOR` = 0.8 for the OK-check pulse:
  the channel is linear);
- ``residual_fraction = (var - g x.r) / var`` with ``var = x.x - (x.1)^2 / n``: the
  share of the trace's variance about its mean that the scaled reference does not
  explain.

A row is *cleared* as healthy when its residual fraction is at most
``max_residual_fraction`` and its gain lies in the jetting band (class
``healthy_nozzle``) or the OK-check band (class ``ok_signal``). Every other row,
every row of a nozzle without a reference and every non-finite or constant row is
not cleared: it takes the full model.

Default thresholds (calibrated on simulated healthy traces of the default head, 30 dB
SNR, 1.5 K ink-temperature spread per trace, the reference from 8 healthy frames at the
nominal temperature; ``scripts/reports/gate.py`` measures them): the residual fraction
of healthy rows is about 0.0015 (jetting) / 0.002 (OK-check) at the median, 0.005 /
0.0053 at the 99th percentile and 0.0069 / 0.0073 at the 99.9th; their gain relative to
the reference spans 0.90-1.10 (jetting) and 0.72-0.88 (OK-check) between the 0.1st and
99.9th percentiles. The bands are those spans and the residual bound is 0.0075, above
both classes' 99.9th percentile. Within the bands, the fault rows nearest to it are
held-out crosstalk's with the neighbour's ring-down faint: of 70,000 (5,000 of the whole
range and 5,000 of the mild end per seed; ``scripts/report gate`` seeds 0 and 1, five
more seeds in a scratch run) one at 0.0057 (seed 1), the others at 0.010 or more. In the
report's two seeds, held-out foreign bodies come no nearer than 0.02 and every other class and
condition stays out of the bands; in the five others no fault row of any class or condition
lies in a band below 0.010. So each clears at most 0.1 % of its rows (``reports/gate.md``: per class, the smallest residual
fraction within the bands). A head with another noise level or temperature spread needs
its own numbers (its healthy rows' residual fractions and gains).

The three row sums are one compiled loop per row (:func:`inkdiag_core._kernels.row_sums`,
accumulated in float64). The gate holds each mean-removed reference as int16 with a power-of-two
scale (:func:`quantize_references`), half the bytes each trace's sums read, and fits to it re-centred
(``r.1`` stays 0: a trace's offset still changes no verdict): within ``2**-13`` of the row's largest
magnitude, far below a reference's own noise; no ROS.
"""

from __future__ import annotations

import warnings
from typing import NamedTuple

import numpy as np

from .faults import FaultClass

__all__ = ["CLEARED_HEALTHY", "CLEARED_OK", "GATE_CLASSES", "GateResult", "HealthyGate", "quantize_references"]

#: Default bound on a cleared row's residual fraction (module docstring).
DEFAULT_MAX_RESIDUAL_FRACTION = 0.0075
#: Default gain band of a cleared jetting-pulse row (``healthy_nozzle``), relative to its reference.
DEFAULT_JETTING_GAIN = (0.90, 1.10)
#: Default gain band of a cleared OK-check row (``ok_signal``), relative to its reference.
DEFAULT_OK_GAIN = (0.72, 0.88)


class GateResult(NamedTuple):
    """What :meth:`HealthyGate.screen` found, per row.

    Attributes
    ----------
    cleared : ndarray of bool, shape (n,)
        Cleared as healthy (no full model needed).
    classes : ndarray of object (str), shape (n,)
        ``"healthy_nozzle"`` or ``"ok_signal"`` where cleared, ``""`` elsewhere.
    gain : ndarray of float64, shape (n,)
        Least-squares gain of the row on its nozzle's reference; NaN without a reference.
    residual_fraction : ndarray of float64, shape (n,)
        Unexplained share of the row's variance, in [0, 1]; NaN without a reference.
    """

    cleared: np.ndarray
    classes: np.ndarray
    gain: np.ndarray
    residual_fraction: np.ndarray


def _band(name, v):
    try:
        lo, hi = (float(x) for x in v)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a pair (lo, hi), got {v!r}") from None
    if not (np.isfinite(lo) and np.isfinite(hi) and 0 < lo < hi):
        raise ValueError(f"{name} must be finite with 0 < lo < hi, got {v!r}")
    return lo, hi


class HealthyGate:
    """Clear rows as healthy by a gain/offset fit to their nozzle's healthy reference.

    Parameters
    ----------
    baselines : NozzleBaselines
        The head's baselines; only nozzles with a reference trace
        (:attr:`NozzleBaselines.reference`) can be cleared. Without references no
        row is ever cleared (:attr:`active` is False).
    max_residual_fraction : float
        Largest residual fraction of a cleared row, in (0, 1) (module docstring).
    jetting_gain, ok_gain : (float, float)
        Gain bands of cleared ``healthy_nozzle`` and ``ok_signal`` rows; they must not overlap.

    Raises
    ------
    ValueError
        Bad thresholds.
    """

    def __init__(self, baselines, *, max_residual_fraction: float = DEFAULT_MAX_RESIDUAL_FRACTION,
                 jetting_gain=DEFAULT_JETTING_GAIN, ok_gain=DEFAULT_OK_GAIN):
        t = float(max_residual_fraction)
        if not 0.0 < t < 1.0:
            raise ValueError(f"max_residual_fraction must be in (0, 1), got {max_residual_fraction!r}")
        self.max_residual_fraction = t
        self.jetting_gain = _band("jetting_gain", jetting_gain)
        self.ok_gain = _band("ok_gain", ok_gain)
        if self.ok_gain[1] >= self.jetting_gain[0] and self.jetting_gain[1] >= self.ok_gain[0]:
            raise ValueError(f"ok_gain {self.ok_gain} and jetting_gain {self.jetting_gain} overlap")
        self.baselines = baselines
        ref = baselines.reference
        if ref is None or not len(baselines):
            self._ref = None
            return
        with warnings.catch_warnings():  # a nozzle without a reference is a row of NaN: its mean is NaN
            warnings.filterwarnings("ignore", "Mean of empty slice", RuntimeWarning)
            centred = (ref - np.nanmean(ref, axis=1, keepdims=True)).astype(np.float32)
        rr = np.einsum("ij,ij->i", centred.astype(np.float64), centred.astype(np.float64))
        usable = np.isfinite(rr) & (rr > 0)
        centred[~usable] = 0.0
        peak = np.abs(centred).max(axis=1)
        usable &= (peak >= _PEAK_RANGE[0]) & (peak < _PEAK_RANGE[1])  # else not quantizable: no reference
        centred[~usable] = 0.0
        self._ref, self._scale = quantize_references(centred)  # int16: half the bytes read per trace
        exact = self._ref * self._scale[:, None]  # float64, exact
        self._mean = exact.mean(axis=1)  # rounding moved each row's mean off 0: the sums are against exact - mean
        exact -= self._mean[:, None]
        rr = np.einsum("ij,ij->i", exact, exact)
        usable &= rr > 0
        self._rr = np.where(usable, rr, np.nan)
        self._usable = usable
        ids = baselines.nozzle_ids
        self._table = None  # each nozzle id's usable reference row (-1: none), by id, where the ids are dense
        if ids[-1] < max(1 << 16, 4 * len(ids)):
            self._table = np.full(int(ids[-1]) + 1, -1, np.int64)
            self._table[ids[usable]] = np.flatnonzero(usable)

    @property
    def active(self) -> bool:
        """Whether any nozzle has a usable reference."""
        return self._ref is not None and bool(self._usable.any())

    @property
    def n_samples(self) -> int:
        return int(self.baselines.n_samples)

    def screen(self, traces, nozzle_ids) -> GateResult:
        """Fit each row to its nozzle's reference and clear the healthy ones.

        Parameters
        ----------
        traces : array_like of float, shape (n, n_samples)
            V; float32 and float64 are used as they are (no copy), other dtypes are converted to float32.
        nozzle_ids : int or array_like of int, shape (n,)
            Each row's nozzle id; an int: the first row's, the others consecutive.

        Returns
        -------
        GateResult

        Raises
        ------
        ValueError
            ``traces`` is not 2-D with the baselines' ``n_samples``, or ``nozzle_ids``
            has the wrong shape.
        """
        x = np.asarray(traces)
        if x.ndim != 2 or x.shape[1] != self.n_samples:
            raise ValueError(f"traces must have shape (n, {self.n_samples}), got {x.shape}")
        if x.dtype not in (np.float32, np.float64):
            x = x.astype(np.float32)
        n = x.shape[0]
        if np.ndim(nozzle_ids) == 0:
            first = int(nozzle_ids)
            ids = np.arange(first, first + n, dtype=np.int64)
        else:
            ids = np.asarray(nozzle_ids, dtype=np.int64)
            if ids.shape != (n,):
                raise ValueError(f"nozzle_ids must have shape ({n},), got {ids.shape}")
        if self._ref is None or n == 0:
            return _nothing_cleared(n)
        pos = self.positions(ids)
        return self.decide(*_row_sums(x, self._ref, pos, self._scale, self._mean), pos)

    def positions(self, nozzle_ids) -> np.ndarray:
        """Each nozzle's row of the gate's reference table, -1 where it has no usable reference.

        Parameters
        ----------
        nozzle_ids : array_like of int, shape (n,)

        Returns
        -------
        ndarray of int64, shape (n,)
            What :meth:`decide` and the row-sums kernel (:attr:`references`) take.
        """
        ids = np.asarray(nozzle_ids, dtype=np.int64)
        if self._ref is None:
            return np.full(ids.shape, -1, np.int64)
        t = self._table
        if t is not None:  # one look-up per id; an id outside the table has no baseline
            if ids.size and ids.min() >= 0 and ids.max() < t.size:
                return t[ids]
            return np.where((ids >= 0) & (ids < t.size), t[np.clip(ids, 0, t.size - 1)], -1)
        has, pos = self.baselines.reference_rows(ids)
        return np.where(has & self._usable[pos], pos, -1)

    def range_positions(self, first: int, n: int) -> np.ndarray:
        """:meth:`positions` of the consecutive ids ``first .. first + n - 1``: a slice of the gate's
        table where it covers them (no array of ids built, nothing looked up).

        Parameters
        ----------
        first, n : int

        Returns
        -------
        ndarray of int64, shape (n,)
        """
        t = None if self._ref is None else self._table
        if t is not None and 0 <= first and first + n <= t.size:
            return t[first:first + n].copy()  # a copy: the table is the gate's
        return self.positions(np.arange(first, first + n, dtype=np.int64))

    @property
    def verdict_params(self) -> tuple | None:
        """What the compiled verdict takes (:func:`inkdiag_core._kernels.screen_gate_frames`):
        ``(quantized references, r.r per reference row, n_samples, max_residual_fraction, jetting_gain, ok_gain,
        the references' scales, their means)``; None without references."""
        if self._ref is None:
            return None
        return (self._ref, self._rr, self.n_samples, self.max_residual_fraction, self.jetting_gain, self.ok_gain,
                self._scale, self._mean)

    @property
    def references(self) -> np.ndarray | None:
        """The mean-removed reference traces as the gate fits them (quantized, :func:`quantize_references`, and
        re-centred), float32 (n_nozzles_with_baselines, n_samples), V; None without. A new array per call."""
        if self._ref is None:
            return None
        return (self._ref * self._scale[:, None] - self._mean[:, None]).astype(np.float32)

    def decide(self, x1, xx, xr, pos) -> GateResult:
        """Clear rows from their three sums against their references (:meth:`screen` from the sums).

        Parameters
        ----------
        x1, xx, xr : ndarray of float64, shape (n,)
            Each row's ``sum(x)``, ``sum(x * x)`` and ``sum(x * r)``, V, V^2, V^2, with ``r`` its
            reference (:attr:`references` row ``pos``); any value where ``pos`` is -1.
        pos : ndarray of int64, shape (n,)
            :meth:`positions` (-1: not cleared).

        Returns
        -------
        GateResult
        """
        has = pos >= 0
        with np.errstate(invalid="ignore", divide="ignore"):
            g = np.where(has, xr, np.nan) / (self._rr[pos] if self._ref is not None else np.nan)
            var = xx - x1 * x1 / self.n_samples
            f = (var - g * xr) / var
        f = np.where(var > 0, np.minimum(np.maximum(f, 0.0), 1.0), np.nan)
        f[~has] = np.nan
        ok = f <= self.max_residual_fraction  # NaN: False
        jet = ok & (g >= self.jetting_gain[0]) & (g <= self.jetting_gain[1])
        oks = ok & (g >= self.ok_gain[0]) & (g <= self.ok_gain[1])
        code = jet.view(np.uint8) + 2 * oks.view(np.uint8)  # the bands do not overlap: 0, 1 or 2
        return GateResult(jet | oks, GATE_CLASSES[code], g, f)

    def codes(self, x1, xx, xr, pos) -> np.ndarray:
        """:meth:`decide`'s verdict alone, per row: 0 not cleared, 1 ``healthy_nozzle``, 2 ``ok_signal``
        (:data:`GATE_CLASSES`), from one compiled loop (:func:`inkdiag_core._kernels.gate_codes`: the
        same arithmetic, the same verdicts; the labeller's kernel, :func:`inkdiag_core._kernels.screen_gate_frames`,
        calls the same loop). Same arguments as :meth:`decide`."""
        n = np.shape(x1)[0]
        if self._ref is None:
            return np.zeros(n, np.uint8)
        from ._kernels import gate_codes  # numba: imported when a kernel is first needed

        return gate_codes(x1, xx, xr, pos, self._rr, self.n_samples, self.max_residual_fraction, self.jetting_gain,
                          self.ok_gain)


#: A gate row's class by its code: not cleared, cleared jetting, cleared OK-check.
GATE_CLASSES = np.array(["", FaultClass.HEALTHY_NOZZLE.value, FaultClass.OK_SIGNAL.value], dtype=object)
#: The codes of rows cleared as ``healthy_nozzle`` / ``ok_signal`` among the labeller's per-row codes
#: (:func:`inkdiag_core._kernels.screen_gate_frames`: 0 left for the detector, 1-4 screening's reasons).
CLEARED_HEALTHY, CLEARED_OK = 5, 6


def _nothing_cleared(n: int) -> GateResult:
    return GateResult(np.zeros(n, bool), np.full(n, "", dtype=object), np.full(n, np.nan), np.full(n, np.nan))


def _row_sums(x, ref, pos, scale, mean):
    """``sum(x)``, ``sum(x * x)``, ``sum(x * r)`` per row in float64, ``r = ref[pos] * scale[pos] - mean[pos]``
    (NaN where ``pos`` is -1): the compiled kernel (one loop per row)."""
    from ._kernels import screen_and_row_sums

    return screen_and_row_sums(x, None, None, None, ref, pos, ref_scale=scale, ref_mean=mean)[1:]


def _row_sums_numpy(x, ref, pos, scale, mean):
    """:func:`_row_sums` in numpy passes (the baseline ``scripts/bench fdi`` measures the kernel against):
    the references gathered, row-wise dot products as batched (1 x m) @ (m x 1) BLAS products, float32
    rows accumulated in float32."""
    r = (ref[pos] * scale[pos, None] - mean[pos, None]).astype(x.dtype)
    xr = np.matmul(x[:, None, :], r[:, :, None]).reshape(-1).astype(np.float64)
    xx = np.matmul(x[:, None, :], x[:, :, None]).reshape(-1).astype(np.float64)
    none = pos < 0
    xr[none] = np.nan
    return x.sum(axis=1).astype(np.float64), xx, xr


def quantize_references(ref):
    """Reference rows as int16 and a power-of-two scale per row: ``q * scale`` (float32-exact) is each row to
    within half a step, at most ``2**-14`` of the row's largest magnitude.

    The healthy gate's references are read for every trace of a working head; int16 halves what each
    trace's sums read from memory (``scripts/bench node``). A reference is the median of a few
    noisy healthy frames: its own noise is orders of magnitude above this rounding.

    Parameters
    ----------
    ref : ndarray of float, shape (n_ref, m)
        Finite rows (a row of zeros stays zeros).

    Returns
    -------
    q : ndarray of int16, shape (n_ref, m)
        ``|q| <= 2**14``.
    scale : ndarray of float64, shape (n_ref,)
        Powers of two.

    Raises
    ------
    ValueError
        A row that is not finite, or whose values would not be float32-exact (beyond float32's range,
        or so small that they are subnormal).
    """
    ref = np.asarray(ref, dtype=np.float64)
    if ref.ndim != 2 or not np.isfinite(ref).all():
        raise ValueError(f"quantize_references takes finite rows (n_ref, m), got shape {ref.shape}"
                         + ("" if ref.ndim != 2 else " with a NaN or Inf"))
    peak = np.abs(ref).max(axis=1) if ref.size else np.zeros(ref.shape[0])
    scale = np.ldexp(1.0, np.frexp(peak)[1] - 14)  # peak < 2**e: |q| <= 2**14 after rounding
    nonzero = peak > 0
    if np.any(nonzero & ((peak < _PEAK_RANGE[0]) | (peak >= _PEAK_RANGE[1]))):
        raise ValueError(f"quantize_references: row peaks from {peak[nonzero].min():.3g} to {peak.max():.3g}; "
                         f"float32-exact steps need peaks in [{_PEAK_RANGE[0]:.3g}, {_PEAK_RANGE[1]:.3g})")
    q = np.rint(ref / scale[:, None]).astype(np.int16)
    return q, scale


#: The row peaks :func:`quantize_references` takes (besides 0): steps of ``q * scale`` normal float32 numbers
#: (scale >= float32's smallest normal), and ``2**14 * scale`` within float32's range.
_PEAK_RANGE = (2.0 ** 14 * float(np.finfo(np.float32).tiny), float(np.finfo(np.float32).max) / 2)
