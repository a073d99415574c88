"""Estimation of the drying-nozzle fault f_m (thesis section 4.3-4.5).

The fault is multiplicative: ``A_faulty = A + f_m B_f e3^T`` (eq. 12-13; with
``B_f = e3`` this changes entry (3, 3) only), ``f_m = -dR_n / I_n < 0`` for a
drying nozzle (Appendix F). Five estimators:

``"dt"`` -- the thesis's discrete-time approach (eq. 22-25). The healthy model is
    discretised exactly, ``A_H^DT = expm(A_H dt)``, and the fault is the
    Appendix-E term ``B_f x3(k) f_m dt``. A discrete UIO (eq. 14-19 with
    ``A_H^DT``) started from the given ``x0`` reconstructs ``x_hat``; the
    residual ``r(k) = y(k+1) - C A_H^DT x_hat(k)`` and the regressor
    ``e(k) = C B_f x_hat3(k) dt`` pass through the same pre-filter ``tau``
    (eq. 5) and ``f_hat = e^+ r`` (eq. 6) is solved by least squares over a
    sliding window (``.trace``) and over the steady-state part (``.fm``), so a
    zero crossing of ``x3`` never divides by zero. Needs ``x0``. Exact on eq. (25)
    data; on exact continuous-time data the part of the true step that eq. (24)
    drops (``O(f_m dt^2)``, not along ``B_f``) drives the DT UIO's error, which
    decays only at about 128 /ms at 10 MHz: once a strongly damped ring-down decays
    faster (viscosity about x3 and up on the default channel) ``x_hat3`` is mostly
    that error and the estimate collapses even with the true ``x0`` -- a property of
    the method, not of the windowing, pre-filter or scaling (``reports/fe.md``).
``"dt_exact"`` -- ours: the "dt" regression with the exact discretisation
    linearised in f_m instead of Appendix E's ``B_f x3(k) f_m dt``:
    ``A_d(f) = expm((A_H + f e3 e3^T) dt) ~ A_d(f0) + (f - f0) D(f0)``, ``D`` the
    Frechet derivative of expm in the direction ``e3 e3^T dt`` (block-matrix
    expm, one per trace). The DT UIO is built on ``A_d(f0)`` and started from
    ``x0``; ``r(k) = y(k+1) - C A_d(f0) x_hat(k)``, and the regressor is
    ``e(k) = C D(f0) x_hat(k) + C A_d(f0) dx_hat(k)/df``: the second term (the
    UIO state's sensitivity, one extra 3-state recursion) is needed because
    the UIO decouples only the ``e3`` part of ``D``; without it the fixed-point
    iteration converges only linearly (about x0.5 per pass). ``f - f0 = e^+ r``,
    then ``n_iter`` (default 3) re-linearisations around the steady-state
    estimate: Gauss-Newton, quadratic convergence, exact at the fixed point on
    exact continuous-time data. Needs ``x0``.
``"ct"`` -- the thesis's continuous-time approach (eq. 26). The UIO runs in
    continuous time (``F = (I - HC) A``, ``T = F H``), driven by the sampled
    output held first-order (linear) between samples and integrated exactly;
    the residual ``r = y' - C A x_hat`` is never differentiated numerically:
    the pre-filter ``tau(s) = 1 / (T_f s + 1)`` makes ``tau[y']`` proper, and
    ``tau`` is applied equally to ``r`` and to ``e = C B_f x_hat3``. Needs ``x0``.
``"vp"`` -- variable projection, needs no initial state. For a candidate
    ``f_m`` the noise-free output is ``y_k = C A_d(f_m)^k x0 + y_dc``, linear in
    ``(x0, y_dc)``: those are solved by least squares, and the residual norm,
    a smooth 1-D function of ``f_m``, is minimised (grid, then Gauss-Newton).
    This is the maximum-likelihood estimate under white Gaussian noise; its
    standard deviation comes from the Gauss-Newton curvature with the residual
    variance, and ``.ci`` is the 95 % interval ``fm +- 1.96 std``.

``"vp_cal"`` -- ours: ``"vp"`` plus a learned correction of the model mismatch.
    A real nozzle is not the nominal linear model (ink temperature, geometry and
    piezo tolerances, meniscus stiffness, nozzle entrance loss) and ``"vp"``,
    whose only free parameter is f_m, reads part of that as a fault. Around the
    ``"vp"`` solution the ring-down's oscillatory pair is refitted freely (its
    decay rate and frequency, Gauss-Newton with everything else projected out);
    their deviations ``(d_sigma, d_omega)`` from the model's pair at the ``"vp"``
    estimate measure the mismatch, and
    ``fm = f_vp + (a_s + b_s f_vp/w0) d_sigma + (a_w + b_w f_vp/w0) d_omega``
    with the four constants of :data:`VP_CAL`, learned (least squares, no
    intercept) on physics-based simulations whose seeds are disjoint from the
    report's evaluation set (``scripts/calibrate_vp_cal.py``). The correction
    vanishes on data the nominal model explains, so ``"vp_cal"`` is as exact as
    ``"vp"`` there; the constants belong to the default nominal channel and the
    simulator's spreads. ``.std`` propagates the pair's noise covariance through
    the correction; like ``"vp"``'s it is the noise part only (the mismatch left
    after the correction, about 6 % of f_m rms on the calibration set, is not in it).

``method="auto"`` uses ``"vp_cal"`` when no ``x0`` is given (the case it was made
for) and ``"vp"`` when one is: both are unbiased on exact data whatever ``x0``
and the most robust to noise and to a wrong initial state; the thesis's
methods are there to be reproduced, and only when the initial state is known.

All public inputs and outputs are SI (s, m^3/s, 1/s, Pa s). Internally, time
is in microseconds, the states are balanced by a diagonal similarity and
each trace is divided by its RMS; nothing of this leaks out.

The package, one topic per module: :mod:`.base` (result types, the scaled model, the
windowed regression, shared helpers), :mod:`.uio` ("dt", "dt_exact", "ct" and their
options :class:`DtOptions`, :class:`DtExactOptions`, :class:`CtOptions`), :mod:`.vp`
("vp", "vp_cal", :class:`VpOptions`, :data:`VP_CAL`), :mod:`.vp_calibration` (the
"vp_cal" constants of a head: :func:`calibrate_vp_cal`, :func:`vp_cal_for`) and :mod:`.dispatch`
(:func:`estimate_fm_batch`, :func:`estimate_fm`). Input checks raise the typed errors
of :mod:`inkdiag_core.checks` (``ValueError`` subclasses).
"""

from .base import MIN_FM_SAMPLES, FmBatchEstimate, FmEstimate
from .dispatch import METHODS, OPTIONS, estimate_fm, estimate_fm_batch
from .uio import CtOptions, DtExactOptions, DtOptions
from .vp import VP_CAL, VpOptions
from .vp_calibration import calibrate_vp_cal, vp_cal_fit_seconds, vp_cal_for, vp_cal_needs_fit

__all__ = [
    "METHODS",
    "MIN_FM_SAMPLES",
    "MIN_SAMPLES",
    "OPTIONS",
    "VP_CAL",
    "CtOptions",
    "DtExactOptions",
    "DtOptions",
    "FmBatchEstimate",
    "FmEstimate",
    "VpOptions",
    "calibrate_vp_cal",
    "estimate_fm",
    "estimate_fm_batch",
    "vp_cal_for",
    "vp_cal_fit_seconds",
    "vp_cal_needs_fit",
]

MIN_SAMPLES = MIN_FM_SAMPLES
"""Former name of :data:`MIN_FM_SAMPLES`, kept for existing imports."""
