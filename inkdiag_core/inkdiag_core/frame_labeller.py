"""Label frames of traces with one :class:`inkdiag_core.FaultDetector`: :class:`FrameLabeller`.

A :class:`FrameLabeller` is what the fdi node labels with: the detector, the
head's recorded per-nozzle baselines (optional) and the node's input checks
(sample rate, samples per trace, largest plausible sample). It holds the rules
that say whether a detector and a baselines file go together, so a node only
reports :class:`LabellerConfigError`, and it validates each frame once:

1. each frame's shape (per frame: a bad one is a :class:`FrameFailure`, the others go on);
2. a screening of every row (:func:`inkdiag_core.screen_traces`'s verdicts, ``max_abs_v``);
3. when the baselines carry reference traces, the healthy gate
   (:class:`inkdiag_core.HealthyGate`): valid rows that match their nozzle's healthy
   reference are labelled ``healthy_nozzle`` or ``ok_signal`` at once (confidence 1.0,
   ``baseline`` True, ``gate_cleared`` True). Float frames are screened, gated and the rows
   left for the detector gathered by one kernel call per frame
   (:func:`inkdiag_core._kernels.screen_gate_frames`: each row read from memory once, only the
   few rows left copied), not stacked into one array first; each row's outcome is a small
   code until the batch's columns are built from the codes in a few numpy calls;
4. one :meth:`inkdiag_core.FaultDetector.label` call for the other valid rows of the batch,
   each row routed to the baseline branch when its nozzle has a baseline;
5. if that call raises, each frame alone, so one bad frame costs only itself.

:meth:`FrameLabeller.label` does it all at once; :meth:`FrameLabeller.screen` (1-3) and
:meth:`FrameLabeller.finish` (4-5) apart let a node screen each burst of frames as it
arrives and run the detector once for several bursts (its fixed cost per call is most of
what a working head's few leftover rows cost). For frames of one dtype (a node's are all
float32) the grouping changes no label.

No ROS in here.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from itertools import accumulate

import numpy as np

from .baselines import BaselineFileError, NozzleBaselines
from .detector import FaultDetector
from .gate import CLEARED_HEALTHY, CLEARED_OK, GATE_CLASSES, HealthyGate
from .persistence import load_detector
from .labelling import FrameLabels
from .openset import UNKNOWN
from .screening import INVALID_REASONS, screening_codes, screening_settings

__all__ = ["FrameFailure", "FrameInputError", "FrameLabeller", "LabellerConfigError", "ScreenedFrames", "load_labeller"]


#: A screened row's class, reason and validity by its code (:func:`inkdiag_core._kernels.screen_gate_frames`':
#: 0 left for the detector, 1-4 screening's reasons, the gate's two cleared classes), and the code of a row
#: whose features came out non-finite.
_NON_FINITE_FEATURES = CLEARED_OK + 1
_CLASS_OF_CODE = np.array(["", "", "", "", "", *GATE_CLASSES[1:], ""], dtype=object)
_REASON_OF_CODE = np.array(["", *INVALID_REASONS[:4], "", "", INVALID_REASONS[4]], dtype=object)
_VALID_CODE = np.array([True, False, False, False, False, True, True, False])


@functools.cache
def _screen_gate_frames():
    """:func:`inkdiag_core._kernels.screen_gate_frames`, imported when first needed (numba: ~0.35 s), once
    (an import statement in the hot path costs a few us per call)."""
    from ._kernels import screen_gate_frames

    return screen_gate_frames


class LabellerConfigError(ValueError):
    """A detector, a baselines file and the node's settings that do not go together."""


class FrameInputError(ValueError):
    """A frame that cannot be labelled as given (wrong shape or sample count)."""


@dataclass(frozen=True)
class FrameFailure:
    """One frame of a batch that was not labelled.

    frame_index : int -- its position in the batch
    error : BaseException -- why (:class:`FrameInputError` for a bad frame; any other
        exception is an error of the labelling itself)
    """

    frame_index: int
    error: BaseException

    @property
    def why(self) -> str:
        """``"<ExceptionType>: <message>"``."""
        return f"{type(self.error).__name__}: {self.error}"


