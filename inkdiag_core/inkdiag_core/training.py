"""Train a :class:`inkdiag_core.FaultDetector` for one head: :func:`train_detector`.

The faults are simulated on the head's own (calibrated) model by
:meth:`inkdiag_core.HeadProfile.simulate`: the same physical mechanisms and
severity ranges as for the default head (air bubbles, blockage, drying, an empty
channel, ...; :data:`inkdiag_core.faults.MECHANISMS`) on the head's own geometry,
ink, drive and sampling. The ranges are relative to the head's nozzle and ink (a
viscosity ratio, fractions of the nozzle bore, an ink-film mass ratio) but for the
chamber bubble's absolute radius. Optionally the user's own labelled recordings join
them.

How real and simulated rows are combined
----------------------------------------
With ``data`` (a labelled :class:`inkdiag_core.Recording` of the same head):

1. only the recorded rows labelling would judge are used
   (:func:`inkdiag_core.screen_traces` at 5x the head's ADC range: rows that are
   non-finite, out of range, flat or clipped are left out and counted);
2. each recorded class is split first, ``validation_fraction`` (a quarter) held
   out, seeded (a class of one row goes to fitting); the simulated rows get the
   detector's usual stratified split;
3. the held-out recorded rows join the validation rows once: the fault-detection
   threshold and the scores see real rows too;
4. the fitting part of each recorded class is *replicated* (whole copies, then
   a seeded sample of the remainder) up to the number of simulated fitting rows
   of that class (``0.75 x n_per_class``), so a class's recorded rows weigh as
   much in the forest as its simulated ones however few were recorded: for a
   recorded class, real and simulated rows count half and half. Replication is
   what a ``sample_weight`` of ``n_sim / n_real`` would do; the detector's
   pipelines take none. Copies never cross the split (it is done before). A
   class recorded with more rows than that keeps them all, once.

Classes the recording does not have are simulated only.
"""

from __future__ import annotations

import numpy as np

from .faults import FaultClass
from .openset import UNKNOWN

__all__ = ["N_PER_CLASS", "TrainingData", "leaf_size", "train_detector"]


class TrainingData:
    """The rows :func:`train_detector` fitted on (for reports and tests).

    Attributes
    ----------
    traces : ndarray, shape (n, n_samples), float32
        V; simulated rows first, then recorded ones (replicated).
    labels : ndarray of str, shape (n,)
    real : ndarray of bool, shape (n,)
        The row came from the recording.
    """

    def __init__(self, traces, labels, real):
        self.traces, self.labels, self.real = traces, labels, real


def _check_profile(profile):
    from .head_profile import HeadProfile, ProfileError

    if not isinstance(profile, HeadProfile):
        raise TypeError(f"profile must be a HeadProfile, got {type(profile).__name__}")
    if not profile.is_complete:
        raise ProfileError(f"profile {profile.name!r} is nominal ({', '.join(profile.missing)} missing): training "
                           "simulates faults on the head's complete model: run `inkdiag calibrate` first")
    f_max = empty_channel_mode_hz(profile)
    if not profile.sample_rate_hz >= 2.0 * f_max:
        raise ProfileError(  # a given f_act (a datasheet's, calibrate --empty's) is below Nyquist: the loader says
            f"profile {profile.name!r}: its empty channels ring at the actuator's own resonance, {f_max / 1e3:.0f} kHz "
            "(assumed like the default head's: the profile gives no channel.f_act), above the Nyquist frequency of "
            f"its sampling, {profile.sample_rate_hz / 2e3:.0f} kHz, so the empty-channel classes cannot be "
            "simulated: if the actuator's datasheet puts its resonance below that, give it as channel.f_act (Hz) in "
            "the nominal profile (or calibrate with --empty DRY.npz, traces of the head's empty channels) and "
            "calibrate again; if above, the head needs a higher sample rate for inkdiag to tell its empty channels")


