"""The constants of ``"vp_cal"`` for one head: fit them, find them, cache them.

``"vp_cal"`` corrects the ``"vp"`` estimate with four dimensionless constants
(:data:`~.vp.VP_CAL` for the default head) learned on physics-based simulations of
the head's dried nozzles: how the fault error of ``"vp"`` goes with the ring-down's
damping and frequency deviations ``(d_sigma, d_omega)`` from the nominal model,

    (f_true - f_vp) / |f_true| ~ [(a_s + b_s x) d_sigma + (a_w + b_w x) d_omega] / |f_true|,

``x = f_vp / w0`` (w0 the nominal healthy angular frequency in the estimator's
scaled units), weighted least squares, no intercept: the correction vanishes on
data the nominal linear model explains. The simulations are
:func:`~inkdiag_core.fe_datasets.nonlinear_set` on the head (its channel, drive,
spreads, noise and sampling), seeds disjoint from the fault-estimation report's
evaluation set (seed 100) and from the tests. The constants belong to a head:
another geometry, ink or drive changes how the simulator's spreads and nonlinear
terms bend the ring-down, so each head gets its own (:func:`vp_cal_for`).

``scripts/calibrate_vp_cal.py`` runs :func:`calibrate_vp_cal` on the default head
with the seeds and sizes that produced :data:`~.vp.VP_CAL`.
"""

from __future__ import annotations

import math
import threading
import time

import numpy as np

from .. import checks
from .base import T0, model_matrices, scaled, default_bounds
from .vp import VP_CAL, pair_refit, vp_batch
from ..head_profile import MAX_VP_CAL, VP_CAL_KEYS

__all__ = [
    "EVAL_SEEDS",
    "HEAD_SEEDS",
    "HEAD_N_PER_CLASS",
    "calibrate_vp_cal",
    "vp_cal_needs_fit",
    "vp_cal_features",
    "vp_cal_fit_seconds",
    "vp_cal_for",
]

EVAL_SEEDS = (100,)
"""Seeds of the fault-estimation report's physics-based evaluation set: never calibrated on."""

HEAD_SEEDS = (11, 13)
"""Seeds (first, last, inclusive) :func:`vp_cal_for` calibrates a new head on (``VP_CAL``: 11-19)."""

HEAD_N_PER_CLASS = 60
"""Traces per dried class and seed :func:`vp_cal_for` simulates for a new head (``VP_CAL``: 100)."""

_KEYS = VP_CAL_KEYS
_CACHE: dict = {}
_LOCK = threading.Lock()


def vp_cal_features(model, y, sample_rate_hz):
    """The "vp" estimate and the mismatch deviations, exactly as ``"vp_cal"`` computes them.

    Parameters
    ----------
    model : InkChannelModel
        The head's nominal model.
    y : ndarray, shape (n, n_samples)
        Outputs, m^3/s (any scale: each trace is divided by its RMS).
    sample_rate_hz : float
        Hz.

    Returns
    -------
    f, x, d_sigma, d_omega : ndarray, shape (n,)
        The "vp" estimate in scaled units (1/us), ``x = f / w0`` and the pair's
        decay-rate and angular-frequency deviations (1/us).
    """
    A, C, B_f, _ = model_matrices(model)
    sc = scaled(A, C, B_f, sample_rate_hz)
    key = (tuple(A.ravel()), tuple(C.ravel()), tuple(B_f.ravel()), float(sample_rate_hz))
    c = np.sqrt(np.mean(y * y, axis=1))
    ys = y / c[:, None]
    f = vp_batch(sc, key, ys, fm_bounds=default_bounds(A, B_f))[0] * T0
    dev = pair_refit(sc, ys, f)[0]
    return f, f / sc.w0, dev[:, 0], dev[:, 1]


def _design(x, d_sigma, d_omega):
    return np.column_stack([d_sigma, x * d_sigma, d_omega, x * d_omega])


def _fit(rows):
    X = np.concatenate([_design(*r[1:4]) for r in rows])
    f = np.concatenate([r[0] for r in rows])
    ft = np.concatenate([r[4] for r in rows])
    w = 1.0 / np.abs(ft)
    return np.linalg.lstsq(X * w[:, None], (ft - f) * w, rcond=None)[0]