class FrameLabeller:
    """Screen and classify frames of traces with a :class:`FaultDetector`, each frame isolated.

    Parameters
    ----------
    detector : FaultDetector
        Fitted (:func:`inkdiag_core.load_detector`).
    baselines : NozzleBaselines, optional
        The head's recorded healthy baselines. Used only when the detector has a
        baseline branch (else :class:`LabellerConfigError` if any nozzle has one).
        With reference traces (:attr:`NozzleBaselines.reference`) the healthy gate
        (:class:`inkdiag_core.HealthyGate`, default thresholds) clears the rows that
        match their nozzle's reference before the detector; a cleared row's label
        is the gate's healthy class with confidence 1.0 (the gate does not estimate
        a probability: it clears only rows within its calibrated bounds,
        ``reports/gate.md``).
    sample_rate_hz : float, optional
        Sample rate of the frames, Hz; must be the detector's (and the baselines').
    n_samples : int, optional
        Samples per trace; must be the detector's ``n_features_in_`` (and the
        baselines'). None: the detector's.
    max_abs_v : float, optional
        Largest sample magnitude a sensor can produce, V: rows beyond it are
        invalid, ``"out_of_range"``. None: no such check.
    profile : HeadProfile, optional
        The head the frames come from: the detector must have been built for it
        (the same :attr:`inkdiag_core.HeadProfile.sha256`; a detector without a
        profile is the default head's), and ``sample_rate_hz`` / ``n_samples``
        default to its sampling. None: no head check.

    Raises
    ------
    LabellerConfigError
        A ``max_abs_v`` that is not positive; not a fitted FaultDetector; a detector built for another head than
        ``profile``; its sample rate or trace length differ from
        ``sample_rate_hz`` / ``n_samples``; the baselines' differ; or baselines with
        nozzles were given to a detector without a baseline branch.
    """

    def __init__(self, detector, baselines: NozzleBaselines | None = None, *, sample_rate_hz: float | None = None,
                 n_samples: int | None = None, max_abs_v: float | None = None, profile=None):
        if not isinstance(detector, FaultDetector) or not hasattr(detector, "pipeline_"):
            raise LabellerConfigError(f"a fitted FaultDetector is needed, got {type(detector).__name__}; "
                                      "retrain the model: python -m inkdiag_core.model_cache")
        outdated = detector.openset_outdated()
        if outdated:
            raise LabellerConfigError(outdated)
        if profile is not None:
            if detector.head_sha256 != profile.sha256:
                raise LabellerConfigError(
                    f"the model is for head {detector.head_name!r} (profile sha256 {detector.head_sha256[:12]}), "
                    f"this is head {profile.name!r} (profile sha256 {profile.sha256[:12]}): a model of another head; "
                    "train one on this head's profile (inkdiag train --profile)")
            sample_rate_hz = profile.sample_rate_hz if sample_rate_hz is None else sample_rate_hz
            n_samples = profile.n_samples if n_samples is None else n_samples
        want_fs = float(detector.sample_rate_hz_)
        want_n = int(detector.n_features_in_)
        if sample_rate_hz is not None and float(sample_rate_hz) != want_fs:
            raise LabellerConfigError(f"the model is for {want_fs:.10g} Hz, the frames are "
                                      f"{float(sample_rate_hz):.10g} Hz")
        if n_samples is not None and int(n_samples) != want_n:
            raise LabellerConfigError(f"the model is for {want_n} samples per trace, the frames have {int(n_samples)}")
        if baselines is not None:
            if baselines.head_sha256 != detector.head_sha256:
                raise LabellerConfigError(
                    f"the baselines were recorded on another head (profile sha256 {baselines.head_sha256[:12]}) than "
                    f"the model's {detector.head_name!r} ({detector.head_sha256[:12]}): record them on this head")
            got = (float(baselines.sample_rate_hz), int(baselines.n_samples))
            if got != (want_fs, want_n):
                raise LabellerConfigError(f"the baselines are for {got[0]:.10g} Hz x {got[1]} samples, the model "
                                          f"for {want_fs:.10g} Hz x {want_n}")
            if len(baselines) and detector.baseline_pipeline_ is None:
                raise LabellerConfigError(f"{detector.model_id} has no baseline branch: per-nozzle baselines "
                                          "need a detector trained with baselines (`inkdiag train --baseline`, "
                                          "train_detector(baseline=True))")
        self.detector = detector
        # every class a row can get, once ("" an invalid row's), and each screened row's class code by its code
        self._class_names = tuple(dict.fromkeys(["", *GATE_CLASSES[1:].tolist(), *map(str, detector.classes_.tolist()),
                                                 UNKNOWN]))
        self._class_of = np.array(self._class_names, dtype=object)  # a row's class by its class code
        self._sorted_names = np.array(sorted(self._class_names))  # the detector's classes to codes, in one search
        self._sorted_codes = np.array([self._class_names.index(c) for c in self._sorted_names.tolist()], np.uint8)
        self._class_of_code = self._sorted_codes[np.searchsorted(self._sorted_names, _CLASS_OF_CODE.astype(str))]
        self.baselines = baselines if baselines is not None and len(baselines) else None
        gate = HealthyGate(self.baselines) if self.baselines is not None and self.baselines.has_reference else None
        self.gate = gate if gate is not None and gate.active else None
        self.n_samples = want_n
        self.sample_rate_hz = want_fs
        self.profile = profile
        self.max_abs_v = None if max_abs_v is None else float(max_abs_v)
        try:  # (flat_tol, max_abs_v, clip_run): what every frame is screened with, float or not
            self._screening = screening_settings(max_abs_v=self.max_abs_v, sample_rate_hz=want_fs)
        except ValueError as exc:
            raise LabellerConfigError(str(exc)) from None
        _warm_up_kernels()

    def __setstate__(self, state):  # unpickled in the labelling process's child: its kernels too
        self.__dict__.update(state)
        _warm_up_kernels()

    @property
    def model_id(self) -> str:
        """The detector's :attr:`FaultDetector.model_id` (``+baseline`` when it has that branch)."""
        return self.detector.model_id

    @property
    def uses_baselines(self) -> bool:
        """Rows of nozzles with a recorded baseline are classified against it."""
        return self.baselines is not None

    @property
    def uses_gate(self) -> bool:
        """Rows of nozzles with a recorded reference trace go through the healthy gate first."""
        return self.gate is not None

    def label(self, frames, first_nozzles, *, nozzles=None) -> list:
        """Label a batch of frames: each frame screened and gated by one kernel call, one detector call
        for the rows left, each frame isolated (:meth:`finish` of one :meth:`screen`).

        Parameters
        ----------
        frames : sequence of array_like, each of shape (n_i, n_samples)
            Traces, V.
        first_nozzles : sequence of int
            Each frame's first nozzle id (row ``j`` of frame ``i`` is nozzle
            ``first_nozzles[i] + j``).
        nozzles : sequence of array_like of int, each of shape (n_i,), optional
            Each frame's nozzle id per row, instead of consecutive ids from
            ``first_nozzles`` (a recording's rows; they select the baselines).

        Returns
        -------
        list
            Per frame, in order: its :class:`FrameLabels` (n_i rows; invalid rows
            with their reason: screening's, or ``"non_finite_features"``), or a
            :class:`FrameFailure` (a :class:`FrameInputError` for a frame of the
            wrong shape; the exception labelling it alone raised otherwise).
        """
        return self.finish([self.screen(frames, first_nozzles, nozzles=nozzles)])[0]

    def screen(self, frames, first_nozzles, *, nozzles=None) -> "ScreenedFrames":
        """The first stage of :meth:`label`: screening and the healthy gate, the rows left for the
        detector gathered. :meth:`finish` labels them, for several screened batches in one
        detector call: a node screens each burst of messages as it takes it and runs the
        detector once its input is idle. ``label(...)`` is ``finish([screen(...)])[0]``; how
        frames of one dtype are grouped into screened batches and finished changes no label (the
        detector labels each row on its own; rows of several dtypes taken together are computed in
        their common dtype, as by one :meth:`label` call).

        Parameters and their checks are :meth:`label`'s.

        Returns
        -------
        ScreenedFrames
            Opaque; for :meth:`finish` (``len()`` is its number of frames, ``rows_left`` the
            rows the detector will take).
        """
        if len(frames) != len(first_nozzles):
            raise ValueError(f"{len(frames)} frames but {len(first_nozzles)} first nozzle ids")
        if nozzles is not None and len(nozzles) != len(frames):
            raise ValueError(f"{len(frames)} frames but {len(nozzles)} nozzle id arrays")
        out: list = [None] * len(frames)
        good, arrays = [], []
        head = f" (head {self.profile.name!r})" if self.profile is not None else ""
        for i, f in enumerate(frames):
            a = np.asarray(f)
            if a.ndim != 2 or a.shape[1] != self.n_samples:
                out[i] = FrameFailure(i, FrameInputError(
                    f"frame {i} has shape {a.shape}, the model{head} takes (n, {self.n_samples})"))
            elif nozzles is not None and np.shape(nozzles[i]) != (a.shape[0],):
                out[i] = FrameFailure(i, FrameInputError(
                    f"frame {i} has {a.shape[0]} rows but {np.shape(nozzles[i])} nozzle ids"))
            else:
                good.append(i)
                arrays.append(a)
        screened = ScreenedFrames(out)
        if not good:
            return screened
        if nozzles is None:
            firsts = [int(first_nozzles[i]) for i in good]
        else:  # each row's own id
            firsts = [np.array(nozzles[i], dtype=np.int64) for i in good]  # a writable C copy: one kernel signature
        try:
            screened.parts.append(_Part(good, arrays, firsts, self._screen_rows(arrays, firsts)))
        except Exception:  # noqa: BLE001 - find the frame(s) at fault: each alone
            for i, a, first in zip(good, arrays, firsts):
                try:
                    screened.parts.append(_Part([i], [a], [first], self._screen_rows([a], [first])))
                except Exception as exc:  # noqa: BLE001 - this frame's failure, reported by the caller
                    out[i] = FrameFailure(i, exc)
        return screened

    def finish(self, screened) -> list:
        """The second stage of :meth:`label`: one detector call for the rows every batch of
        ``screened`` left, each frame's labels.

        Parameters
        ----------
        screened : sequence of ScreenedFrames
            From :meth:`screen` of this labeller, each finished once.

        Returns
        -------
        list of list
            Per screened batch, per frame: as :meth:`label` returns them. If the one call
            raises, each batch alone, then each of its frames alone: one bad frame costs only itself.
        """
        owners = [s for s in screened for _ in s.parts]
        parts = [p for s in screened for p in s.parts]
        try:
            done = self._finish_rows([p.pending for p in parts])
        except Exception:  # noqa: BLE001 - find the frame(s) at fault: each batch, then each frame alone
            done = [self._finish_part(p, whole=len(parts) > 1 and len(p.frames) > 1) for p in parts]
        for s, p, rows in zip(owners, parts, done):
            for i, r in zip(p.frames, rows):
                s.out[i] = FrameFailure(i, r) if isinstance(r, BaseException) else r
        return [s.out for s in screened]

    def _finish_part(self, p, whole: bool) -> list:
        """One screened part's frame results: the part in one detector call (``whole``), and if that raises
        (or not ``whole``), each frame alone; a frame that still fails gives its exception."""
        if whole:
            try:
                return self._finish_rows([p.pending])[0]
            except Exception:  # noqa: BLE001 - each frame alone, below
                pass
        rows = []
        for a, first in zip(p.arrays, p.firsts):
            try:
                rows.append(self._finish_rows([self._screen_rows([a], [first])])[0][0])
            except Exception as exc:  # noqa: BLE001 - this frame's failure, reported by the caller
                rows.append(exc)
        return rows

    def _screen_rows(self, arrays, firsts) -> "_Pending":
        """Screen frames of the right width together, the gate's rows labelled, the others gathered.

        Frames of one float dtype (a node's): one compiled call per frame screens, gates and gathers
        (:func:`inkdiag_core._kernels.screen_gate_frames`); others (ADC counts, mixed dtypes) are
        stacked in their common dtype first, and screened in numpy passes where that is not a float."""
        sizes = [a.shape[0] for a in arrays]
        ends = list(accumulate(sizes))
        starts = [e - k for e, k in zip(ends, sizes)]
        n = ends[-1]
        consecutive = all(type(f) is int for f in firsts)  # else each row's own id (screen() gives ints or arrays)
        if len({a.dtype for a in arrays}) > 1 or arrays[0].dtype not in (np.float32, np.float64):
            x = np.concatenate(arrays) if len(arrays) > 1 else arrays[0]
            ids = (np.repeat(np.asarray(firsts, dtype=np.int64) - starts, sizes) + np.arange(n) if consecutive
                   else np.concatenate(firsts))
            if x.dtype not in (np.float32, np.float64):  # ADC counts or other dtypes: screen_traces' numpy passes
                return self._screen_numpy(x, ids, starts, ends)
            arrays, firsts, consecutive = [x], [ids], False
        gate = self.gate
        positions = None
        if gate is not None:
            positions = [gate.range_positions(f, a.shape[0]) if consecutive else gate.positions(f)
                         for f, a in zip(firsts, arrays)]
        if consecutive and self.baselines is None:  # the ids are not needed (any int a caller gave goes)
            firsts = [0] * len(arrays)
        code, at, nozzle, rows = _screen_gate_frames()(
            arrays, *self._screening, positions, None if gate is None else gate.verdict_params,
            firsts if consecutive else None, None if consecutive else firsts)
        return self._pending(starts, ends, code, at, nozzle, rows)

    def _screen_numpy(self, x, ids, starts, ends) -> "_Pending":
        """:meth:`_screen_rows` of stacked rows that are not floats: screening's and the gate's numpy passes."""
        flat_tol, max_abs, clip_run = self._screening
        code = screening_codes(x, flat_tol=flat_tol, clip_run=clip_run, max_abs_v=None if max_abs == np.inf else max_abs)
        at = np.flatnonzero(code == 0)
        if at.size and self.gate is not None:
            g = self.gate.screen(x if at.size == x.shape[0] else x[at], ids[at])
            code[at[g.cleared]] = np.where(g.classes[g.cleared] == GATE_CLASSES[1], CLEARED_HEALTHY, CLEARED_OK)
            at = at[~g.cleared]
        return self._pending(starts, ends, code, at, ids[at], [x if at.size == x.shape[0] else x[at]])

    def _pending(self, starts, ends, code, at, nozzle, rows) -> "_Pending":
        """The screened rows' codes (:func:`inkdiag_core._kernels.screen_gate_frames`') and the rows left; their
        columns and baselines are built by :meth:`_finish_rows`, for every batch of a detector pass at once."""
        return _Pending(starts, ends, code, at, nozzle, rows if at.size else None)

    def _finish_rows(self, pending) -> list:
        """One detector call for the rows left in every ``pending`` batch; per batch, its frames' FrameLabels.

        The batches' columns come from their rows' codes, concatenated: a few numpy calls per detector
        pass, not per batch (a node screens each message as it arrives, and finishes several)."""
        if not pending:
            return []
        offsets = list(accumulate([0] + [p.code.size for p in pending]))
        code = pending[0].code if len(pending) == 1 else np.concatenate([p.code for p in pending])
        cleared = code >= CLEARED_HEALTHY
        reasons, class_codes = _REASON_OF_CODE[code], self._class_of_code[code]
        confidence, with_base = np.where(cleared, 1.0, np.nan), cleared.copy()
        left = [(p, o) for p, o in zip(pending, offsets) if p.at.size]
        if left:
            at = left[0][0].at if len(left) == 1 and left[0][1] == 0 else np.concatenate([p.at + o for p, o in left])
            parts = [r for p, _ in left for r in p.rows]
            rows = parts[0] if len(parts) == 1 else np.concatenate(parts)
            kpis = None
            if self.baselines is not None:
                has, kpis = self.baselines.lookup(left[0][0].nozzle if len(left) == 1 else
                                                  np.concatenate([p.nozzle for p, _ in left]))
                kpis[~has] = np.nan  # routed to the plain branch
            got = self.detector.label(rows, baseline_kpis=kpis)
            ok = got.valid
            if ok.all():  # nearly always: no row's features came out non-finite
                class_codes[at], confidence[at] = self._codes_of(got.classes), got.confidence
            else:
                class_codes[at[ok]] = self._codes_of(got.classes[ok])
                confidence[at[ok]] = got.confidence[ok]
                reasons[at[~ok]] = "non_finite_features"
                code[at[~ok]] = _NON_FINITE_FEATURES
            with_base[at] = got.baseline
        valid = _VALID_CODE[code]
        with_base &= valid
        classes = self._class_of[class_codes]  # the codes name every row's class ("" an invalid row's)
        cols = (classes, confidence, valid, reasons, with_base, cleared if self.gate is not None else None, class_codes)
        names = self._class_names
        return [[FrameLabels(*(None if col is None else col[o + i:o + j] for col in cols), names)  # views
                 for i, j in zip(p.starts, p.ends)] for p, o in zip(pending, offsets)]

    def _codes_of(self, classes) -> np.ndarray:
        """The class codes of the detector's classes (strings), by one search in the sorted names."""
        got = np.asarray(classes).astype(str)
        at = np.minimum(np.searchsorted(self._sorted_names, got), len(self._sorted_names) - 1)
        if not np.array_equal(self._sorted_names[at], got):  # a class the labeller's names lack: never silently
            raise ValueError(f"the detector gave a class outside {self._class_names}: {sorted(set(got.tolist()))}")
        return self._sorted_codes[at]


