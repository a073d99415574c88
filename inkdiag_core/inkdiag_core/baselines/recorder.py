"""Record a head's per-nozzle healthy baselines from its frames as they arrive (:class:`BaselineRecorder`)."""

from __future__ import annotations

import warnings

import numpy as np

from .. import checks
from ..estimation import estimate_fm_batch
from ..kpis import MIN_KPI_SAMPLES, InvalidTraceError, extract_kpis
from ..screening import rings_above_noise, screen_traces
from .features import N_KPIS, median_kpis
from .store import FM_METHOD, NozzleBaselines

__all__ = ["DEFAULT_MAX_NOZZLES", "FM_METHOD", "BaselineRecorder"]

#: Default bound on the nozzle ids a :class:`BaselineRecorder` accepts (ids are below it).
#: It bounds memory: the recorder counts rows per nozzle id in a dense int32 array,
#: grown on demand by doubling, so ids up to this bound cost at most 4 bytes times
#: twice the bound (128 MiB here) whatever ids a frame claims.
DEFAULT_MAX_NOZZLES = 1 << 24

#: A nozzle whose baseline's dominant frequency or damping ratio lies more than this many robust standard
#: deviations (1.4826 x the median absolute deviation over the head's nozzles; at least 0.5 % of the median
#: frequency, 2 % of the median damping) from the head's median rings unlike the head's other nozzles: no
#: baseline (faulty at commissioning). Healthy nozzles of the five heads of ``tests/foreign_head.py`` (300
#: each, 8 frames) lie within 3.1 of them; dried, blocked, empty and nozzle-bubble traces beyond 6 (a small
#: chamber bubble's, 5-100 %).
UNLIKE_HEAD_SDS = 6.0
#: Nozzles with a baseline needed before :data:`UNLIKE_HEAD_SDS` is applied (a head's spread to go by).
UNLIKE_HEAD_MIN_NOZZLES = 8