def _finite(rows):
    """``rows`` (per seed: the "vp" estimate, x, d_sigma, d_omega, the true f_m) without the traces whose values are
    not all finite; InputError when those are half of them or more, or fewer than 20 are left (lstsq on NaN rows
    had given four zeros without a word, helper-137)."""
    keep = [np.logical_and.reduce([np.isfinite(c) for c in r]) & (r[4] != 0) for r in rows]
    n, n_ok = sum(k.size for k in keep), sum(int(k.sum()) for k in keep)
    if 2 * n_ok <= n or n_ok < 20 or not all(k.any() for k in keep):  # every seed's set (the last one is held out)
        raise checks.InputError(f"vp_cal: {n - n_ok} of the head's {n} simulated dried traces give no finite estimate: "
                                "check the profile's spreads and sensor")
    return [tuple(c[k] for c in r) for r, k in zip(rows, keep)]


def _accuracy(r, b):
    """Per-trace accuracy 100 (1 - |f_hat - f| / |f|), %."""
    return 100 * (1 - np.abs(r[0] + _design(*r[1:4]) @ b - r[4]) / np.abs(r[4]))


def calibrate_vp_cal(profile=None, *, seeds=(11, 19), n_per_class=100, progress=None) -> dict:
    """Fit the ``"vp_cal"`` constants of a head (the procedure of ``scripts/calibrate_vp_cal.py``).

    Parameters
    ----------
    profile : HeadProfile, optional
        A complete head profile; None: the simulator's default head and sampling
        (10 MHz x 512), as :data:`~.vp.VP_CAL` was made.
    seeds : (int, int)
        First and last seed (inclusive) of the simulated sets, at least two (the
        last is also held out once to report the correction's accuracy); never
        :data:`EVAL_SEEDS`.
    n_per_class : int
        Dried traces per class (slightly, intermediately, deeply) and seed.
    progress : callable, optional
        Called as ``progress(seed, n_traces)`` after each seed's set.

    Returns
    -------
    dict
        ``a_sigma, b_sigma, a_omega, b_omega`` (dimensionless, the form of
        :data:`~.vp.VP_CAL`), ``seeds``, ``n_traces``, ``holdout`` (``{"seed",
        "vp_median", "vp_cal_median", "vp_p10", "vp_cal_p10"}``: f_m accuracy in %,
        100 (1 - |error| / |f_m|), of the last seed with constants fitted on the
        others), ``residual_rel_std`` (relative f_m residual of the final fit),
        ``seconds`` (wall time) and, with a profile, ``profile_sha256``.

    Raises
    ------
    inkdiag_core.checks.InputError
        Bad seeds or sizes, a nominal profile.
    """
    from ..fe_datasets import nonlinear_set
    from ..model import InkChannelModel

    lo, hi = (int(s) for s in seeds)
    seed_list = list(range(lo, hi + 1))
    if len(seed_list) < 2:
        raise checks.InputError(f"calibrate_vp_cal needs at least two seeds, got {seeds!r}")
    if set(seed_list) & set(EVAL_SEEDS):
        raise checks.InputError(f"calibration seeds must not include the evaluation seeds {EVAL_SEEDS}")
    n_per_class = checks.positive_int("n_per_class", n_per_class)
    if profile is not None:
        profile._need_complete("calibrating vp_cal")
        model, fs, n_samples = profile.model(), profile.sample_rate_hz, profile.n_samples
    else:
        model, fs, n_samples = InkChannelModel(), 10e6, 512
    t0 = time.perf_counter()
    rows = []
    for s in seed_list:
        ds = nonlinear_set(n_per_class, seed=s, sample_rate_hz=fs, n_samples=n_samples, profile=profile,
                           clean=False)
        rows.append((*vp_cal_features(model, ds.y, fs), ds.fm * T0))
        if progress is not None:
            progress(s, ds.y.shape[0])
    rows = _finite(rows)
    hold = _fit(rows[:-1])
    a0, a1 = _accuracy(rows[-1], np.zeros(4)), _accuracy(rows[-1], hold)
    b = _fit(rows)
    res = np.concatenate([r[0] + _design(*r[1:4]) @ b - r[4] for r in rows])
    fts = np.concatenate([r[4] for r in rows])
    out = dict(zip(_KEYS, (float(v) for v in b)))
    if not all(abs(v) <= MAX_VP_CAL for v in out.values()):  # what a profile stores (its calibration section)
        raise checks.InputError(f"vp_cal: the fitted constants {out} are beyond any head's (magnitude above "
                                f"{MAX_VP_CAL:g}): check the profile's channel, spreads and sensor")
    out.update(seeds=(lo, hi), n_traces=int(fts.size),
               holdout={"seed": seed_list[-1], "vp_median": float(np.median(a0)),
                        "vp_cal_median": float(np.median(a1)), "vp_p10": float(np.percentile(a0, 10)),
                        "vp_cal_p10": float(np.percentile(a1, 10))},
               residual_rel_std=float(np.std(res / np.abs(fts))),
               seconds=float(time.perf_counter() - t0))
    if profile is not None:
        out["profile_sha256"] = profile.sha256
    return out


