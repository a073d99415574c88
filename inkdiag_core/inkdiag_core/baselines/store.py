"""The recorded baselines by nozzle id (:class:`NozzleBaselines`) and their checked ``.npz`` file.

A file holds the arrays (``nozzle_ids``, ``kpis``, optional ``fm``, optional
``reference``: each nozzle's healthy reference trace for :class:`inkdiag_core.HealthyGate`), no pickle, and a
JSON header (``meta``) with :data:`BASELINE_FORMAT`, :data:`BASELINE_FORMAT_VERSION`,
the settings, the head profile's sha256 (``head_sha256``: the head the baselines
were recorded on) and the sha256 of the content; :meth:`NozzleBaselines.load` checks
them all and says what is wrong (:class:`BaselineFileError`). Files of versions 1
and 2 (before head profiles) read as baselines of the default head; files of versions
1 to 3 (before reference traces) read with no references (no healthy gate); files of
versions 2 to 4 read with ``fm_method`` None (their f_m readings are ``"vp_cal"``'s with the
default head's constants, whatever the head).
"""

from __future__ import annotations

import hashlib
import json
import os
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import checks
from .._fileio import temp_beside
from ..kpis import KPI_NAMES, InvalidTraceError, extract_kpis
from .features import N_KPIS

__all__ = ["BASELINE_FORMAT", "BASELINE_FORMAT_VERSION", "FM_METHOD", "GAIN_MISMATCH_LOG", "PHASE_MISMATCH_RAD",
           "BaselineFileError", "NozzleBaselines"]

BASELINE_FORMAT = "inkdiag-nozzle-baselines"
BASELINE_FORMAT_VERSION = 5  # 5: the estimator of the f_m readings ("fm_method"); 4: optional reference
# trace per nozzle ("reference"); 3: head_sha256; 2: optional healthy f_m per nozzle ("fm"); 1: KPIs only
_READABLE_VERSIONS = (1, 2, 3, 4, 5)
#: The estimator of a nozzle's healthy f_m reading (:attr:`NozzleBaselines.fm_method`): the raw
#: ``"vp"`` estimate. Subtracted from ``"vp_cal"`` estimates too: on the heads of
#: ``reports/heads.md`` a nozzle's offset is in the raw estimate, and taking its ``"vp_cal"``
#: reading off instead made the dried rows' d_mu errors larger than no baseline at all.
FM_METHOD = "vp"
#: |log| of the ratio of a head's healthy amplitude to its profile's beyond which
#: :meth:`NozzleBaselines.gain_mismatch` speaks: at a gain of 0.9 (log -0.105) the default model
#: called 22 % of the default head's deeply dried nozzles unknown; at 1.1, 17 % of its fully blocked.
GAIN_MISMATCH_LOG = 0.06
#: Phase difference (rad) between a head's healthy ringing and its profile's beyond which
#: :meth:`NozzleBaselines.gain_mismatch` speaks. An inverted sensor sign is pi (the default model then
#: called every class of the default head ``unknown``); a sensing window that starts later or earlier
#: than the profile's ``drive.switch_delay_s`` shifts it too: with the default model, 0.30 rad left 45 %
#: of the default head's traces ``unknown``, 0.15 rad 2 % (helper-93, 600 traces). Healthy nozzles of one
#: head agree within about 0.05 rad; five heads of ``tests/foreign_head.py`` with their true or calibrated
#: profiles gave no warning at 0.2 rad.
PHASE_MISMATCH_RAD = 0.2


def _default_head_sha256() -> str:
    from ..head_profile import HeadProfile  # the profile module imports the simulators

    return HeadProfile.default().sha256


class BaselineFileError(ValueError):
    """A baselines file that is missing, not one, modified, or inconsistent (a ``ValueError``)."""