class BaselineRecorder:
    """Record each nozzle's healthy baseline from the frames of a head, as they arrive.

    Each :meth:`add` takes one message's rows (a contiguous nozzle range, any size,
    any order, repeated ranges welcome); rows that :func:`inkdiag_core.screen_traces`
    finds invalid, that do not ring above their own noise (:attr:`rows_not_ringing`) or that
    ``keep`` excludes are not used. A nozzle's baseline is the
    median of its first ``n_frames`` valid rows' KPIs (:func:`baseline_kpis` on
    the same traces gives the same numbers for the nozzles it keeps); rows beyond that are ignored, so memory
    stays at ``n_frames`` KPI rows per nozzle. Record while the head is healthy
    (after a purge, at commissioning).

    Parameters
    ----------
    n_frames : int
        Frames per nozzle in its baseline, >= 1.
    sample_rate_hz : float, optional
        Sample rate of the traces, Hz (default: the profile's). Given, it must be the profile's.
    n_samples : int, optional
        Samples per trace; every frame must have it (default: the profile's; given,
        it must be the profile's).
    fm_frames : int
        Also record each nozzle's healthy f_m reading (:attr:`NozzleBaselines.fm`),
        the median of ``estimate_fm_batch(rows, profile, sample_rate_hz, method="vp").fm`` (the
        raw estimate on the head's model, :data:`FM_METHOD`: the nozzle's own offset, which
        :class:`inkdiag_core.DryingTracker` takes off its ``"vp"`` and ``"vp_cal"`` estimates)
        over its first ``fm_frames`` rows (at most ``n_frames``); 0: none. It costs
        about a millisecond per row, so it is taken on fewer rows than the KPIs.
    max_nozzles : int
        Nozzle ids must be below this, >= 1 (:data:`DEFAULT_MAX_NOZZLES`): a bound on
        the recorder's memory (a dense int32 row count per nozzle id, 4 bytes each,
        grown by doubling), so a frame claiming huge ids is refused rather than
        allocating for them.
    profile : HeadProfile, optional
        The head (default: the shipped default head, 10 MHz x 512, whose model is
        ``InkChannelModel()``): its sampling, its healthy model for the f_m readings,
        and its sha256, which the baselines carry (:attr:`NozzleBaselines.head_sha256`).
        A complete profile.
    reference : bool
        Also record each nozzle's healthy reference trace (:attr:`NozzleBaselines.reference`,
        for :class:`inkdiag_core.HealthyGate`): the sample-wise median of the same rows
        as its KPI baseline. It keeps those rows (float32, ``n_frames`` rows of
        ``n_samples`` per nozzle) until :meth:`baselines`. Like the KPI baselines it
        assumes the recorded rows are healthy jetting-pulse traces (``healthy_nozzle``).
    max_abs_v : float, optional
        A row with a sample beyond +-``max_abs_v`` V is not used (out of the sensor's range:
        :func:`inkdiag_core.screen_traces`); default: the profile's
        :attr:`~inkdiag_core.HeadProfile.max_abs_v` (5x its ADC range), as fdi.

    Raises
    ------
    ValueError
        Bad settings; :class:`inkdiag_core.ProfileError` (a ``ValueError``) for a
        nominal profile or a sampling that is not the profile's.
    """

    def __init__(self, *, n_frames: int = 8, sample_rate_hz: float | None = None, n_samples: int | None = None,
                 fm_frames: int = 0, max_nozzles: int = DEFAULT_MAX_NOZZLES, profile=None, reference: bool = True,
                 max_abs_v: float | None = None):
        from ..head_profile import HeadProfile, ProfileError

        if profile is None:
            profile = HeadProfile.default()
        elif not isinstance(profile, HeadProfile):
            raise TypeError(f"profile must be a HeadProfile (or None: the default head), got {type(profile).__name__}")
        if not profile.is_complete:
            raise ProfileError(f"profile {profile.name!r} is nominal ({', '.join(profile.missing)} missing): "
                               "baselines need a complete profile (run `inkdiag calibrate` on recorded healthy traces)")
        if sample_rate_hz is None:
            sample_rate_hz = profile.sample_rate_hz
        elif sample_rate_hz != profile.sample_rate_hz:
            raise ProfileError(f"sample_rate_hz {sample_rate_hz!r} Hz is not head profile {profile.name!r}'s "
                               f"{profile.sample_rate_hz:g} Hz")
        if n_samples is None:
            n_samples = profile.n_samples
        elif n_samples != profile.n_samples:
            raise ProfileError(f"n_samples {n_samples!r} is not head profile {profile.name!r}'s {profile.n_samples}")
        if isinstance(n_frames, bool) or not isinstance(n_frames, (int, np.integer)) or n_frames < 1:
            raise ValueError(f"n_frames must be a positive integer, got {n_frames!r}")
        if isinstance(fm_frames, bool) or not isinstance(fm_frames, (int, np.integer)) \
                or not 0 <= fm_frames <= n_frames:
            raise ValueError(f"fm_frames must be an integer in 0..n_frames ({n_frames}), got {fm_frames!r}")
        self.fm_frames = int(fm_frames)
        if isinstance(n_samples, bool) or not isinstance(n_samples, (int, np.integer)) or n_samples < MIN_KPI_SAMPLES:
            raise ValueError(f"n_samples must be an integer >= {MIN_KPI_SAMPLES}, got {n_samples!r}")
        if isinstance(max_nozzles, bool) or not isinstance(max_nozzles, (int, np.integer)) or max_nozzles < 1:
            raise ValueError(f"max_nozzles must be a positive integer, got {max_nozzles!r}")
        self.max_nozzles = int(max_nozzles)
        if max_abs_v is not None and not (isinstance(max_abs_v, (int, float, np.floating, np.integer))
                                          and not isinstance(max_abs_v, bool) and 0 < max_abs_v < np.inf):
            raise ValueError(f"max_abs_v must be a finite number > 0 V or None (the profile's), got {max_abs_v!r}")
        self.max_abs_v = profile.max_abs_v if max_abs_v is None else float(max_abs_v)
        self.n_frames = int(n_frames)
        self.sample_rate_hz = checks.sample_rate(sample_rate_hz, error=InvalidTraceError)
        self.n_samples = int(n_samples)
        self.profile = profile
        self._ids = []  # chunks of the rows kept so far, in arrival order
        self._kpis = []
        self.reference = bool(reference)
        self._traces = []  # the kept rows (float32), when recording references
        self._count_of = np.zeros(0, np.int32)  # rows kept per nozzle id (dense, grown on demand)
        #: what the last :meth:`baselines` left out as ringing unlike the head's other nozzles: their ids, dominant
        #: frequencies (Hz) and damping ratios, and the head's median frequency and damping; ``unlike_note()``
        self.unlike_head = (np.empty(0, np.int64), np.empty(0), np.empty(0), np.nan, np.nan)
        #: rows screening passed but that do not ring above their own noise
        #: (:func:`~inkdiag_core.screening.rings_above_noise`), not used
        self.rows_not_ringing = 0
        self._mode_hz = float(profile.healthy_mode()[0])  # whether the ringing check can tell at this sampling

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
        n = x.shape[0] if x.ndim == 2 else 0
        self._check_below_max(int(first_nozzle), int(first_nozzle) + max(n, 1) - 1)  # Python ints: no int64 overflow
        return self._add(int(first_nozzle) + np.arange(n, dtype=np.int64), x, keep, distinct=True)

    def add_rows(self, nozzle_ids, traces, keep=None) -> int:
        """Use rows of any nozzles, a nozzle any number of times (a recording's rows, in its order).

        Parameters
        ----------
        nozzle_ids : array_like of int, shape (n,)
            Each row's nozzle id, >= 0; repeated ids are that nozzle's later frames.
        traces : array_like, shape (n, n_samples)
            V.
        keep : array_like of bool, shape (n,), optional
            Rows to use.

        Returns
        -------
        int
            Rows used: for each nozzle its first valid rows, up to its ``n_frames`` in all.
        """
        ids = np.asarray(nozzle_ids)
        if ids.ndim != 1 or not (np.issubdtype(ids.dtype, np.integer) or ids.size == 0):
            raise ValueError(f"nozzle_ids must be a 1-d integer array, got shape {ids.shape}, dtype {ids.dtype}")
        if ids.size and ids.min() < 0:
            raise ValueError(f"nozzle ids must be >= 0, got {int(ids.min())}")
        if ids.size:
            self._check_below_max(int(ids.min()), int(ids.max()))  # before the cast to int64 (uint64 ids wrap)
        x = np.asarray(traces)
        if x.ndim == 2 and x.shape[0] != ids.size:
            raise ValueError(f"nozzle_ids has {ids.size} ids for {x.shape[0]} rows of traces")
        return self._add(ids.astype(np.int64), x, keep, distinct=False)

    def _check_below_max(self, lo: int, hi: int) -> None:
        if hi >= self.max_nozzles:
            raise ValueError(f"nozzle ids must stay below {self.max_nozzles} (the recorder's max_nozzles, "
                             f"a bound on its memory), got {lo}..{hi}")

    def _add(self, all_ids, x, keep, *, distinct: bool) -> int:
        if x.ndim != 2 or x.shape[1] != self.n_samples:
            raise ValueError(f"traces must have shape (n, {self.n_samples}), got {x.shape}")
        use, _ = screen_traces(x, sample_rate_hz=self.sample_rate_hz, max_abs_v=self.max_abs_v)
        if keep is not None:
            k = np.asarray(keep, dtype=bool)
            if k.shape != (x.shape[0],):
                raise ValueError(f"keep must have shape ({x.shape[0]},), got {k.shape}")
            use &= k
        rows, ids, place, need = self._places(all_ids, use, distinct)
        if need.any():  # a row that does not ring above its noise is no healthy trace (a nozzle that did not fire)
            quiet = rows[need][~rings_above_noise(x[rows[need]], sample_rate_hz=self.sample_rate_hz,
                                                  mode_hz=self._mode_hz)]
            if quiet.size:  # the places again without them
                use[quiet] = False
                self.rows_not_ringing += int(quiet.size)
                rows, ids, place, need = self._places(all_ids, use, distinct)
        if not need.any():
            return 0
        rows, ids, place = rows[need], ids[need], place[need]
        y = checks.traces_2d(x[rows], min_samples=MIN_KPI_SAMPLES, error=InvalidTraceError)
        kpis = np.full((ids.size, N_KPIS + 1), np.nan)  # the last column: f_m, NaN where not taken
        kpis[:, :N_KPIS] = extract_kpis(y, self.sample_rate_hz)
        if self.fm_frames:
            fm_rows = np.flatnonzero(place < self.fm_frames)
            if fm_rows.size:
                # the raw "vp" reading on the head's model: the nozzle's own offset, which
                # DryingTracker takes off its estimates (vp_cal's correction is not the nozzle's)
                kpis[fm_rows, N_KPIS] = estimate_fm_batch(y[fm_rows], self.profile, self.sample_rate_hz,
                                                          method=FM_METHOD).fm
        self._kpis.append(kpis)
        if self.reference:
            self._traces.append(y.astype(np.float32))
        self._ids.append(ids)
        np.add.at(self._count_of, ids, 1)
        return int(ids.size)

    def _places(self, all_ids, use, distinct: bool):
        """The rows ``use`` takes, their nozzle ids, each row's place among its nozzle's rows so far, and whether
        its nozzle still needs it (place < ``n_frames``)."""
        rows = np.flatnonzero(use)
        ids = all_ids[rows]
        if ids.size and ids.max() >= self._count_of.size:
            grown = np.zeros(max(int(ids.max()) + 1, 2 * self._count_of.size), np.int32)
            grown[: self._count_of.size] = self._count_of
            self._count_of = grown
        # each row's place among its nozzle's rows so far: its count before this call plus
        # its rank among the call's rows of that nozzle (0 when the ids are distinct)
        place = self._count_of[ids].astype(np.int64)
        if not distinct and ids.size:
            order = np.argsort(ids, kind="stable")
            s = ids[order]
            first = np.r_[True, s[1:] != s[:-1]]
            start = np.maximum.accumulate(np.where(first, np.arange(s.size), 0))
            rank = np.empty(ids.size, np.int64)
            rank[order] = np.arange(s.size) - start
            place += rank
        return rows, ids, place, place < self.n_frames  # nozzles short of n_frames rows, at most their shortfall

    @property
    def n_complete(self) -> int:
        """Nozzles with ``n_frames`` rows recorded."""
        return int(np.count_nonzero(self._count_of >= self.n_frames))

    @property
    def n_seen(self) -> int:
        """Nozzles with at least one row recorded."""
        return int(np.count_nonzero(self._count_of))

    def baselines(self, min_frames: int | None = None) -> NozzleBaselines:
        """The baselines of the nozzles with at least ``min_frames`` rows (default ``n_frames``).

        Each is the median over the nozzle's rows (up to ``n_frames``), KPI by KPI (:func:`median_kpis`).
        A nozzle whose baseline rings unlike the head's others (:data:`UNLIKE_HEAD_SDS`) gets none: it was
        not healthy when recorded (a dried nozzle's taken as healthy turned its later estimates upside down);
        :attr:`unlike_head` and :meth:`unlike_note` say which.
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
                med = median_kpis(stack, skip_nan=True)  # the phase's on the circle where it wraps
        else:
            med = np.empty((0, N_KPIS + 1))
        reference = None
        if self.reference:
            reference = np.empty((med.shape[0], self.n_samples), np.float32)
            if ok.any():
                rows = np.concatenate(self._traces)[order]
                counts_ok = np.minimum(counts[ok], self.n_frames)
                for c in np.unique(counts_ok):  # nozzles with the same number of rows together
                    sel = np.flatnonzero(counts_ok == c)
                    reference[sel] = np.median(rows[idx[sel, :c]], axis=1)
        ids = ids[ok]
        like = self._like_the_head(ids, med)
        return NozzleBaselines(ids[like], med[like, :N_KPIS], self.sample_rate_hz, self.n_samples, self.n_frames,
                               fm=med[like, N_KPIS] if self.fm_frames else None, head_sha256=self.profile.sha256,
                               reference=None if reference is None else reference[like])  # fm_method: FM_METHOD with fm

    def _like_the_head(self, ids, med):
        """(m,) bool: the nozzles (``ids``, their median KPIs ``med``) that ring like the head's others."""
        f, z = med[:, 1], med[:, 2]
        like = np.ones(ids.size, bool)
        fin = np.isfinite(f) & np.isfinite(z)
        self.unlike_head = (ids[:0], f[:0], z[:0], np.nan, np.nan)
        if np.count_nonzero(fin) < UNLIKE_HEAD_MIN_NOZZLES:
            return like
        fm, zm = np.median(f[fin]), np.median(z[fin])
        sf = max(1.4826 * np.median(np.abs(f[fin] - fm)), 0.005 * abs(fm))
        sz = max(1.4826 * np.median(np.abs(z[fin] - zm)), 0.02 * abs(zm))
        like[fin] = (np.abs(f[fin] - fm) <= UNLIKE_HEAD_SDS * sf) & (np.abs(z[fin] - zm) <= UNLIKE_HEAD_SDS * sz)
        self.unlike_head = (ids[~like], f[~like], z[~like], float(fm), float(zm))
        return like

    def unlike_note(self) -> str:
        """What the last :meth:`baselines` left out as ringing unlike the head's other nozzles, or ""."""
        ids, f, z, fm, zm = self.unlike_head
        if not ids.size:
            return ""
        shown = ", ".join(f"{i} ({fi / 1e3:.1f} kHz, {zi:.3f})" for i, fi, zi in zip(ids[:5], f[:5], z[:5]))
        return (f"{ids.size} nozzle(s) ring unlike the head's others (its median {fm / 1e3:.1f} kHz, damping "
                f"{zm:.3f}): {shown}{', ...' if ids.size > 5 else ''}: no baseline for them (not healthy when recorded? purge "
                "them and record again); they are labelled without one")