def _stored(profile):
    """The constants in the profile's ``calibration: vp_cal:`` section, if they are this head's."""
    cal = profile.calibration.get("vp_cal") if profile.calibration else None
    if not isinstance(cal, dict) or cal.get("profile_sha256") != profile.sha256:
        return None
    try:
        got = {**cal, **{k: float(cal[k]) for k in _KEYS}}
    except (KeyError, TypeError, ValueError):
        return None
    return got if all(math.isfinite(got[k]) for k in _KEYS) else None  # NaN constants: every estimate lost


def vp_cal_fit_seconds(profile) -> float:
    """Roughly how long :func:`vp_cal_for`'s fit of a new head takes on a 2-core machine, s: its physics-based
    simulation integrates each trace's whole duration, about 8 s plus 0.1 s per microsecond of trace (measured
    2026-11-29: 14 s at 10 MHz x 1024, 26 s at x 2048, 143 s at x 16384; 10.5 s at 100 MHz x 4096)."""
    return 8.0 + 0.1 * profile.n_samples / profile.sample_rate_hz * 1e6


def vp_cal_needs_fit(profile) -> bool:
    """Whether :func:`vp_cal_for` would fit ``profile``'s constants now (seconds): not the default
    head, none stored in the profile for this head, none fitted yet in this process."""
    from ..head_profile import HeadProfile

    if profile.sha256 == HeadProfile.default().sha256 or _stored(profile) is not None:
        return False
    with _LOCK:
        return profile.sha256 not in _CACHE


def vp_cal_for(profile) -> dict:
    """The ``"vp_cal"`` constants of a head: :data:`~.vp.VP_CAL` for the default head, else fitted once.

    In order: the default head (same :attr:`~inkdiag_core.HeadProfile.sha256`)
    gets :data:`~.vp.VP_CAL` itself; a profile whose ``calibration: vp_cal:``
    section holds constants with this head's ``profile_sha256`` gets those; else
    :func:`calibrate_vp_cal` runs on the head (seeds :data:`HEAD_SEEDS`,
    :data:`HEAD_N_PER_CLASS` traces per class and seed) and the result is kept
    in this process per sha256 (later calls are free). Save it into the profile
    to skip the fit next time (without its wall time, ``seconds``, as ``inkdiag calibrate`` does, so
    that the same inputs write the same file)::

        cal = {k: v for k, v in vp_cal_for(profile).items() if k != "seconds"}
        profile.replace(calibration={"vp_cal": cal}).save(path)

    Parameters
    ----------
    profile : HeadProfile
        A complete profile.

    Returns
    -------
    dict
        ``a_sigma, b_sigma, a_omega, b_omega`` and the fit's provenance.
    """
    from ..head_profile import HeadProfile

    if not isinstance(profile, HeadProfile):
        raise checks.InputError(f"vp_cal_for takes a HeadProfile, got {type(profile).__name__}")
    if profile.sha256 == HeadProfile.default().sha256:
        return VP_CAL
    stored = _stored(profile)
    if stored is not None:
        return stored
    with _LOCK:
        hit = _CACHE.get(profile.sha256)
        if hit is None:
            hit = _CACHE[profile.sha256] = calibrate_vp_cal(profile, seeds=HEAD_SEEDS,
                                                             n_per_class=HEAD_N_PER_CLASS)
        return hit