def empty_channel_mode_hz(profile) -> float:
    """The highest mode the profile's empty-channel classes ring at, Hz (the actuator's own resonance): training
    refuses a profile sampled below twice it (the calibrate verb warns of the same)."""
    from .simulation.modal import class_max_frequency

    return class_max_frequency(FaultClass.EMPTY_CHANNEL_1, profile.channel_params())


def _share(n_per_class, n_draws, k):
    """Traces per class of draw ``k`` of ``n_draws``: ``n_per_class`` split evenly, the remainder to draw
    ``n_draws // 2`` (with an odd count, the profile itself)."""
    n = n_per_class // n_draws + (n_per_class % n_draws if k == n_draws // 2 else 0)
    return {c: int(n) for c in FaultClass}


def _real_rows(data, profile, seed, validation_fraction, n_sim_per_class):
    """Recorded rows split per class, the training part replicated: (X_fit, y_fit, X_val, y_val, counts).

    A class's identical rows (the recording's own copies) go to one side of the split together, as
    the copies this function makes do: a validation row is never a training row.

    ``counts``: ``n_real_rows`` (used), ``n_real_rows_validation`` (of them, held out),
    ``n_real_rows_repeated`` (used rows identical to another of their class), ``n_real_rows_invalid``
    (left out: the sum of ``n_real_rows_screened_out``, rows screening refuses, and
    ``n_real_rows_without_class``, rows labelled ``invalid`` or ``unknown``), ``real_rows_per_class``.
    """
    from .recording import NOT_CLASSES, RecordingError
    from .screening import screen_traces

    if data.label is None:
        raise RecordingError(f"{data.source}: the recording has no 'label' array: training data needs each row's "
                             "class")
    profile.check_traces(data.traces, data.sample_rate_hz, what=data.source)
    # the rows labelling would judge (not invalid: non-finite, beyond 5x the ADC range, flat, clipped), of a class
    usable, why = screen_traces(data.traces, max_abs_v=profile.max_abs_v, sample_rate_hz=profile.sample_rate_hz)
    n_screened = int((~usable).sum())
    usable &= ~np.isin(np.asarray(data.label).astype(str), NOT_CLASSES)
    if not usable.any():
        units = (f"; {int((why == 'out_of_range').sum())} of {why.size} rows have a sample beyond "
                 f"{profile.max_abs_v:g} V: are the traces in volts (not millivolts or ADC counts)?"
                 if (why == "out_of_range").sum() >= why.size / 2 else "")
        raise RecordingError(f"{data.source}: no row is usable (every row is non-finite, out of range, flat or "
                             f"clipped, or labelled {' or '.join(NOT_CLASSES)}){units}")
    X, y = data.traces[usable], np.asarray(data.label[usable]).astype(str)
    rng = np.random.default_rng([int(seed), 14])
    fit_x, fit_y, val_x, val_y = [], [], [], []
    n_repeated = 0
    for cls in np.unique(y):
        idx = rng.permutation(np.flatnonzero(y == cls))
        n_val = int(np.floor(validation_fraction * idx.size)) if idx.size > 1 else 0
        rows = np.ascontiguousarray(X[idx]).view(np.dtype((np.void, X.dtype.itemsize * X.shape[1]))).ravel()
        _, first, group = np.unique(rows, return_index=True, return_inverse=True)
        if first.size == idx.size:  # no two rows alike
            val, fit = idx[:n_val], idx[n_val:]
        else:  # whole groups of identical rows, in the order their first rows come, each that still fits in n_val
            n_repeated += idx.size - first.size
            sizes = np.bincount(group)
            taken, n_held = [], 0
            for g in np.argsort(first, kind="stable"):
                if n_held + sizes[g] <= n_val:
                    taken.append(g)
                    n_held += int(sizes[g])
            held = np.isin(group, taken)
            val, fit = idx[held], idx[~held]
        want = max(int(n_sim_per_class * (1 - validation_fraction)), fit.size)
        reps = np.concatenate([np.tile(fit, want // fit.size), rng.choice(fit, want % fit.size, replace=False)])
        fit_x.append(X[reps])
        fit_y.append(y[reps])
        val_x.append(X[val])
        val_y.append(y[val])
    per_class = {str(c): int((y == c).sum()) for c in np.unique(y)}
    counts = {"n_real_rows": int(usable.sum()), "n_real_rows_validation": int(sum(v.size for v in val_y)),
              "n_real_rows_repeated": n_repeated, "n_real_rows_invalid": int((~usable).sum()),
              "n_real_rows_screened_out": n_screened,
              "n_real_rows_without_class": int((~usable).sum()) - n_screened, "real_rows_per_class": per_class}
    return np.concatenate(fit_x), np.concatenate(fit_y), np.concatenate(val_x), np.concatenate(val_y), counts


N_PER_CLASS = 5000
"""Simulated traces per class :func:`train_detector` (and ``inkdiag train``) fits by default.

On the calibrated profiles of ``tests/foreign_head.py``'s heads h20, h16, h12 and h5 (300 healthy
traces, seeds 0, 7 and 11, 1,000 test traces a class; ``reports/train_size.md``, 2026-11-26), 5,000
a class with 15 traces a leaf against 1,000 with 3: FI 90.74 against 89.89 % on average, the
weakest class 62.69 against 59.45 % (77.86 against 71.83 % without h5, whose partially blocked
nozzles no single trace tells apart: ``reports/separability.md``), the FD, FI and per-class targets
met in 6 of the 12 runs against 4. 3,000 with 9 a leaf fell between (90.27 %, 61.20 %, 5 runs).
The forest grows by about 60 % (32,689 to 51,566 nodes: ``min_samples_leaf`` scales with the rows,
:func:`leaf_size`) and training takes several times as long (``inkdiag train`` on h20: 28 s)."""


def leaf_size(n_per_class: int) -> int:
    """Default ``min_samples_leaf`` for ``n_per_class`` simulated traces a class: 3 per 1,000, at least 3."""
    return max(3, int(3 * int(n_per_class) / 1000 + 0.5))  # halves up


def train_detector(profile, *, features: str = "kpi_y", kind: str = "rf", baseline: bool = False,
                   n_per_class: int = N_PER_CLASS, data=None, seed: int = 0, n_estimators: int = 50,
                   min_samples_leaf=None, max_features=None, fnr_target: float = 0.005,
                   validation_fraction: float = 0.25,
                   unknown_rate: float | None = 0.01, posterior_draws: int = 5, progress=None,
                   return_data: bool = False):
    """Fit a :class:`inkdiag_core.FaultDetector` for the head of ``profile``.

    Simulates ``n_per_class`` traces of each of the 12 classes on the head
    (:meth:`inkdiag_core.HeadProfile.simulate`, ``seed``; with ``posterior_draws`` > 1 and a
    profile ``inkdiag calibrate`` wrote, spread evenly over
    :func:`inkdiag_core.calibration.posterior_profiles`: the fit and its neighbours along what
    its healthy traces left uncertain), adds the recorded rows of
    ``data`` if given (see the module docstring: split first, the training part
    replicated per class up to the simulated count, the validation part once),
    and fits a detector with ``profile=profile`` (its sample rate, its residual
    model, its feature bands). With ``baseline=True`` also the baseline branch:
    each simulated trace gets its nozzle's healthy baseline, ``8`` healthy frames of
    the same simulated nozzle on this head (recorded rows have no baseline and
    then train the plain branch only, so ``baseline`` with ``data`` is refused).

    For the default head and no ``data`` the detector is the one
    :func:`inkdiag_core.fdi.train_default_model` fits with the same ``n_per_class``, ``seed``
    and ``min_samples_leaf`` (its default is 3; here :func:`leaf_size`, 3 up to 1,166 a class).

    Parameters
    ----------
    profile : HeadProfile
        A complete profile (``inkdiag calibrate`` makes one from a nominal one).
    features : str
        Feature set of the plain branch (:data:`inkdiag_core.FEATURE_SETS` but
        ``"kpi_y+baseline"``).
    kind : {"rf", "knn"}
    baseline : bool
        Fit the per-nozzle baseline branch too.
    n_per_class : int
        Simulated traces per class, >= 8 (default :data:`N_PER_CLASS`).
    data : Recording, optional
        Labelled recordings of this head (``label`` required, the profile's sampling).
    seed : int
        Seed of the simulation, the split and the forest.
    min_samples_leaf : int, optional
        As :class:`inkdiag_core.FaultDetector`; default :func:`leaf_size` of ``n_per_class``
        (3 traces a leaf per 1,000 a class: the forest's trees grow much less than the
        simulated rows).
    n_estimators, max_features, fnr_target, validation_fraction, unknown_rate
        As :class:`inkdiag_core.FaultDetector` (``unknown_rate``: the open-set layer's
        false-unknown bound, default 0.01; None or 0: no ``unknown``).
    posterior_draws : int
        Profiles the simulated rows are spread over (1: the profile alone; the default is
        :data:`inkdiag_core.calibration.POSTERIOR_DRAWS`): for a profile ``inkdiag calibrate``
        wrote, :func:`inkdiag_core.calibration.posterior_profiles`, its restrictor inertance
        spread over calibration's own scatter, with the healthy mode kept. On the heads of
        ``tests/foreign_head.py`` whose restrictor calibration fitted 6-7 % too large, the
        dried classes a model of the fit alone lost to partially blocked came back, 66.0-71.0
        -> 78.5-80.0 % for the weakest class (``docs/calibration.md``).
    progress : callable(step: int, total: int, message: str), optional
        Called after each stage.
    return_data : bool
        Also return the :class:`TrainingData` fitted on.

    Returns
    -------
    detector : FaultDetector
        Fitted; ``scores_`` are on the validation split (simulated and recorded rows).
    info : dict
        JSON-ready description of the training data for the manifest's config
        (``n_per_class``, ``seed``, ``training_data``, ``n_real_rows``, ...).
    data : TrainingData
        Only with ``return_data``.

    Raises
    ------
    ProfileError
        A nominal profile.
    RecordingError
        ``data`` without labels or of another sampling.
    """
    from .baselines import baseline_kpis
    from .calibration import posterior_profiles, restrictor_spread
    from .detector import FaultDetector
    from .simulation import healthy_twin_chunks

    _check_profile(profile)
    if isinstance(n_per_class, bool) or not isinstance(n_per_class, (int, np.integer)) or n_per_class < 8:
        raise ValueError(f"n_per_class must be an integer >= 8, got {n_per_class!r}")
    if baseline and data is not None:
        raise ValueError("baseline=True with recorded data: recorded rows have no per-nozzle baselines; train the "
                         "baseline branch on simulated rows only (leave out data) or train without baseline")
    report = progress or (lambda step, total, message: None)
    total = 4
    if isinstance(posterior_draws, bool) or not isinstance(posterior_draws, (int, np.integer)) or posterior_draws < 1:
        raise ValueError(f"posterior_draws must be an integer >= 1, got {posterior_draws!r}")
    if posterior_draws > n_per_class and len(posterior_profiles(profile, 2)) > 1:  # no effect without a posterior
        raise ValueError(f"posterior_draws ({posterior_draws}) must not exceed n_per_class ({n_per_class}): each "
                         "draw simulates n_per_class / posterior_draws traces per class")
    heads = posterior_profiles(profile, int(posterior_draws))  # [profile] without a recorded posterior
    sims = [(head, head.simulate(_share(n_per_class, len(heads), k), seed=seed + 7919 * k), seed + 7919 * k)
            for k, head in enumerate(heads)]
    X = np.concatenate([sim.traces for _, sim, _ in sims]) if len(sims) > 1 else sims[0][1].traces
    y = np.concatenate([sim.label_values() for _, sim, _ in sims])
    report(1, total, f"simulated {len(y)} traces on head {profile.name!r}"
           + (f" over {len(heads)} restrictors its calibration allows" if len(heads) > 1 else ""))
    info = {"n_per_class": int(n_per_class), "seed": int(seed),
            "training_data": "simulated", "n_real_rows": 0, "posterior_draws": len(heads),
            "restrictor_sd_log": restrictor_spread(profile) if len(heads) > 1 else 0.0}
    det = FaultDetector(kind=kind, features=features, profile=profile, n_estimators=int(n_estimators),
                        min_samples_leaf=leaf_size(n_per_class) if min_samples_leaf is None else int(min_samples_leaf),
                        max_features=max_features,
                        fnr_target=float(fnr_target), validation_fraction=float(validation_fraction),
                        unknown_rate=unknown_rate, random_state=int(seed))
    real = np.zeros(len(y), dtype=bool)
    if data is None:
        base = None
        if baseline:  # each simulated nozzle's healthy twin, on its own draw's channel
            base = np.concatenate([baseline_kpis(frames, profile.sample_rate_hz) for head, sim, sim_seed in sims
                                   for _, frames in healthy_twin_chunks(
                len(sim), seed=sim_seed, n_frames=8, noise_std_v=sim.noise_std_v, spreads=head.spreads(),
                sample_rate_hz=head.sample_rate_hz, n_samples=head.n_samples, drive=head.drive,
                base_params=head.channel_params(), sensor_gain_v_per_m3s=head.sensor_gain_v_per_m3s,
                sensor_offset_v=head.sensor_offset_v)])  # frames a block of rows at a time: bounded memory
        det.fit(X, y, baseline_kpis=base)
    else:
        Xr_fit, yr_fit, Xr_val, yr_val, counts = _real_rows(
            data, profile, seed, float(validation_fraction), int(n_per_class))
        info.update(training_data="simulated+recorded", **counts,
                    real_rows_weighting="per class: recorded training rows replicated up to the simulated count "
                    "(never cut below their own number); a quarter of each recorded class held out for validation, "
                    "once, identical rows together")
        from sklearn.model_selection import train_test_split

        # the simulated rows' usual split, the recorded rows' own (done before replicating)
        _, sim_val = train_test_split(np.arange(len(y)), test_size=float(validation_fraction),
                                      random_state=int(seed), stratify=y)
        mask = np.zeros(len(y) + len(yr_fit) + len(yr_val), dtype=bool)
        mask[sim_val] = True
        mask[len(y) + len(yr_fit):] = True
        X = np.concatenate([X, Xr_fit, Xr_val])
        y = np.concatenate([y, yr_fit, yr_val])
        real = np.concatenate([real, np.ones(len(yr_fit) + len(yr_val), dtype=bool)])
        det.fit(X, y, validation_mask=mask)
        if len(yr_val):  # the recorded rows' own score at the FD threshold, as inkdiag label labels them
            got = det.label(Xr_val)
            named = got.valid & (got.classes != UNKNOWN)  # a class given (unknown: the open-set layer's, scored apart)
            info["n_real_rows_validation_classified"] = int(named.sum())
            info["validation_real_unknown_share"] = (float(np.mean(got.classes[got.valid] == UNKNOWN))
                                                     if got.valid.any() else float("nan"))
            info["validation_real_fi_accuracy"] = (float(np.mean(got.classes[named] == yr_val[named])) if named.any()
                                                   else float("nan"))
    report(2, total, f"fitted {kind} on {features} features" + (" and baselines" if baseline else ""))
    s = det.scores_
    report(3, total, f"validation FI accuracy {100 * s['validation_fi_accuracy']:.1f}%, "
                     f"FD miss rate {100 * s['validation_fd_fnr']:.2f}%, false alarms {100 * s['validation_fd_fpr']:.2f}%")
    if return_data:
        return det, info, TrainingData(X, y, real)
    return det, info