def _content_sha256(ids: np.ndarray, kpis: np.ndarray, meta: dict, fm=None, reference=None) -> str:
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(ids, dtype="<i8").tobytes())
    h.update(np.ascontiguousarray(kpis, dtype="<f8").tobytes())
    if fm is not None:
        h.update(np.ascontiguousarray(fm, dtype="<f8").tobytes())
    if reference is not None:
        h.update(np.ascontiguousarray(reference, dtype="<f4").tobytes())
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
        ``estimate_fm_batch(rows, profile, sample_rate_hz, method=fm_method).fm`` over
        its first healthy rows (:class:`BaselineRecorder` ``fm_frames``), for
        ``estimate_fm_batch(..., baseline_fm=...)``; NaN where a nozzle has
        none. None: no f_m baselines at all.
    head_sha256 : str, optional
        :attr:`inkdiag_core.HeadProfile.sha256` of the head the baselines were
        recorded on (64 hex digits); default (None): the shipped default head's.
    reference : array_like of float, shape (m, n_samples), optional
        Each nozzle's healthy reference trace, V (float32): the sample-wise
        median of its recorded healthy rows (:class:`BaselineRecorder`), what
        :class:`inkdiag_core.HealthyGate` fits each new trace to; a row of NaN
        where a nozzle has none. None: no references (no gate).
    fm_method : {"vp", None}
        The estimator the ``fm`` readings were taken with (default :data:`FM_METHOD`; set to
        None when there is no ``fm``). None with ``fm``: ``"vp_cal"`` readings with the
        default head's constants, what files before version 5 hold;
        :class:`inkdiag_core.DryingTracker` uses those on the default head with ``"vp_cal"`` only.

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
    head_sha256: str | None = None
    reference: np.ndarray | None = None
    fm_method: str | None = FM_METHOD

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
        ref = None
        if self.reference is not None:
            ref = np.array(self.reference, dtype=np.float32)
            if ref.shape != (ids.size, int(self.n_samples)):
                raise ValueError(f"reference must have shape ({ids.size}, {int(self.n_samples)}), got {ref.shape}")
            if np.isinf(ref).any() or (np.isnan(ref).any(axis=1) != np.isnan(ref).all(axis=1)).any():
                raise ValueError("reference must be finite, or a whole row of NaN where a nozzle has none")
            ref.flags.writeable = False
        object.__setattr__(self, "reference", ref)
        if self.fm_method not in (FM_METHOD, None):
            raise ValueError(f"fm_method must be {FM_METHOD!r} or None, got {self.fm_method!r}")
        object.__setattr__(self, "fm_method", self.fm_method if fm is not None else None)
        for arr in (ids, kpis):
            arr.flags.writeable = False
        object.__setattr__(self, "nozzle_ids", ids)
        object.__setattr__(self, "kpis", kpis)
        object.__setattr__(self, "fm", fm)
        object.__setattr__(self, "sample_rate_hz", fs)
        object.__setattr__(self, "n_samples", int(self.n_samples))
        object.__setattr__(self, "n_frames", int(self.n_frames))
        head = _default_head_sha256() if self.head_sha256 is None else self.head_sha256
        if not isinstance(head, str) or len(head) != 64 or any(ch not in "0123456789abcdef" for ch in head):
            raise ValueError(f"head_sha256 must be a head profile's sha256 (64 lowercase hex digits), got {head!r}")
        object.__setattr__(self, "head_sha256", head)

    def check_head(self, profile, *, what: str = "baselines") -> None:
        """Refuse baselines recorded on another head than ``profile``.

        Parameters
        ----------
        profile : HeadProfile or str
            The head (or its sha256) the baselines are about to be used with.

        Raises
        ------
        BaselineFileError
            The baselines carry another head's sha256.
        """
        sha = profile if isinstance(profile, str) else profile.sha256
        if sha != self.head_sha256:
            name = "" if isinstance(profile, str) else f" {profile.name!r}"
            raise BaselineFileError(f"{what} were recorded on another head (profile sha256 {self.head_sha256[:12]}), "
                                    f"not on head profile{name} (sha256 {sha[:12]}): record them again on this head")

    def gain_mismatch(self, profile, *, n_sim: int = 256, seed: int = 0) -> str:
        """Whether these healthy nozzles ring at the amplitude and in the phase ``profile``'s healthy nozzles do.

        The amplitude KPI scales with the sensor gain, and a model trained on ``profile``
        reads it: a head whose analog gain is not the profile's has its faults called
        ``unknown`` (docs/controller.md). The baselines' median log amplitude is compared
        with that of ``n_sim`` healthy traces simulated on ``profile``; so is their mean
        phase (circular): beyond :data:`PHASE_MISMATCH_RAD` the sensor's sign is inverted
        (pi) or the sensing window starts at another delay than the profile's.

        Parameters
        ----------
        profile : HeadProfile
            The head the baselines are used with (its sampling must be theirs).
        n_sim : int
            Healthy traces simulated (about 0.1 s for 256 on the default head).
        seed : int

        Returns
        -------
        str
            "" when the two agree within :data:`GAIN_MISMATCH_LOG` (or three standard errors of
            their medians, if more: few nozzles) and :data:`PHASE_MISMATCH_RAD`, or when it cannot
            tell (fewer than 3 nozzles with an amplitude, a nominal profile, or baselines of another
            sampling: refused elsewhere); else one line saying the phase, the ratio or both, and what to do.
        """
        if (not profile.is_complete or self.sample_rate_hz != profile.sample_rate_hz
                or self.n_samples != profile.n_samples):
            return ""
        col = KPI_NAMES.index("amplitude")
        amp = np.abs(self.kpis[:, col])
        amp = amp[amp > 0]
        if amp.size < 3:
            return ""
        sim = extract_kpis(profile.simulate({"healthy_nozzle": n_sim}, seed=seed).traces, profile.sample_rate_hz)
        ref = np.abs(sim[:, col])
        la, lr = np.log(amp), np.log(ref[ref > 0])
        d = float(np.median(la) - np.median(lr))
        se = 1.2533 * float(np.hypot(la.std(ddof=1) / np.sqrt(la.size), lr.std(ddof=1) / np.sqrt(lr.size)))  # a median's
        ph = KPI_NAMES.index("phase_rad")
        mine = self.kpis[:, ph][np.isfinite(self.kpis[:, ph]) & (np.abs(self.kpis[:, col]) > 0)]
        dphi = float(np.angle(np.exp(1j * mine).mean() * np.conj(np.exp(1j * sim[:, ph]).mean()))) if mine.size >= 3 else 0.0
        said = []
        if abs(dphi) > PHASE_MISMATCH_RAD:
            said.append(
                f"the baselines' {mine.size} healthy nozzles ring {abs(dphi):.2f} rad out of phase with the healthy "
                f"nozzles of head {profile.name!r}: " + ("an inverted sensor sign? " if abs(dphi) > 2.5 else "")
                + "the model reads the phase (classes then read as unknown): negate the samples if the "
                "sensor's sign is inverted; else the sensing window starts at another delay than the profile's "
                "drive.switch_delay_s: give the controller's sensing delay as drive.switch_delay_s in the nominal "
                "profile, calibrate (inkdiag calibrate) and train on that profile")
        if abs(d) > max(GAIN_MISMATCH_LOG, 3.0 * se):
            said.append(
                f"the baselines' {amp.size} healthy nozzles ring at {np.exp(d):.2f}x the amplitude of the healthy "
                f"nozzles of head {profile.name!r}: a sensor gain other than the profile's? The model reads the "
                "amplitude (faults then read as unknown): calibrate this head's own profile (inkdiag calibrate) and "
                "train on it, or scale the samples to the profile's volts")
        return "; and ".join(said)

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

    @property
    def has_reference(self) -> bool:
        """Whether the baselines carry reference traces (:attr:`reference`)."""
        return self.reference is not None

    def reference_rows(self, nozzle_ids):
        """Where the given nozzles' reference traces are.

        Parameters
        ----------
        nozzle_ids : array_like of int, shape (n,)

        Returns
        -------
        has : ndarray of bool, shape (n,)
            Whether each nozzle has a reference trace (all False without references).
        rows : ndarray of int64, shape (n,)
            Its row of :attr:`reference` (meaningless where ``has`` is False).
        """
        has, pos = self._rows(nozzle_ids)
        if self.reference is None or not len(self):
            return np.zeros(has.size, bool), pos
        return has & ~np.isnan(self.reference[pos, 0]), pos

    def _meta(self) -> dict:
        return {"format": BASELINE_FORMAT, "format_version": BASELINE_FORMAT_VERSION,
                "kpi_names": list(KPI_NAMES), "sample_rate_hz": self.sample_rate_hz,
                "n_samples": self.n_samples, "n_frames": self.n_frames, "has_fm": self.fm is not None,
                "has_reference": self.reference is not None, "head_sha256": self.head_sha256,
                "fm_method": self.fm_method}

    def save(self, path) -> Path:
        """Write an ``.npz`` (no pickle) with the arrays, the settings and their sha256.

        Written to a temporary file and renamed, so a reader never sees half a file.
        Returns the path written.
        """
        path = Path(path)
        meta = self._meta()
        meta["sha256"] = _content_sha256(self.nozzle_ids, self.kpis, self._meta(), self.fm, self.reference)
        arrays = {"nozzle_ids": self.nozzle_ids, "kpis": self.kpis}
        if self.fm is not None:
            arrays["fm"] = self.fm
        if self.reference is not None:
            arrays["reference"] = self.reference
        fd, tmp = temp_beside(path)
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
            with open(path, "rb") as f:
                magic = f.read(4)
        except OSError as exc:
            raise BaselineFileError(f"{path}: cannot read it ({exc.strerror})") from None
        if not magic.startswith((b"PK\x03\x04", b"PK\x05\x06")):  # not a zip: numpy would talk of pickles
            raise BaselineFileError(f"{path} is not an inkdiag baselines file: not an .npz archive ("
                                    + (f"it starts with {magic!r})" if magic else "an empty file)"))
        try:
            with np.load(path, allow_pickle=False) as z:
                arrays = {k: z[k] for k in ("nozzle_ids", "kpis", "meta")}
                fm = z["fm"] if "fm" in z.files else None
                reference = z["reference"] if "reference" in z.files else None
            meta = json.loads(str(arrays["meta"]))
        except (OSError, ValueError, KeyError, EOFError, TypeError, RecursionError, zipfile.BadZipFile,
                zlib.error) as exc:  # RecursionError: a meta nested too deeply for json's decoder
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
        if (reference is not None) != bool(meta.get("has_reference", False)):
            raise BaselineFileError(f"{path}: its reference traces do not match its header (modified or "
                                    "corrupted); record the baselines again")
        if meta.get("kpi_names") != list(KPI_NAMES):
            raise BaselineFileError(f"{path}: KPI columns {meta.get('kpi_names')!r} are not {list(KPI_NAMES)}")
        if meta.get("format_version") >= 5 and fm is not None and meta.get("fm_method") != FM_METHOD:
            raise BaselineFileError(f"{path}: its f_m readings name no estimator this inkdiag takes "
                                    f"(fm_method {meta.get('fm_method')!r}); record the baselines again")
        if meta.get("format_version") >= 3 and not isinstance(meta.get("head_sha256"), str):
            raise BaselineFileError(f"{path}: its header names no head profile (head_sha256); record the "
                                    "baselines again")
        stored = meta.pop("sha256", None)
        ids, kpis = arrays["nozzle_ids"], arrays["kpis"]
        try:
            actual = _content_sha256(ids, kpis, meta, fm, reference)
        except (TypeError, ValueError) as exc:
            raise BaselineFileError(f"{path}: unreadable arrays ({exc})") from None
        if stored != actual:
            raise BaselineFileError(f"{path}: its content does not match its sha256 (modified or "
                                    "corrupted); record the baselines again")
        try:
            return cls(ids, kpis, meta["sample_rate_hz"], meta["n_samples"], meta["n_frames"], fm,
                       head_sha256=meta.get("head_sha256"),  # None (versions 1, 2): the default head
                       reference=reference,  # None (versions 1-3): no references
                       fm_method=meta.get("fm_method"))  # absent (versions 1-4): default-head vp_cal readings
        except (KeyError, ValueError) as exc:
            raise BaselineFileError(f"{path}: inconsistent baselines ({exc})") from None
