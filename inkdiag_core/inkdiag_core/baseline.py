"""Per-nozzle healthy baselines: each nozzle compared with itself.

A nozzle's trace depends on its fault and on its own build: nozzle radius and
length, piezo compliance and coupling, drive and sense-amplifier tolerances
(:class:`inkdiag_core.simulator.Spreads`). Those tolerances blur the classes of
any classifier that sees one trace alone (``reports/fdi.md``: a Random Forest
on each trace's *true* dominant mode reaches only ~88 %). They are properties
of the nozzle, not of the moment, so a monitor that has seen the nozzle healthy
(after a purge or at commissioning) can divide them out: the trace's KPIs
relative to the nozzle's own healthy KPIs.

- :func:`baseline_kpis`: a nozzle's baseline, the median KPIs over a few healthy frames;
- :func:`with_baseline`: the input rows of a baseline pipeline, ``[trace, baseline]``;
- :class:`BaselineKpis`: transformer from those rows to KPI_Y plus the relative features;
- :class:`BaselineRecorder`: a head's baselines from its frames as they arrive (nozzle
  ranges of any size, in any order), as a printer records them after a purge;
- :class:`NozzleBaselines`: the recorded baselines by nozzle id, saved to and loaded
  from a checked ``.npz`` file (:class:`BaselineFileError` says what is wrong).
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
import warnings
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from sklearn.base import BaseEstimator, TransformerMixin
from sklearn.utils.validation import check_is_fitted, validate_data

from . import checks
from .estimation import estimate_fm_batch
from .kpis import KPI_NAMES, MIN_KPI_SAMPLES, InvalidTraceError, extract_kpis
from .model import InkChannelModel
from .screening import screen_traces

__all__ = ["RELATIVE_NAMES", "BaselineFileError", "BaselineKpis", "BaselineRecorder",
           "NozzleBaselines", "baseline_kpis", "baseline_training_kpis", "baseline_training_rows",
           "with_baseline"]

N_KPIS = len(KPI_NAMES)

#: Names of the relative features :class:`BaselineKpis` appends to KPI_Y.
RELATIVE_NAMES = ("frequency_ratio", "damping_ratio_difference", "damping_ratio_ratio",
                  "amplitude_ratio", "energy_ratio", "phase_difference_rad")

_EPS = 1e-30


def baseline_kpis(frames, sample_rate_hz: float) -> np.ndarray:
    """A nozzle's healthy baseline: the median of its KPIs over healthy frames.

    Parameters
    ----------
    frames : array_like, shape (n_nozzles, n_frames, n_samples)
        Healthy traces of each nozzle, V (each row's frames from the same nozzle).
    sample_rate_hz : float

    Returns
    -------
    ndarray, shape (n_nozzles, 7)
        Columns of :data:`inkdiag_core.KPI_NAMES`. The median keeps a frame with a
        passing disturbance from moving the baseline.
    """
    f = np.asarray(frames)
    if f.ndim != 3 or f.shape[1] < 1:
        raise ValueError(f"frames must be (n_nozzles, n_frames >= 1, n_samples), got shape {f.shape}")
    n, k, m = f.shape
    return np.median(extract_kpis(f.reshape(n * k, m), sample_rate_hz).reshape(n, k, N_KPIS), axis=1)


def with_baseline(traces, baseline) -> np.ndarray:
    """Input rows of a ``"kpi_y+baseline"`` pipeline: each trace followed by its nozzle's baseline.

    Parameters
    ----------
    traces : array_like, shape (n, n_samples)
    baseline : array_like, shape (n, 7)
        Row ``i``: the baseline KPIs (:func:`baseline_kpis`) of trace ``i``'s nozzle.

    Returns
    -------
    ndarray, shape (n, n_samples + 7)
        float64 (float32 if both inputs are float32).
    """
    x = np.asarray(traces)
    b = np.asarray(baseline)
    if x.ndim != 2 or b.shape != (x.shape[0], N_KPIS):
        raise ValueError(f"traces must be (n, n_samples) and baseline (n, {N_KPIS}); got shapes "
                         f"{x.shape} and {b.shape}")
    return np.hstack([x, b.astype(np.result_type(x.dtype, b.dtype), copy=False)])


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
    from .simulation.datasets import healthy_twin_frames

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


class BaselineKpis(TransformerMixin, BaseEstimator):
    """KPI_Y of each trace plus its KPIs relative to its nozzle's healthy baseline.

    Input rows are ``[trace (n_samples), baseline KPIs (7)]`` (:func:`with_baseline`).
    Output (n, 7 + 6): :data:`inkdiag_core.KPI_NAMES`, then :data:`RELATIVE_NAMES`:
    frequency ratio, damping-ratio difference and ratio, amplitude ratio, energy
    ratio (dimensionless) and phase difference (rad, wrapped to (-pi, pi]).

    Parameters
    ----------
    sample_rate_hz : float
        Sample rate of the traces, Hz.
    """

    def __init__(self, sample_rate_hz=10e6):
        self.sample_rate_hz = sample_rate_hz

    def fit(self, X, y=None):
        validate_data(self, X, dtype=[np.float64, np.float32], ensure_min_features=MIN_KPI_SAMPLES + N_KPIS)
        return self

    def transform(self, X):
        check_is_fitted(self, "n_features_in_")
        X = validate_data(self, X, dtype=[np.float64, np.float32], reset=False)
        k = extract_kpis(X[:, :-N_KPIS], float(self.sample_rate_hz))
        b = X[:, -N_KPIS:].astype(np.float64)
        dphi = np.angle(np.exp(1j * (k[:, 4] - b[:, 4])))
        rel = np.column_stack([
            k[:, 1] / (b[:, 1] + _EPS), k[:, 2] - b[:, 2], k[:, 2] / (b[:, 2] + _EPS),
            k[:, 3] / (b[:, 3] + _EPS), k[:, 5] / (b[:, 5] + _EPS), dphi,
        ])
        return np.hstack([k, rel])

    def get_feature_names_out(self, input_features=None):
        return np.array(KPI_NAMES + RELATIVE_NAMES, dtype=object)


BASELINE_FORMAT = "inkdiag-nozzle-baselines"
BASELINE_FORMAT_VERSION = 2  # 2: optional healthy f_m per nozzle ("fm"); 1 (KPIs only) is still read
_READABLE_VERSIONS = (1, 2)
#: Nozzle ids a recorder accepts are below this (the trace wire format's limit, 2**24).
MAX_NOZZLES = 1 << 24


class BaselineFileError(ValueError):
    """A baselines file that is missing, not one, modified, or inconsistent (a ``ValueError``)."""


def _content_sha256(ids: np.ndarray, kpis: np.ndarray, meta: dict, fm=None) -> str:
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(ids, dtype="<i8").tobytes())
    h.update(np.ascontiguousarray(kpis, dtype="<f8").tobytes())
    if fm is not None:
        h.update(np.ascontiguousarray(fm, dtype="<f8").tobytes())
    h.update(json.dumps(meta, sort_keys=True).encode())
    return h.hexdigest()


@dataclass(frozen=True, eq=False)
class NozzleBaselines:
    """Healthy KPI baselines of a set of nozzles, one row per nozzle id.

    Parameters
    ----------
    nozzle_ids : array_like of int, shape (m,)
        Strictly increasing, non-negative.
    kpis : array_like of float, shape (m, 7)
        Finite; columns of :data:`inkdiag_core.KPI_NAMES` (SI units, as
        :func:`inkdiag_core.extract_kpis`).
    sample_rate_hz : float
        Sample rate of the traces behind them, Hz.
    n_samples : int
        Samples per trace behind them.
    n_frames : int
        Healthy frames per nozzle the median was taken over (at most).
    fm : array_like of float, shape (m,), optional
        Each nozzle's healthy f_m reading, 1/s: the median of
        ``estimate_fm_batch(rows, InkChannelModel(), sample_rate_hz).fm`` over
        its first healthy rows (:class:`BaselineRecorder` ``fm_frames``), for
        ``estimate_fm_batch(..., baseline_fm=...)``; NaN where a nozzle has
        none. None: no f_m baselines at all.

    Raises
    ------
    ValueError
        Shapes, order, finiteness or the scalars are wrong.
    """

    nozzle_ids: np.ndarray
    kpis: np.ndarray
    sample_rate_hz: float
    n_samples: int
    n_frames: int
    fm: np.ndarray | None = None

    def __post_init__(self):
        ids = np.asarray(self.nozzle_ids)
        kpis = np.asarray(self.kpis, dtype=np.float64)
        if ids.ndim != 1 or (ids.size and ids.dtype.kind not in "iu"):
            raise ValueError(f"nozzle_ids must be a 1-D integer array, got dtype {ids.dtype} shape {ids.shape}")
        ids = ids.astype(np.int64)
        if kpis.shape != (ids.size, N_KPIS):
            raise ValueError(f"kpis must have shape ({ids.size}, {N_KPIS}), got {kpis.shape}")
        if ids.size and (ids[0] < 0 or np.any(np.diff(ids) <= 0)):
            raise ValueError("nozzle_ids must be non-negative and strictly increasing")
        if not np.isfinite(kpis).all():
            raise ValueError("kpis must be finite")
        fm = None
        if self.fm is not None:
            fm = np.asarray(self.fm, dtype=np.float64)
            if fm.shape != (ids.size,):
                raise ValueError(f"fm must have shape ({ids.size},), got {fm.shape}")
            if np.isinf(fm).any():
                raise ValueError("fm must be finite, or NaN where a nozzle has no f_m baseline")
            fm.flags.writeable = False
        fs = checks.sample_rate(self.sample_rate_hz, error=InvalidTraceError)
        for name in ("n_samples", "n_frames"):
            v = getattr(self, name)
            if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)) or v < 1:
                raise ValueError(f"{name} must be a positive integer, got {v!r}")
        for arr in (ids, kpis):
            arr.flags.writeable = False
        object.__setattr__(self, "nozzle_ids", ids)
        object.__setattr__(self, "kpis", kpis)
        object.__setattr__(self, "fm", fm)
        object.__setattr__(self, "sample_rate_hz", fs)
        object.__setattr__(self, "n_samples", int(self.n_samples))
        object.__setattr__(self, "n_frames", int(self.n_frames))

    def __len__(self) -> int:
        return int(self.nozzle_ids.size)

    def lookup(self, nozzle_ids):
        """The baselines of the given nozzles.

        Parameters
        ----------
        nozzle_ids : array_like of int, shape (n,)

        Returns
        -------
        has : ndarray of bool, shape (n,)
            Whether each nozzle has a baseline.
        kpis : ndarray of float64, shape (n, 7)
            Its baseline, NaN where it has none.
        """
        has, pos = self._rows(nozzle_ids)
        out = np.full((has.size, N_KPIS), np.nan)
        out[has] = self.kpis[pos[has]]
        return has, out

    def _rows(self, nozzle_ids):
        """Whether each nozzle id has a row, and its row (clipped where it has none)."""
        q = np.asarray(nozzle_ids, dtype=np.int64).reshape(-1)
        pos = np.minimum(np.searchsorted(self.nozzle_ids, q), max(len(self) - 1, 0))
        has = self.nozzle_ids[pos] == q if len(self) else np.zeros(q.size, bool)
        return has, pos

    def lookup_fm(self, nozzle_ids):
        """The healthy f_m baselines of the given nozzles.

        Parameters
        ----------
        nozzle_ids : array_like of int, shape (n,)

        Returns
        -------
        has : ndarray of bool, shape (n,)
            Whether each nozzle has an f_m baseline.
        fm : ndarray of float64, shape (n,)
            Its healthy f_m, 1/s; 0 where it has none (``baseline_fm``'s "none").
        """
        has, pos = self._rows(nozzle_ids)
        if self.fm is None:
            return np.zeros(has.size, bool), np.zeros(has.size)
        fm = np.where(has, self.fm[pos] if len(self) else 0.0, np.nan)
        has = ~np.isnan(fm)
        return has, np.where(has, fm, 0.0)

    def _meta(self) -> dict:
        return {"format": BASELINE_FORMAT, "format_version": BASELINE_FORMAT_VERSION,
                "kpi_names": list(KPI_NAMES), "sample_rate_hz": self.sample_rate_hz,
                "n_samples": self.n_samples, "n_frames": self.n_frames, "has_fm": self.fm is not None}

    def save(self, path) -> Path:
        """Write an ``.npz`` (no pickle) with the arrays, the settings and their sha256.

        Written to a temporary file and renamed, so a reader never sees half a file.
        Returns the path written.
        """
        path = Path(path)
        meta = self._meta()
        meta["sha256"] = _content_sha256(self.nozzle_ids, self.kpis, self._meta(), self.fm)
        arrays = {"nozzle_ids": self.nozzle_ids, "kpis": self.kpis}
        if self.fm is not None:
            arrays["fm"] = self.fm
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name + ".", suffix=".tmp")
        try:
            with os.fdopen(fd, "wb") as f:
                np.savez(f, **arrays, meta=np.array(json.dumps(meta, sort_keys=True)))
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        return path

    @classmethod
    def load(cls, path) -> "NozzleBaselines":
        """Read a file written by :meth:`save`, checking it before use.

        Raises
        ------
        BaselineFileError
            The file is missing, not a baselines file (or another format version),
            its arrays do not match the checksum it carries (modified or corrupted),
            or they are inconsistent.
        """
        path = Path(path)
        if not path.is_file():
            raise BaselineFileError(f"no baselines file at {path}")
        try:
            with np.load(path, allow_pickle=False) as z:
                arrays = {k: z[k] for k in ("nozzle_ids", "kpis", "meta")}
                fm = z["fm"] if "fm" in z.files else None
            meta = json.loads(str(arrays["meta"]))
        except (OSError, ValueError, KeyError, EOFError, TypeError, zipfile.BadZipFile, zlib.error) as exc:
            raise BaselineFileError(f"{path} is not an inkdiag baselines file, or is damaged "
                                    f"({type(exc).__name__}: {exc})") from None
        if not isinstance(meta, dict) or meta.get("format") != BASELINE_FORMAT:
            raise BaselineFileError(f"{path} is not an inkdiag baselines file (format "
                                    f"{meta.get('format') if isinstance(meta, dict) else meta!r})")
        if meta.get("format_version") not in _READABLE_VERSIONS:
            raise BaselineFileError(f"{path}: baselines format version {meta.get('format_version')!r}, "
                                    f"this inkdiag reads {', '.join(map(str, _READABLE_VERSIONS))}")
        if (fm is not None) != bool(meta.get("has_fm", False)):
            raise BaselineFileError(f"{path}: its f_m column does not match its header (modified or "
                                    "corrupted); record the baselines again")
        if meta.get("kpi_names") != list(KPI_NAMES):
            raise BaselineFileError(f"{path}: KPI columns {meta.get('kpi_names')!r} are not {list(KPI_NAMES)}")
        stored = meta.pop("sha256", None)
        ids, kpis = arrays["nozzle_ids"], arrays["kpis"]
        try:
            actual = _content_sha256(ids, kpis, meta, fm)
        except (TypeError, ValueError) as exc:
            raise BaselineFileError(f"{path}: unreadable arrays ({exc})") from None
        if stored != actual:
            raise BaselineFileError(f"{path}: its content does not match its sha256 (modified or "
                                    "corrupted); record the baselines again")
        try:
            return cls(ids, kpis, meta["sample_rate_hz"], meta["n_samples"], meta["n_frames"], fm)
        except (KeyError, ValueError) as exc:
            raise BaselineFileError(f"{path}: inconsistent baselines ({exc})") from None


class BaselineRecorder:
    """Record each nozzle's healthy baseline from the frames of a head, as they arrive.

    Each :meth:`add` takes one message's rows (a contiguous nozzle range, any size,
    any order, repeated ranges welcome); rows that :func:`inkdiag_core.screen_traces`
    finds invalid, or that ``keep`` excludes, are not used. A nozzle's baseline is the
    median of its first ``n_frames`` valid rows' KPIs (:func:`baseline_kpis` on
    the same traces gives the same numbers); rows beyond that are ignored, so memory
    stays at ``n_frames`` KPI rows per nozzle. Record while the head is healthy
    (after a purge, at commissioning).

    Parameters
    ----------
    n_frames : int
        Frames per nozzle in its baseline, >= 1.
    sample_rate_hz : float
        Sample rate of the traces, Hz.
    n_samples : int
        Samples per trace; every frame must have it.
    fm_frames : int
        Also record each nozzle's healthy f_m reading (:attr:`NozzleBaselines.fm`),
        the median of ``estimate_fm_batch(rows, InkChannelModel(), sample_rate_hz).fm``
        over its first ``fm_frames`` rows (at most ``n_frames``); 0: none. It costs
        about a millisecond per row, so it is taken on fewer rows than the KPIs.
    """

    def __init__(self, *, n_frames: int = 8, sample_rate_hz: float = 10e6, n_samples: int = 512,
                 fm_frames: int = 0):
        if isinstance(n_frames, bool) or not isinstance(n_frames, (int, np.integer)) or n_frames < 1:
            raise ValueError(f"n_frames must be a positive integer, got {n_frames!r}")
        if isinstance(fm_frames, bool) or not isinstance(fm_frames, (int, np.integer)) \
                or not 0 <= fm_frames <= n_frames:
            raise ValueError(f"fm_frames must be an integer in 0..n_frames ({n_frames}), got {fm_frames!r}")
        self.fm_frames = int(fm_frames)
        if isinstance(n_samples, bool) or not isinstance(n_samples, (int, np.integer)) or n_samples < MIN_KPI_SAMPLES:
            raise ValueError(f"n_samples must be an integer >= {MIN_KPI_SAMPLES}, got {n_samples!r}")
        self.n_frames = int(n_frames)
        self.sample_rate_hz = checks.sample_rate(sample_rate_hz, error=InvalidTraceError)
        self.n_samples = int(n_samples)
        self._ids = []  # chunks of the rows kept so far, in arrival order
        self._kpis = []
        self._count_of = np.zeros(0, np.int32)  # rows kept per nozzle id (dense, grown on demand)

    def add(self, first_nozzle: int, traces, keep=None) -> int:
        """Use one message's rows: nozzles ``first_nozzle .. first_nozzle + n - 1``.

        Parameters
        ----------
        first_nozzle : int
            Id of row 0's nozzle, >= 0.
        traces : array_like, shape (n, n_samples)
            V.
        keep : array_like of bool, shape (n,), optional
            Rows to use (for instance those a classifier calls healthy).

        Returns
        -------
        int
            Rows used.
        """
        if isinstance(first_nozzle, bool) or not isinstance(first_nozzle, (int, np.integer)) or first_nozzle < 0:
            raise ValueError(f"first_nozzle must be a non-negative integer, got {first_nozzle!r}")
        x = np.asarray(traces)
        if x.ndim != 2 or x.shape[1] != self.n_samples:
            raise ValueError(f"traces must have shape (n, {self.n_samples}), got {x.shape}")
        if first_nozzle + x.shape[0] > MAX_NOZZLES:
            raise ValueError(f"nozzle ids must stay below {MAX_NOZZLES} (2**24, the wire format's limit), "
                             f"got {first_nozzle}..{first_nozzle + x.shape[0] - 1}")
        use, _ = screen_traces(x)
        if keep is not None:
            k = np.asarray(keep, dtype=bool)
            if k.shape != (x.shape[0],):
                raise ValueError(f"keep must have shape ({x.shape[0]},), got {k.shape}")
            use &= k
        ids = first_nozzle + np.flatnonzero(use)
        # only nozzles still short of n_frames rows (at most their shortfall; the ids of
        # one message are distinct)
        if ids.size and ids[-1] >= self._count_of.size:
            grown = np.zeros(max(int(ids[-1]) + 1, 2 * self._count_of.size), np.int32)
            grown[: self._count_of.size] = self._count_of
            self._count_of = grown
        need = self._count_of[ids] < self.n_frames
        if not need.any():
            return 0
        rows = np.flatnonzero(use)[need]
        ids = ids[need]
        y = checks.traces_2d(x[rows], min_samples=MIN_KPI_SAMPLES, error=InvalidTraceError)
        kpis = np.full((ids.size, N_KPIS + 1), np.nan)  # the last column: f_m, NaN where not taken
        kpis[:, :N_KPIS] = extract_kpis(y, self.sample_rate_hz)
        if self.fm_frames:
            fm_rows = np.flatnonzero(self._count_of[ids] < self.fm_frames)
            if fm_rows.size:
                kpis[fm_rows, N_KPIS] = estimate_fm_batch(y[fm_rows], InkChannelModel(), self.sample_rate_hz).fm
        self._kpis.append(kpis)
        self._ids.append(ids.astype(np.int64))
        self._count_of[ids] += 1  # the ids of one message are distinct
        return int(ids.size)

    @property
    def n_complete(self) -> int:
        """Nozzles with ``n_frames`` rows recorded."""
        return int(np.count_nonzero(self._count_of >= self.n_frames))

    def baselines(self, min_frames: int | None = None) -> NozzleBaselines:
        """The baselines of the nozzles with at least ``min_frames`` rows (default ``n_frames``).

        Each is the median over the nozzle's rows (up to ``n_frames``), KPI by KPI.
        """
        need = self.n_frames if min_frames is None else int(min_frames)
        if not 1 <= need <= self.n_frames:
            raise ValueError(f"min_frames must be in 1..{self.n_frames}, got {min_frames!r}")
        all_ids = np.concatenate(self._ids) if self._ids else np.empty(0, np.int64)
        all_kpis = np.concatenate(self._kpis) if self._kpis else np.empty((0, N_KPIS + 1))
        order = np.argsort(all_ids, kind="stable")  # grouped by nozzle, arrival order within
        ids = np.flatnonzero(self._count_of).astype(np.int64)
        counts = self._count_of[ids].astype(np.int64)
        ok = counts >= need
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
        k = np.arange(self.n_frames)
        idx = starts[ok][:, None] + k  # (m, n_frames) rows of each nozzle, in arrival order
        valid = k < np.minimum(counts[ok], self.n_frames)[:, None]
        stack = np.where(valid[..., None], all_kpis[order][np.where(valid, idx, 0)], np.nan)
        if ok.any():
            with warnings.catch_warnings():  # a nozzle whose f_m rows were all non-finite: NaN
                warnings.simplefilter("ignore", RuntimeWarning)
                med = np.nanmedian(stack, axis=1)
        else:
            med = np.empty((0, N_KPIS + 1))
        return NozzleBaselines(ids[ok], med[:, :N_KPIS], self.sample_rate_hz, self.n_samples, self.n_frames,
                               fm=med[:, N_KPIS] if self.fm_frames else None)
