"""The public f_m estimators: one dispatcher over the method modules.

:func:`estimate_fm_batch` checks the inputs once, scales the traces, hands them to
the chosen method (:mod:`.uio` or :mod:`.vp`) with that method's options, and turns
the scaled result into SI (:class:`~.base.FmBatchEstimate`). :func:`estimate_fm`
is the same for one trace.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .. import checks
from ..model import fm_to_viscosity
from .base import (
    MIN_FM_SAMPLES,
    T0,
    FmBatchEstimate,
    FmEstimate,
    check_x0,
    default_bounds,
    model_matrices,
    scaled,
)
from .uio import CtOptions, DtExactOptions, DtOptions, ct_batch, dt_batch, dt_exact_batch
from .vp import VpOptions, vp_batch, vp_cal_correct, vp_growing_trace

__all__ = ["METHODS", "OPTIONS", "estimate_fm", "estimate_fm_batch"]

METHODS = ("auto", "dt", "dt_exact", "ct", "vp", "vp_cal")
"""Values of ``method``; ``"auto"`` is ``"vp_cal"`` without ``x0``, ``"vp"`` with it."""

OPTIONS = {"dt": DtOptions, "dt_exact": DtExactOptions, "ct": CtOptions,
           "vp": VpOptions, "vp_cal": VpOptions}
"""The options class of each method (``options=`` of :func:`estimate_fm_batch`)."""

# keyword arguments of estimate_fm_batch before the options classes -> option field
_RENAMED = {"vp_trace_points": "trace_points"}
#: A "vp" fit within this fraction of its search interval's width of an edge ended there (``at_bound``): its
#: Gauss-Newton steps are clipped to the interval, so a trace whose residual falls beyond it stops at the edge.
AT_BOUND_FRACTION = 1e-6


def _method_options(method, options, kwargs):
    """The options of ``method`` from an options object and/or the old keywords."""
    cls = OPTIONS[method]
    if options is None:
        options = cls()
    elif type(options) is not cls:
        raise checks.OptionError(
            f"method {method!r} takes options of type {cls.__name__}, "
            f"got {type(options).__name__}")
    if not kwargs:
        return options
    fields = {f.name for f in dataclasses.fields(cls)}
    wrong = sorted(k for k in kwargs if _RENAMED.get(k, k) not in fields)
    if wrong:
        taken = sorted([k for k, v in _RENAMED.items() if v in fields]
                       + [f for f in fields if f not in _RENAMED.values()])
        raise checks.OptionError(
            f"method {method!r} does not take {', '.join(wrong)}; "
            f"it takes {', '.join(taken)} (as keywords or {cls.__name__})")
    return dataclasses.replace(options, **{_RENAMED.get(k, k): v for k, v in kwargs.items()})


def _bounds(A, B_f, fm_bounds):
    bounds = default_bounds(A, B_f) if fm_bounds is None else tuple(map(float, fm_bounds))
    if not bounds[0] < bounds[1]:
        raise checks.InputError(
            f"fm_bounds must be (low, high) with low < high, got {fm_bounds!r}")
    return bounds


def _profile(model):
    """``model`` if it is a HeadProfile (imported lazily: the profile module imports the simulator)."""
    from ..head_profile import HeadProfile

    return model if isinstance(model, HeadProfile) else None


def estimate_fm_batch(Y, model, sample_rate_hz, *, method="auto", x0=None, baseline_fm=None,
                      options=None, **kwargs) -> FmBatchEstimate:
    """Estimate f_m for many traces at once.

    Parameters
    ----------
    Y : array_like, shape (n_traces, n_samples)
        Outputs ``y = C x`` in m^3/s; sample k at ``t = k / sample_rate_hz``; at least
        :data:`~.base.MIN_FM_SAMPLES` (16) finite samples per trace.
    model : InkChannelModel, HeadProfile or tuple (A, C, B_f)
        Healthy model (eq. 12), shapes (3, 3), (1, 3), (3, 1) if given as matrices.
        A complete :class:`~inkdiag_core.HeadProfile`: its model, and for "vp_cal"
        its constants (:func:`~.vp_calibration.vp_cal_for`: the default head's
        :data:`~.vp.VP_CAL`, another head's fitted once) unless ``cal`` is given;
        the traces must be of its sampling rate.
    sample_rate_hz : float
        Sample rate, Hz.
    method : {"auto", "dt", "dt_exact", "ct", "vp", "vp_cal"}
        "auto": "vp_cal" without ``x0``, "vp" with it.
    x0 : array_like, shape (3,) or (n_traces, 3), optional
        Initial state (SI) for "dt", "dt_exact" and "ct" (required there); ignored by
        "vp" and "vp_cal".
    baseline_fm : float or array_like, shape (n_traces,), optional
        The same nozzle's estimate while it was healthy, 1/s (for instance the
        median over a few healthy frames; 0 = none). It is subtracted from
        ``.fm``, ``.trace`` and ``.ci``. A real nozzle differs from the nominal
        model (nozzle geometry, piezo compliance and coupling, within their
        tolerances), and the estimator reads that difference as a fault; it is a
        property of the nozzle, so its healthy reading removes the part that acts
        as an offset on f_m (e.g. its own R_n / I_n), though not a part that
        scales f_m (``reports/fe.md``). :class:`~inkdiag_core.BaselineRecorder`
        records the raw "vp" reading (:data:`inkdiag_core.baselines.FM_METHOD`),
        which :class:`~inkdiag_core.DryingTracker` subtracts from "vp" and "vp_cal"
        estimates alike: "vp_cal"'s correction is not the nozzle's own.
        ``.std`` stays the fit's own.
    options : DtOptions, DtExactOptions, CtOptions or VpOptions, optional
        The chosen method's options (:data:`OPTIONS`); default: that class's defaults.
    **kwargs
        Single options of the chosen method, applied over ``options``: ``exact_T``,
        ``prefilter_hz``, ``window``, ``steady_frac`` ("dt", "dt_exact", "ct");
        ``n_iter``, ``sensitivity`` ("dt_exact"); ``fm_bounds`` ("dt_exact", "vp",
        "vp_cal"); ``n_grid``, ``vp_trace_points`` (``VpOptions.trace_points``; "vp",
        "vp_cal"); ``cal`` ("vp_cal": the head's constants). See the options classes
        for their meaning.

    Returns
    -------
    FmBatchEstimate

    Raises
    ------
    inkdiag_core.checks.InputError
        Bad traces, model, sample rate, ``x0`` or ``baseline_fm`` (a ``ValueError``).
    inkdiag_core.checks.OptionError
        An option the chosen method does not take (a ``ValueError`` and ``TypeError``).
    """
    if method not in METHODS:
        raise checks.InputError(
            f"unknown method {method!r}; valid methods are {', '.join(METHODS)}")
    profile = _profile(model)
    if profile is not None:
        model = profile.model()
    A, C, B_f, params = model_matrices(model)
    fs = checks.sample_rate(sample_rate_hz)
    if profile is not None:  # its vp_cal constants are of its own sampling: traces of another are another head's
        from ..head_profile import same_sample_rate

        if not same_sample_rate(fs, profile.sample_rate_hz):
            raise checks.InputError(f"traces sampled at {fs:.10g} Hz; head profile {profile.name!r} is sampled at "
                                    f"{profile.sample_rate_hz:.10g} Hz: give its traces, or its InkChannelModel "
                                    "(profile.model()) for traces of another sampling")
    Y = checks.traces_2d(Y, "y", min_samples=MIN_FM_SAMPLES, promote_1d=False, dtype=np.float64)
    n, N = Y.shape
    if method == "auto":
        method = "vp_cal" if x0 is None else "vp"
    if method in ("dt", "dt_exact", "ct") and x0 is None:
        raise checks.InputError(
            f"method {method!r} needs x0 (the initial state, shape (3,), SI): the thesis's "
            "UIO is not asymptotically stable; use method='vp' when x0 is unknown"
        )
    X0 = check_x0(x0, n) if x0 is not None else None
    o = _method_options(method, options, kwargs)
    if method == "vp_cal" and o.cal is None and profile is not None:
        from .vp_calibration import vp_cal_for

        o = dataclasses.replace(o, cal=vp_cal_for(profile))
    sc = scaled(A, C, B_f, fs)
    c = np.sqrt(np.mean(Y * Y, axis=1))
    c = np.where(c > 0, c, 1.0)
    Ys = Y / c[:, None]
    std = np.full(n, np.nan)
    offset = np.zeros(n)
    at_bound = np.zeros(n, bool)
    residual_rel = np.full(n, np.nan)
    if method in ("dt", "dt_exact", "ct"):
        Xs0 = sc.to_scaled_x(X0, c)
        common = dict(exact_T=o.exact_T, window=o.window, steady_frac=o.steady_frac)
        if method == "dt":
            fm_s, trace_s = dt_batch(sc, Ys, Xs0, prefilter_hz=o.prefilter_hz,
                                     sample_rate_hz=fs, **common)
        elif method == "dt_exact":
            lo, hi = _bounds(A, B_f, o.fm_bounds)
            fm_s, trace_s = dt_exact_batch(sc, Ys, Xs0, prefilter_hz=o.prefilter_hz,
                                           sample_rate_hz=fs, n_iter=o.n_iter,
                                           sensitivity=o.sensitivity,
                                           bounds_s=(lo * T0, hi * T0), **common)
        else:
            fm_s, trace_s = ct_batch(sc, Ys, Xs0, prefilter_hz=1e6 if o.prefilter_hz is None
                                     else o.prefilter_hz, **common)
        fm = fm_s / T0
        trace = trace_s / T0
        x0_out = X0
    else:
        bounds = _bounds(A, B_f, o.fm_bounds)
        key = (tuple(A.ravel()), tuple(C.ravel()), tuple(B_f.ravel()), float(fs))
        fm, std, xs0, off_s, rss = vp_batch(sc, key, Ys, fm_bounds=bounds, n_grid=o.n_grid)
        # the share of the row's variation the fitted channel leaves (its sum of squares about the row's mean)
        tss = np.einsum("nk,nk->n", Ys, Ys) - N * np.mean(Ys, axis=1) ** 2
        with np.errstate(invalid="ignore", divide="ignore"):
            residual_rel = np.sqrt(np.maximum(rss, 0.0) / tss)
        edge = AT_BOUND_FRACTION * (bounds[1] - bounds[0])  # the search ends exactly at an edge it cannot pass
        at_bound = (fm <= bounds[0] + edge) | (fm >= bounds[1] - edge)
        if method == "vp_cal":
            fm_c, std_c, _ = vp_cal_correct(sc, Ys, fm * T0, cal=o.cal)
            fm, std = fm_c / T0, std_c / T0
        if o.trace_points and o.trace_points > 1:
            trace = vp_growing_trace(sc, key, Ys, fm, fm_bounds=bounds, n_grid=o.n_grid,
                                     points=int(o.trace_points), cal=method == "vp_cal",
                                     cal_constants=o.cal)
        else:
            trace = np.repeat(fm[:, None], N, axis=1)
        x0_out = sc.from_scaled_x(xs0, c)
        offset = off_s * c
    if baseline_fm is not None:
        base = np.asarray(baseline_fm, dtype=float)
        base = np.full(n, float(base)) if base.ndim == 0 else base
        if base.shape != (n,) or not np.isfinite(base).all():
            raise checks.InputError(f"baseline_fm must be a finite scalar or have shape ({n},), "
                                    f"got shape {np.shape(baseline_fm)}")
        fm = fm - base
        trace = trace - base[:, None]
    ci = np.stack([fm - 1.959964 * std, fm + 1.959964 * std], axis=1)
    if params is not None:
        d_mu, mu = fm_to_viscosity(params, fm)
    else:
        d_mu = mu = np.full(n, np.nan)
    return FmBatchEstimate(fm=fm, trace=trace, method=method, std=std, ci=ci, d_mu=d_mu,
                           viscosity=mu, x0=x0_out, offset=offset, at_bound=at_bound,
                           residual_rel=residual_rel)


def estimate_fm(y, model, sample_rate_hz, *, method="auto", x0=None, **kwargs) -> FmEstimate:
    """Estimate the multiplicative drying-nozzle fault f_m from one trace.

    Parameters
    ----------
    y : array_like, shape (n_samples,)
        Output ``y = C x`` of eq. (12) in m^3/s, sample k at ``t = k / sample_rate_hz``;
        at least 16 finite samples.
    model : InkChannelModel or tuple (A, C, B_f)
    sample_rate_hz : float
        Sample rate, Hz.
    method : {"auto", "dt", "dt_exact", "ct", "vp", "vp_cal"}
        "dt"/"ct": the thesis's approaches (need ``x0``); "dt_exact": "dt" with the
        exact discretisation linearised in f_m (needs ``x0``); "vp": variable projection
        (no ``x0``, gives ``std`` and ``ci``); "vp_cal": "vp" with the learned
        mismatch correction; "auto": "vp_cal" without ``x0``, "vp" with it.
    x0 : array_like, shape (3,), optional
        Initial state ``[V_r + V_n, V_r', V_n']`` (m^3, m^3/s, m^3/s) at t = 0.
    **kwargs
        Passed to :func:`estimate_fm_batch` (``options``, ``baseline_fm`` or single
        options). For "vp"/"vp_cal" the growing-window ``.trace`` defaults to 12
        window ends (``vp_trace_points=12``) unless ``options`` is given.

    Returns
    -------
    FmEstimate
    """
    Y = checks.trace_1d(y, "y", min_samples=MIN_FM_SAMPLES)[None, :]
    if x0 is not None:
        x0 = np.asarray(x0, dtype=float)
        if x0.shape != (3,):
            raise checks.InputError(f"x0 must have shape (3,), got {x0.shape}")
    if method in ("auto", "vp", "vp_cal") and kwargs.get("options") is None:
        kwargs.setdefault("vp_trace_points", 12)  # one trace: a per-sample estimate is affordable
    return estimate_fm_batch(Y, model, sample_rate_hz, method=method, x0=x0, **kwargs)[0]