class ScreenedFrames:
    """A batch of frames after :meth:`FrameLabeller.screen`, waiting for :meth:`FrameLabeller.finish`."""

    def __init__(self, out: list):
        self.out = out  # per frame: its result once known (a FrameFailure from screening at once)
        self.parts: list = []  # _Part: frames screened together

    def __len__(self) -> int:
        return len(self.out)

    @property
    def rows_left(self) -> int:
        """Rows the detector will take."""
        return sum(int(p.pending.at.size) for p in self.parts)


@dataclass
class _Part:
    frames: list  # their indices in the batch
    arrays: list
    firsts: list
    pending: "_Pending"


@dataclass
class _Pending:
    """Frames screened together (``starts``, ``ends``: each frame's rows); ``code`` each row's
    (:func:`inkdiag_core._kernels.screen_gate_frames`'); ``at``: the batch rows left for the detector, ``nozzle``
    their nozzle ids, ``rows`` them (a list of arrays, in order; None when none is left)."""

    starts: list
    ends: list
    code: np.ndarray
    at: np.ndarray
    nozzle: np.ndarray
    rows: list | None


def _warm_up_kernels() -> None:
    """The screening and gate kernels compiled (or loaded from their cache) now, not on a first frame."""
    from ._kernels import warm_up

    warm_up()


def load_labeller(model_path, baseline_path=None, *, n_nozzles: int = 0, **checks):
    """A :class:`FrameLabeller` of a model file, with the head's baselines if they load and fit.

    What a node does at start: the model must load (:func:`inkdiag_core.load_detector`,
    verified before unpickling) and fit the node's ``checks``; baselines that do not
    load or do not fit the model are left out and the labeller labels without them.

    Parameters
    ----------
    model_path : str or Path
        A FaultDetector file.
    baseline_path : str or Path, optional
        The head's recorded baselines (:meth:`NozzleBaselines.load`); empty or None: none.
    n_nozzles : int
        The head's nozzles (ids ``0 .. n_nozzles - 1``): baselines none of whose nozzles is one of them
        are left out (another head's, or another numbering). 0: no check.
    **checks
        ``sample_rate_hz``, ``n_samples``, ``max_abs_v``, ``profile`` as for :class:`FrameLabeller`.

    Returns
    -------
    labeller : FrameLabeller
    baseline_error : BaselineFileError, LabellerConfigError, OSError or None
        Why the baselines were left out (None: used, or none given).

    Raises
    ------
    ModelFileError
        The model file is missing, tampered with, from other library versions, or not a
        FaultDetector (an older plain-pipeline file: retrain it).
    LabellerConfigError
        The model does not fit ``checks`` (e.g. it was built for another head than ``profile``).
    """
    labeller = FrameLabeller(load_detector(model_path), **checks)
    if not baseline_path:
        return labeller, None
    try:
        baselines = NozzleBaselines.load(baseline_path)
        ids = baselines.nozzle_ids
        if n_nozzles > 0 and ids.size and not np.any(ids < n_nozzles):
            raise LabellerConfigError(
                f"{baseline_path} holds the baselines of {ids.size} nozzles, ids {int(ids.min())}..{int(ids.max())}: "
                f"none of this head's nozzles 0..{n_nozzles - 1} (n_nozzles {n_nozzles}); record them on this head")
        return FrameLabeller(labeller.detector, baselines, **checks), None
    except (BaselineFileError, LabellerConfigError, OSError) as exc:
        return labeller, exc
