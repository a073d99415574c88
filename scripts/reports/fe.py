"""Fault-estimation report: the thesis's section 4.4-4.5 side by side with ours.

    python scripts/reports/fe.py [--seed 0]

Writes reports/fe.md and reports/fe_*.png (one core, about a minute or two).
"""

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "inkdiag_core"))

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from inkdiag_core import (  # noqa: E402
    InkChannelModel,
    InkChannelParams,
    design_uio,
    estimate_fm_batch,
)
from inkdiag_core.estimation import VP_CAL  # noqa: E402
from inkdiag_core.fe_datasets import common_x0, nonlinear_set, synthetic_set  # noqa: E402
from inkdiag_core.nonlinear import DEFAULT_COUPLING_M3_PER_V  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import fe_dt_viscosity as dtv  # noqa: E402

FS = 10e6
STEADY = 0.2  # steady state starts at 20 % of the trace
ENV_FLOOR = 0.01  # ... and ends where the clean signal's envelope falls below 1 % of its peak


def steady_mask(y_clean, n_win=42):
    """Samples of the steady-state part: k >= 0.2 N and windowed RMS >= 1 % of its max."""
    n, N = y_clean.shape
    p = np.cumsum(np.pad(y_clean**2, ((0, 0), (n_win, 0))), axis=1)
    rms = np.sqrt((p[:, n_win:] - p[:, :-n_win]) / n_win)
    mask = rms >= ENV_FLOOR * rms.max(axis=1, keepdims=True)
    mask[:, : int(STEADY * N)] = False
    return mask


VP_CAL_VP_BASE = "vp_cal, vp reading as baseline"
"""The baseline row of what the fe node does: the nozzle's healthy raw vp reading taken off its vp_cal estimate."""


def accuracy(est, ds):
    """Per trace: 100 (1 - mean over the steady-state part of |f_hat(k) - f| / |f|)."""
    m = steady_mask(ds.y_clean) & np.isfinite(est.trace)
    rel = np.abs(est.trace - ds.fm[:, None]) / np.abs(ds.fm[:, None])
    with np.errstate(invalid="ignore"):
        a = 100 * (1 - np.where(m, rel, 0).sum(1) / np.maximum(m.sum(1), 1))
    return np.where(m.sum(1) > 0, a, np.nan)


def run(ds, method, x0, **kw):
    if method in VP_METHODS:
        kw.setdefault("vp_trace_points", 12)  # the report scores the per-sample trace too
    return estimate_fm_batch(ds.y, MODEL, FS, method=method,
                             x0=None if method in VP_METHODS else x0, **kw)


def fm_accuracy(est, ds):
    """Per trace: 100 (1 - |fm_hat - f_m| / |f_m|) of the steady-state estimate ``.fm``."""
    return 100 * (1 - np.abs(est.fm - ds.fm) / np.abs(ds.fm))


MODEL = InkChannelModel()
VP_METHODS = ("vp", "vp_cal")  # x0-free
N_PHYS = 100  # physics-based signals per dried class
N_BASELINE = 8  # healthy frames per nozzle averaged into its vp baseline


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=str(ROOT / "reports"))
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.time()
    seed = args.seed
    x0c = common_x0(MODEL)

    A, C, B_f = MODEL.observable()
    uio_ct = design_uio(A, C, B_f)
    uio_dt = design_uio(MODEL.discretize(FS), C, B_f, dt=1 / FS)

    sets = {
        "synthetic DT model (eq. 25), common x0": synthetic_set(MODEL, kind="dt", seed=seed),
        "synthetic CT exact (eq. 26, RK45), common x0": synthetic_set(MODEL, kind="ct", seed=seed),
        "synthetic CT exact, unknown x0": synthetic_set(MODEL, kind="ct", x0="random",
                                                        seed=seed + 1),
    }
    for snr in (40, 30, 20):
        sets[f"synthetic CT exact, unknown x0, {snr} dB"] = synthetic_set(
            MODEL, kind="ct", x0="random", snr_db=snr, seed=seed + 2 + snr)
    x0_given = {name: ("common", x0c) for name in sets}
    # physics-based (4.5): the simulator's nonlinear variant, all dried signals
    ph = nonlinear_set(N_PHYS, seed=seed + 100, sample_rate_hz=FS, healthy_frames=N_BASELINE)
    x0c_nl = common_x0(InkChannelModel(InkChannelParams(b=DEFAULT_COUPLING_M3_PER_V)))
    PH_COMMON = "physics-based (simulate_nonlinear), default noise"
    PH_TRUE = "physics-based (simulate_nonlinear), default noise, true x0"
    sets[PH_COMMON] = ph
    x0_given[PH_COMMON] = ("common", x0c_nl)
    sets[PH_TRUE] = ph
    x0_given[PH_TRUE] = ("true (oracle)", ph.x0)
    PH_CLEAN = "physics-based (simulate_nonlinear), noise-free, true x0"
    sets[PH_CLEAN] = dataclasses.replace(ph, y=ph.y_clean, snr_db=None)
    x0_given[PH_CLEAN] = ("true (oracle)", ph.x0)

    methods = ("dt", "dt_exact", "ct") + VP_METHODS
    results = {}
    for name, ds in sets.items():
        for m in methods:
            if name == PH_TRUE and m in VP_METHODS:
                results[name, m] = results[PH_COMMON, m]  # VP is given no x0: same run
                continue
            est = run(ds, m, x0_given[name][1])
            results[name, m] = (est, accuracy(est, ds), fm_accuracy(est, ds))
    # ours: the nozzle's own healthy reading as a baseline (what a monitor has seen of it
    # before it dried): the mean vp estimate over N_BASELINE healthy frames, subtracted
    n_ph, _, n_s = ph.y_healthy.shape
    base = run(dataclasses.replace(ph, y=ph.y_healthy.reshape(-1, n_s)), "vp", None,
               vp_trace_points=0).fm.reshape(n_ph, N_BASELINE).mean(axis=1)
    est_b = run(ph, "vp", None, baseline_fm=base)
    PH_BASE = (f"physics-based (simulate_nonlinear), default noise, per-nozzle healthy "
               f"baseline ({N_BASELINE} frames)")
    results[PH_BASE, "vp"] = (est_b, accuracy(est_b, ph), fm_accuracy(est_b, ph))
    cover_b = np.mean((est_b.ci[:, 0] <= ph.fm) & (ph.fm <= est_b.ci[:, 1])) * 100
    # the same per-nozzle baseline with vp_cal: its own healthy readings, and the raw vp readings
    # taken off it (what the fe node does: inkdiag_core.baselines.FM_METHOD)
    base_c = run(dataclasses.replace(ph, y=ph.y_healthy.reshape(-1, n_s)), "vp_cal", None,
                 vp_trace_points=0).fm.reshape(n_ph, N_BASELINE).mean(axis=1)
    est_bc = run(ph, "vp_cal", None, baseline_fm=base_c)
    results[PH_BASE, "vp_cal"] = (est_bc, accuracy(est_bc, ph), fm_accuracy(est_bc, ph))
    est_bv = run(ph, "vp_cal", None, baseline_fm=base)
    results[PH_BASE, VP_CAL_VP_BASE] = (est_bv, accuracy(est_bv, ph), fm_accuracy(est_bv, ph))
    # why vp alone stops near 95 %: the set re-drawn with one kind of spread switched off
    from inkdiag_core import FaultClass
    from inkdiag_core.nonlinear import simulate_nonlinear
    from inkdiag_core.simulator import Spreads
    ablation = {}
    for label, sp in (("all spreads (default)", Spreads()),
                      ("no temperature spread", Spreads(temperature_std_k=0.0)),
                      ("no geometry spread", Spreads(nozzle_radius_rel=0.0, nozzle_length_rel=0.0,
                                                     restrictor_radius_rel=0.0)),
                      ("no piezo spread", Spreads(actuator_compliance_rel=0.0, coupling_rel=0.0)),
                      ("no noise, no ADC", Spreads(snr_db=np.inf, adc_bits=None))):
        r = simulate_nonlinear({c: N_PHYS for c in (FaultClass.SLIGHTLY_DRIED, FaultClass.INTERMEDIATELY_DRIED,
                                                   FaultClass.DEEPLY_DRIED)},
                               seed=seed + 100, sample_rate_hz=FS, spreads=sp)
        y_si = (r.traces.astype(float) - r.sensor_offset[:, None]) / r.sensor_gain[:, None]
        ablation[label] = []
        for m in VP_METHODS:
            f_hat = estimate_fm_batch(y_si, MODEL, FS, method=m).fm
            a = 100 * (1 - np.abs(f_hat - r.fm) / np.abs(r.fm))
            ablation[label] += [np.median(a), np.percentile(a, 10)]
    name_ct = "synthetic CT exact (eq. 26, RK45), common x0"
    bare = {it: accuracy(run(sets[name_ct], "dt_exact", x0c, sensitivity=False, n_iter=it),
                         sets[name_ct]) for it in (0, 2, 3)}
    gn = {it: accuracy(run(sets[name_ct], "dt_exact", x0c, n_iter=it), sets[name_ct])
          for it in (0, 1, 2, 3)}

    # ---------------------------------------------------------------- figures
    lv = np.arange(49)
    ds_dt = sets["synthetic DT model (eq. 25), common x0"]
    ds_ct = sets["synthetic CT exact (eq. 26, RK45), common x0"]
    t_us = np.arange(ds_ct.y.shape[1]) / FS * 1e6
    for tag, ds, m, title in (("fig24_dt_trace", ds_dt, "dt", "DT approach on eq. (25) data"),
                              ("fig26_ct_trace", ds_ct, "ct", "CT approach on exact CT data")):
        est = results[[k for k in sets if sets[k] is ds][0], m][0]
        i = 24
        fig, ax = plt.subplots(2, 1, figsize=(7, 5), sharex=True)
        ax[0].plot(t_us, np.full_like(t_us, ds.fm[i]), "b", label="true f_m")
        ax[0].plot(t_us, est.trace[i], "r--", label="estimate")
        ax[0].set_ylabel("f_m (1/s)")
        ax[0].legend()
        ax[0].set_title(f"{title}, level {i} (Fig. {tag[3:5]})")
        ax[1].semilogy(t_us, np.abs(est.trace[i] - ds.fm[i]))
        ax[1].set_ylabel("|f_m - f_hat| (1/s)")
        ax[1].set_xlabel("t (us)")
        fig.tight_layout()
        fig.savefig(out / f"fe_{tag}.png", dpi=110)
        plt.close(fig)

    fig, ax = plt.subplots(figsize=(7, 4))
    for key, lab in (((list(sets)[0], "dt"), "DT on eq. (25) data (Fig. 25)"),
                     ((list(sets)[1], "ct"), "CT on exact CT data (Fig. 27)"),
                     ((list(sets)[1], "dt"), "DT on exact CT data (Appendix E bias)"),
                     ((list(sets)[1], "dt_exact"), "DT exact-discretisation (ours), exact CT data"),
                     ((list(sets)[2], "vp"), "VP, unknown x0, noise-free"),
                     (("synthetic CT exact, unknown x0, 30 dB", "vp"), "VP, unknown x0, 30 dB")):
        ax.plot(lv, results[key][1], ".-", label=lab)
    ax.axhline(99, color="k", lw=0.5)
    ax.set_xlabel("fault level (d_mu = +0.2 mu ... +10 mu)")
    ax.set_ylabel("accuracy (%)")
    ax.set_ylim(60, 100.5)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "fe_fig25_27_accuracy.png", dpi=110)
    plt.close(fig)

    fig, ax = plt.subplots(2, 2, figsize=(9, 6))
    from inkdiag_core.fe_datasets import _transition_ct  # healthy reference, same x0
    for c, axi, lab in zip((0, 1, 2), (ax[0, 0], ax[0, 1], ax[1, 0]),
                           ("slightly", "intermediately", "deeply")):
        i = int(np.flatnonzero(ph.level == c)[0])
        yh = ph.x0[i] @ _transition_ct(MODEL, 0.0, FS, ph.y.shape[1]).T
        axi.plot(t_us, yh, "b", lw=0.8, label="healthy, same x0")
        axi.plot(t_us, ph.y[i], "r", lw=0.8, label=f"{lab} dried (with noise)")
        axi.set_title(f"{lab} dried (Figs. 28/30/32)", fontsize=9)
        axi.legend(fontsize=7)
    for (nm, m), mk, lab in (((PH_COMMON, "vp"), "o", "vp (no x0)"),
                             ((PH_COMMON, "vp_cal"), "s", "vp_cal (no x0)"),
                             ((PH_CLEAN, "ct"), "x", "ct (true x0, noise-free)"),
                             ((PH_CLEAN, "dt_exact"), "^", "dt_exact (true x0, noise-free)"),
                             ((PH_COMMON, "dt_exact"), "+", "dt_exact (common x0)")):
        ax[1, 1].plot(-ph.fm, -results[nm, m][0].fm, mk, ms=3, label=lab)
    lim = [0, -ph.fm.min() * 1.1]
    ax[1, 1].plot(lim, lim, "k", lw=0.5)
    ax[1, 1].set_xlim(lim)
    ax[1, 1].set_ylim(lim)
    ax[1, 1].set_xlabel("-f_m true (1/s)")
    ax[1, 1].set_ylabel("-f_m estimated (1/s)")
    ax[1, 1].set_title(f"all {ph.fm.size} physics-based signals (Figs. 29/31/33)", fontsize=9)
    ax[1, 1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "fe_fig28_33_physics.png", dpi=110)
    plt.close(fig)

    # ---------------------------------------------------------------- markdown
    thesis = {
        ("synthetic DT model (eq. 25), common x0", "dt"): "> 99 (all levels)",
        ("synthetic CT exact (eq. 26, RK45), common x0", "ct"): "> 98 (all levels)",
        (PH_COMMON, "dt"): "92.94, 99.52 (2 selected signals)",
        (PH_COMMON, "ct"): "89.38 (1 selected signal)",
    }
    lines = []
    P = lines.append
    P("# Fault estimation (thesis 4.3-4.5): reproduction, an exact-discretisation DT estimator "
      "and an x0-free estimator")
    P("")
    P(f"Generated by `python scripts/reports/fe.py --seed {seed}`; model {MODEL!r}, "
      f"{FS / 1e6:.0f} MHz, {ds_ct.y.shape[1]} samples.")
    P("")
    P("Methods: `dt` and `ct` are the thesis's (eq. 22-25 with Appendix E's fault term "
      "`B_f x3 f_m dt`; eq. 26). `dt_exact` is ours: the same UIO + regression, but with the "
      "exact discretisation linearised in f_m, `A_d(f) ~ A_d(f0) + (f - f0) D(f0)`, `D` the "
      "Frechet derivative of `expm((A_H + f e3 e3^T) dt)`; regressor `C D x_hat(k) + C A_d "
      "dx_hat(k)/df` (the UIO's state sensitivity, see findings), first pass at f0 = 0, then 3 "
      "re-linearisations at the current estimate (Gauss-Newton). `vp`: variable projection, no "
      "x0. `vp_cal` (ours, `method=\"auto\"` without x0): vp plus a learned correction of the "
      "model mismatch (see findings); calibrated on physics-based simulations with seeds "
      f"{VP_CAL['seeds'][0]}-{VP_CAL['seeds'][1]}, disjoint from this report's (seed "
      f"{seed + 100} for the physics-based set); the uncalibrated `vp` stays beside it.")
    P("")
    P("## UIO existence (eq. 13-20), computed")
    P("")
    P("```")
    P(uio_ct.summary())
    P("")
    P(uio_dt.summary())
    P("```")
    P("")
    P("Continuous time: one zero eigenvalue of F = (I-HC)A is unobservable, so no gain makes the "
      "error stable; the CT UIO must be started from the true x0 and integrates any input error. "
      "Discrete time (eq. 25 with A_H^DT): F's non-zero eigenvalues have |lambda| = "
      f"{np.abs(uio_dt.eig_F).max():.4f} < 1, i.e. the DT UIO forgets a wrong x0 with a time "
      f"constant of {-1e6 / FS / np.log(np.abs(uio_dt.eig_F).max()):.1f} us -- but this decay "
      "comes from the O(dt^2) terms of expm(A dt), the same order as the fault effect that "
      "Appendix E drops, so it does not rescue the DT method on data it did not generate.")
    P("")
    P("## Accuracy definition")
    P("")
    P("Per trace: `100 (1 - mean_k |f_hat(k) - f_m| / |f_m|)` over the steady-state part: samples "
      f"from {int(STEADY * 100)} % of the trace on, while the clean signal's one-period RMS is at least "
      f"{int(ENV_FLOOR * 100)} % of its peak (after that the ring-down has decayed and the per-sample "
      "estimate is numerical noise). `f_hat(k)` is `.trace`: the sliding one-period least-squares "
      "estimate `e^+ r` for dt/dt_exact/ct (for dt_exact: the last linearisation point plus the "
      "windowed correction); for vp the growing-window fit on samples [0, k] (12 window ends from "
      "two periods to the full trace, interpolated), for vp_cal the same with each window's fit "
      "corrected. Negative values mean errors larger than "
      "|f_m|. Synthetic rows: median and worst over the 49 levels; physics rows: median and 10th "
      "percentile over ALL signals. The `.fm` column is the median of "
      "`100 (1 - |fm_hat - f_m| / |f_m|)` of the steady-state estimate `.fm`.")
    P("")
    P("## Side-by-side")
    P("")
    P("| dataset | method | x0 given | ours: median % | ours: worst / P10 % | ours: .fm median % "
      "| thesis % |")
    P("|---|---|---|---:|---:|---:|---|")
    for name in sets:
        for m in methods:
            est, a, afm = results[name, m]
            lo = np.nanmin(a) if name.startswith("synthetic") else np.nanpercentile(a, 10)
            th = thesis.get((name, m), "n/a")
            xg = "none" if m in VP_METHODS else x0_given[name][0]
            P(f"| {name} | {m} | {xg} | {np.nanmedian(a):.2f} | {lo:.2f} | "
              f"{np.nanmedian(afm):.2f} | {th} |")
    for m in (*VP_METHODS, VP_CAL_VP_BASE):
        _, a_m, afm_m = results[PH_BASE, m]
        P(f"| {PH_BASE} | {m} (ours) | none | {np.nanmedian(a_m):.2f} | "
          f"{np.nanpercentile(a_m, 10):.2f} | {np.nanmedian(afm_m):.2f} | n/a |")
    est_b, a_b, afm_b = results[PH_BASE, "vp"]
    P("")
    P("x0 given: `common` is the common initial state of 4.4.1 (`fe_datasets.common_x0`: "
      "`[-b u, 0, 0]` right after a 20 V stroke; for the physics-based set with the nonlinear "
      f"variant's coupling b = {DEFAULT_COUPLING_M3_PER_V:.2g} m^3/V, i.e. "
      f"[{x0c_nl[0]:.3g}, 0, 0]) -- the thesis's practice (4.4.1, 4.6); `true (oracle)` is each "
      "physics-based trace's true nonlinear state at its first sample (not available in "
      "practice; it separates the x0 problem from the model mismatch). vp is given no x0 (its "
      "and vp_cal physics rows are one run each, listed once). Thesis physics-based numbers are for hand-selected "
      "signals; ours are over all signals.")
    P("")
    P("## Findings")
    P("")
    a_dt_ct = results[name_ct, "dt"][1]
    P(f"* DT on its own eq. (25) data: {np.nanmin(results[list(sets)[0], 'dt'][1]):.3f} % worst "
      "(exact up to rounding). DT on exact continuous-time data: median "
      f"{np.nanmedian(a_dt_ct):.1f} %, worst {np.nanmin(a_dt_ct):.1f} %. This is the Appendix E "
      "approximation: expm((A_H + f_m E) dt) - expm(A_H dt) = f_m dt E + f_m dt^2 (A_H E + E A_H)/2 "
      "+ O(f_m^2 dt^2); the dt^2 terms are a fraction |A_H| dt / 2 ~ 0.075 of the retained term at "
      "10 MHz (w0 dt = 0.15), and the (f_m dt)^2 terms grow with the fault (f_m dt reaches 0.3 at "
      "+10 mu), so the bias is small only for the smallest faults.")
    a_dx = results[name_ct, "dt_exact"][1]
    P(f"* dt_exact on exact CT data, common x0: median {np.nanmedian(a_dx):.4f} %, worst "
      f"{np.nanmin(a_dx):.4f} % (target >= 99 on every level). Worst level after 0/1/2/3 "
      "re-linearisations: " + " / ".join(f"{np.nanmin(gn[i]):.2f}" for i in (0, 1, 2, 3))
      + " % (quadratic convergence; the first pass at f0 = 0 is a poor linearisation for the "
      "large faults). The regressor needs the UIO's state sensitivity: the UIO "
      "(H = B_f (C B_f)^+) cancels only the e3 component of the fault term D x, the rest (O(dt^2)) "
      "leaks into x_hat and its slow error dynamics (|lambda| = 0.987) accumulate it to the order "
      "of the fault effect itself. With the bare regressor `C D x_hat` (the plain fixed-point "
      "iteration) the worst level after 0/2/3 re-linearisations is "
      + " / ".join(f"{np.nanmin(bare[i]):.2f}" for i in (0, 2, 3)) + " % (linear convergence, "
      "about x0.5 per pass). On the thesis's own eq. (25) data dt_exact is of course biased "
      f"(median {np.nanmedian(results[list(sets)[0], 'dt_exact'][1]):.1f} %): that data is not "
      "the exact discretisation. Like dt it needs x0: with the common x0 on unknown-x0 data it "
      "fails like dt.")
    a_ct = results[name_ct, "ct"][1]
    P(f"* CT on exact CT data: median {np.nanmedian(a_ct):.2f} %, worst {np.nanmin(a_ct):.2f} % "
      "(thesis > 98 %). Its remaining error is the interpolation of the sampled output inside the "
      "marginally stable CT UIO (cubic between samples here; a linear hold gives errors of a few "
      "10 % because the UIO's zero eigenvalues integrate it).")
    a_vp = results[list(sets)[2], "vp"][1]
    a_vp30 = results["synthetic CT exact, unknown x0, 30 dB", "vp"][1]
    P(f"* VP with unknown x0 (per-sample growing-window trace): worst {np.nanmin(a_vp):.4f} % "
      f"noise-free, worst {np.nanmin(a_vp30):.2f} % / median {np.nanmedian(a_vp30):.2f} % at "
      "30 dB. Its `.trace` now shows how the estimate settles as samples arrive (fits on [0, k]); "
      "`.fm` is unchanged (the full-trace fit, = `.trace[-1]`). A sliding-window VP trace was not "
      "used: the fault is constant within one ~50 us trace, and late windows of the decayed "
      "ring-down carry little information.")
    z = (results["synthetic CT exact, unknown x0, 30 dB", "vp"][0].fm
         - sets["synthetic CT exact, unknown x0, 30 dB"].fm) \
        / results["synthetic CT exact, unknown x0, 30 dB", "vp"][0].std
    cover = np.mean(np.abs(z) < 1.96) * 100
    P(f"* VP uncertainty: at 30 dB the standardised errors have std {np.std(z):.2f} and the 95 % "
      f"CI covers the truth for {cover:.0f} % of the 49 levels.")
    P("* With the common x0 on unknown-x0 data, DT, dt_exact and CT fail (accuracies far below "
      "0): the thesis's 4.6 diagnosis, reproduced.")
    cls_names = ("slightly", "intermediately", "deeply")
    per_cls = "; ".join(
        f"{cls_names[c]}: vp {np.nanmedian(results[PH_COMMON, 'vp'][2][ph.level == c]):.1f}, "
        f"dt_exact (true x0, noisy) "
        f"{np.nanmedian(results[PH_TRUE, 'dt_exact'][2][ph.level == c]):.1f}, "
        f"ct (true x0, noise-free) {np.nanmedian(results[PH_CLEAN, 'ct'][2][ph.level == c]):.1f}"
        for c in range(3))
    P(f"* Physics-based set: `inkdiag_core.simulate_nonlinear` (branch `sim`, merged), "
      f"{N_PHYS} signals per dried class ({ph.fm.size} in all), the simulator's per-trace spreads, "
      f"drive waveform and default noise (median per-trace SNR {ph.snr_db:.1f} dB, 12-bit ADC); "
      "traces converted to m^3/s with each trace's true gain and offset. Truth f_m is the "
      "simulator's linear-model Appendix F value for the trace's nozzle-vs-ink viscosity; the "
      "estimators use the nominal healthy model (the trace's temperature and geometry spreads, "
      "meniscus stiffness and nozzle entrance loss are model mismatch, which the simulator says "
      "biases f_m by a few % of the healthy R_n / I_n). `.fm` median % per class -- " + per_cls
      + ". The common x0 is far from the state the drive pulse leaves at the first sensed sample, "
      "so dt/dt_exact/ct with the common x0 fail on every class. Given the true x0 they still "
      "fail on the noisy traces (no stabilising UIO gain exists: the CT UIO is marginal, the DT "
      "one decays with |lambda| = 0.987, so both accumulate noise and the per-trace parameter "
      "mismatch), and on the noise-free traces with the true x0 reach "
      f"median .fm accuracies of {np.nanmedian(results[PH_CLEAN, 'dt'][2]):.1f} (dt), "
      f"{np.nanmedian(results[PH_CLEAN, 'dt_exact'][2]):.1f} (dt_exact) and "
      f"{np.nanmedian(results[PH_CLEAN, 'ct'][2]):.1f} % (ct): the thesis's 89-99.5 % on "
      "selected physics-based signals is not what these methods give over all signals. VP, "
      "given nothing, is limited by the model mismatch alone (noise-free "
      f"{np.nanmedian(results[PH_CLEAN, 'vp'][2]):.1f} %, noisy "
      f"{np.nanmedian(results[PH_COMMON, 'vp'][2]):.1f} % median).")
    P(f"* Why vp alone stops near 95 % on the physics-based set, and what does better. "
      f"{ph.fm.size} signals from the same seed with one kind of spread switched off (switching "
      "a geometry or piezo spread off also shifts the later random draws, so these are "
      "comparable sets, not the same nozzles; `.fm` median / P10 %): "
      + "; ".join(f"{k} {v[0]:.2f} / {v[1]:.2f}" for k, v in ablation.items())
      + " (vp_cal on the same: "
      + "; ".join(f"{k} {v[2]:.2f} / {v[3]:.2f}" for k, v in ablation.items()) + ")"
      + ". Noise costs little; the nozzle's own piezo and geometry tolerances cost most: the "
      "nominal model cannot know them, and vp reads them as a fault. They are properties of the "
      "nozzle, not of the moment, so a monitor that has seen the nozzle healthy can remove them: "
      f"**vp with a per-nozzle healthy baseline** (the mean vp estimate over {N_BASELINE} healthy "
      "frames of the same nozzle, at the nominal ink temperature and with their own sensor "
      "noise; `estimate_fm_batch(..., baseline_fm=...)`) reaches a median of "
      f"{np.nanmedian(a_b):.2f} % (P10 {np.nanpercentile(a_b, 10):.2f} %, `.fm` median "
      f"{np.nanmedian(afm_b):.2f} %) over all {ph.fm.size} signals: the >= 95 % target, without "
      "x0. The temperature is not shared between baseline and dried trace, so what remains is "
      "the temperature spread, the nonlinearity and noise. Its 95 % CI is the fit's (noise) "
      f"interval only and covers the truth for {cover_b:.0f} % of these signals: the model "
      "mismatch left is not in it.")
    a_v, afm_v = results[PH_COMMON, "vp"][1:]
    est_c, a_c, afm_c = results[PH_COMMON, "vp_cal"]
    cover_c = np.mean((est_c.ci[:, 0] <= ph.fm) & (ph.fm <= est_c.ci[:, 1])) * 100
    a_c0 = results[PH_CLEAN, "vp_cal"][2]
    s30 = "synthetic CT exact, unknown x0, 30 dB"
    a_c30 = results[s30, "vp_cal"][1]
    z_c = (results[s30, "vp_cal"][0].fm - sets[s30].fm) / results[s30, "vp_cal"][0].std
    _, a_cb, afm_cb = results[PH_BASE, "vp_cal"]
    _, a_cv, _ = results[PH_BASE, VP_CAL_VP_BASE]
    P("* **vp_cal: vp with a learned correction of the model mismatch, no x0, no healthy "
      "history.** vp's only free parameter is f_m, so it forces the nominal model's damping-"
      "frequency relation on the ring-down; a real nozzle's pair (decay rate sigma, frequency "
      "omega) sits off that curve, and where it sits says something about the mismatch. vp_cal "
      "refits the pair freely around the vp solution (Gauss-Newton, amplitudes, the real mode and "
      "the offset projected out; 3 steps) and corrects "
      "`fm = f_vp + (a_s + b_s f_vp/w0) d_sigma + (a_w + b_w f_vp/w0) d_omega` (w0 the nominal "
      "healthy angular frequency). The four constants (`estimation.VP_CAL`: "
      f"a_s {VP_CAL['a_sigma']:.4g}, b_s {VP_CAL['b_sigma']:.4g}, a_w {VP_CAL['a_omega']:.4g}, "
      f"b_w {VP_CAL['b_omega']:.4g}) are a weighted least-squares regression of vp's relative error "
      f"on {VP_CAL['n_traces']} physics-based simulations, seeds {VP_CAL['seeds'][0]}-"
      f"{VP_CAL['seeds'][1]} (`python scripts/calibrate_vp_cal.py`), never on this report's set. "
      "No intercept, so the correction is zero on data the nominal linear model explains: on the "
      f"synthetic sets vp_cal is exact when noise-free (worst {np.nanmin(results[list(sets)[2], 'vp_cal'][1]):.4f} %) "
      f"and at 30 dB has median {np.nanmedian(a_c30):.2f} % / worst {np.nanmin(a_c30):.2f} % "
      f"(vp {np.nanmedian(a_vp30):.2f} / {np.nanmin(a_vp30):.2f} %); its standardised errors "
      f"there have std {np.std(z_c):.2f}. On the thesis's eq. (25) data (a different mismatch, "
      "Appendix E's approximation, which the correction was not learned on) it is worse than vp: "
      f"median {np.nanmedian(results[list(sets)[0], 'vp_cal'][1]):.2f} vs "
      f"{np.nanmedian(results[list(sets)[0], 'vp'][1]):.2f} %. On the physics-based set (all {ph.fm.size} signals): "
      f"median {np.nanmedian(a_c):.2f} % (P10 {np.nanpercentile(a_c, 10):.2f} %, `.fm` median "
      f"{np.nanmedian(afm_c):.2f} %) against the uncalibrated vp's {np.nanmedian(a_v):.2f} % "
      f"(P10 {np.nanpercentile(a_v, 10):.2f} %, `.fm` {np.nanmedian(afm_v):.2f} %); noise-free "
      f"`.fm` median {np.nanmedian(a_c0):.2f} %. With the per-nozzle healthy baseline as well: "
      f"median {np.nanmedian(a_cb):.2f} % (P10 {np.nanpercentile(a_cb, 10):.2f} %) with its own vp_cal "
      f"readings, {np.nanmedian(a_cv):.2f} % (P10 {np.nanpercentile(a_cv, 10):.2f} %) with the raw vp "
      "readings taken off, what the fe node does (`inkdiag_core.baselines.FM_METHOD`). Its `.std` "
      "propagates the pair's noise covariance through the correction; it does not contain the "
      "mismatch the correction leaves (about 6 % of f_m rms on the calibration set), so its 95 % "
      f"CI covers the truth for {cover_c:.0f} % of the physics-based signals. Tried first and "
      "dropped (development runs on seed 0, disjoint from this report and from the calibration; "
      "`.fm` median, vp 95.18 % there): a joint fit of f_m with a common nuisance scale on the "
      "nominal model -- stiffness (piezo compliance, both 1/(I B_t) terms) 94.13 %, ink viscosity "
      "(R_r/I_r and R_n/I_n together) 91.02 %, inertance 93.81 %: each nuisance, fitted, also "
      "absorbs the nonlinear terms' effect and moves f_m the wrong way; and dropping the first "
      "samples (where the entrance loss is largest) did not help: 94.76 / 94.43 / 95.24 / "
      "94.51 / 90.24 % for 5 / 10 / 20 / 40 / 80 samples dropped.")
    P("")
    dt_visc_section(P, out, seed)
    P("")
    P("## Figures")
    P("")
    for f in ("fe_fig24_dt_trace.png", "fe_fig26_ct_trace.png", "fe_fig25_27_accuracy.png",
              "fe_fig28_33_physics.png", "fe_dt_viscosity.png"):
        P(f"![{f}]({f})")
    P("")
    P(f"Runtime: {time.time() - t_start:.0f} s.")
    (out / "fe.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


def dt_visc_section(P, out, seed, n=40):
    """Issue 12: the thesis's DT estimator at viscosity x1.2-x6, true x0, exact CT data."""
    res = dtv.experiment(seed, n)
    dtv.figure(out / "fe_dt_viscosity.png", seed)
    lam = np.abs(dtv.uio_eigs()).max()
    F = dtv.FACTORS
    m = res["mode"]
    h_dt, h_ct = dtv.hybrid_on_eq25()

    def med(fam, k, f):
        return np.median(res[fam][f][k])

    P("## The DT estimator at high viscosity: the method, not our implementation (issue 12)")
    P("")
    P(f"Generated by `python scripts/reports/fe_dt_viscosity.py --seed {seed} --n {n}` (the same "
      "code). Data: for each viscosity factor the nozzle viscosity is `factor * mu_n`, f_m from "
      "eq. (37), and `y(k) = C expm((A + f_m e3 e3^T) dt)^k x0` with A, C from "
      "`InkChannelModel().observable()`, 10 MHz, 512 samples, noise-free: exact samples of the "
      "continuous-time model, not the thesis's eq. (25) data. The true x0 is given to every "
      f"estimator. {n} traces per factor and x0 family: **mode** -- x0 = Re(a v), v the "
      "eigenvector of the complex pair of `A + f_m e3 e3^T` scaled so its volume component is "
      "1 pL, a = U(0.5, 1.5) exp(i U(0, 2 pi)) (volume amplitude 0.5-1.5 pL, neck flows matched "
      "to the mode in amplitude and phase: one damped sinusoid); **random** -- "
      "`fe_datasets.random_x0` (volume -U(0.5, 1.5), flows N(0, 0.5) w0 times the volume) "
      "rescaled to a 1 pL volume. Accuracy 100 (1 - |f_hat / f_m - 1|) of `.fm` unless the row "
      "says otherwise; cells are median (P10) over the traces.")
    P("")
    for fam, title in (("mode", "x0 on the mode"), ("random", "random x0 (random_x0 at 1 pL)")):
        P(f"{title}:")
        P("")
        P(dtv.table(res, fam))
        P("")
    P("What each row rules out:")
    P("")
    P("* **Scaling / conditioning**: a plain SI implementation of eq. 14-19 (UIO on "
      "`A_H^DT = expm(A_H dt)`, T = F H), eq. 25 and eq. 6 with no balancing, no microsecond "
      "time and no per-trace RMS scaling gives the same estimates as `estimate_fm(method=\"dt\")` "
      "to a relative "
      f"{max(res[fam][f]['ref_vs_dt'] for fam in res for f in F):.1e} (largest over all traces).")
    P("* **Pre-filter**: the thesis's tau (eq. 5) at 1 MHz moves the medians by at most "
      f"{max(abs(med(fam, 'dt_pf', f) - med(fam, 'dt', f)) for fam in res for f in F):.1f} points.")
    P("* **Windowing / regression**: the per-sample sliding-window `.trace` scored on the report's "
      "steady-state mask collapses with `.fm`; regressing over the whole trace instead of "
      f"k >= 0.2 N only delays it (x6: {med('mode', 'dt_all', 6.0):.1f} / "
      f"{med('random', 'dt_all', 6.0):.1f} % medians). The regression itself is sound: fed the "
      "true state x(k) in place of x_hat(k), the same eq. 25 residual and regressor give "
      f"{min(med(fam, 'dt_oracle', f) for fam in res for f in F):.1f}-"
      f"{max(med(fam, 'dt_oracle', f) for fam in res for f in F):.1f} % medians at every factor "
      "(P10 >= "
      f"{min(np.percentile(res[fam][f]['dt_oracle'], 10) for fam in res for f in F):.1f} %): "
      "that few-percent loss is the Appendix E approximation's bias, and it does not grow with "
      "viscosity.")
    P("* **The discretisation of the UIO is what collapses.** x_hat(k) comes from the DT UIO "
      "(eq. 14-19) built on `A_H^DT`. It decouples the fault only along B_f = e3; on exact CT "
      "data the true step is `expm((A_H + f_m E) dt) x`, whose part beyond eq. 24, "
      "`f_m dt^2 (A_H E + E A_H)/2 + ...`, is not along e3, and after (I - HC) it drives the "
      "volume state by about `f_m dt^2 x3 / 2` per sample, which the UIO feeds into the neck "
      "flows (the unobserved direction (0, 1, -1), C = [0 1 1]). That error decays only as F's "
      f"slowest mode, |eig F_DT| = {lam:.5f} per sample ({-np.log(lam) * dtv.FS / 1e3:.0f} /ms; "
      "a discretisation artefact: in CT, F = (I - HC) A_H has a double eigenvalue 0 and never "
      f"forgets; {dtv.uio_decay(2 * dtv.FS) / 1e3:.0f} /ms at 20 MHz, "
      f"{dtv.uio_decay(4 * dtv.FS) / 1e3:.0f} /ms at 40 MHz). The ring-down decays at the rate in the last table row: "
      f"{m[1.2]['decay'] / 1e3:.0f} /ms at x1.2, slower than the UIO error, so x_hat3 stays "
      f"close; from x3 ({m[3.0]['decay'] / 1e3:.0f} /ms) on it decays much faster, the UIO error "
      "outlives the signal it estimates, and over the steady-state samples rms(x3 - x_hat3) / "
      f"rms(x3) is {med('mode', 'err_ratio', 3.0):.1f} / {med('mode', 'err_ratio', 4.0):.1f} / "
      f"{med('mode', 'err_ratio', 6.0):.1f} at x3 / x4 / x6 (mode family): the regression then "
      "reads the UIO error, not the fault (figure `fe_dt_viscosity.png`: top, |x3| and "
      "|x3 - x_hat3| at x2 / x4 / x6; middle, the per-sample estimate; bottom, x3 and x_hat3).")
    P("* **Is the DT UIO the thesis's?** Replacing it by the continuous-time UIO of section 4.3.3 "
      "(eq. 14-19 with `A_H^CT`, integrated exactly with the cubic hold of `ct`) in front of the "
      "same eq. 25 regression gives "
      f"{min(med(fam, 'dt_ctuio', f) for fam in res for f in F):.1f}-"
      f"{max(med(fam, 'dt_ctuio', f) for fam in res for f in F):.1f} % medians at every factor "
      "here -- the oracle's numbers, and the range a prototype of 91-97 % points to. But that "
      "hybrid is not the DT approach the thesis validates: on its own eq. (25) data (Fig. 24/25, "
      "errors ~1e-6, > 99 %) only the DT UIO is exact (`dt` 100.000 % on every level, row 1 of "
      "the side-by-side), while the CT UIO is not (on the 49-level eq. (25) set with random x0, "
      f"seed 3: the hybrid's median {np.median(h_ct):.1f} %, best {h_ct.max():.1f} %; the DT "
      f"UIO's worst {h_dt.min():.3f} %). So `dt` "
      "stays as the thesis specifies it and estimation.py is unchanged: the collapse at high "
      "viscosity is the DT approach's, i.e. the Appendix E approximation seen through a DT UIO "
      "whose error dynamics are slower than a strongly damped ring-down. Before = after: no code "
      "of `estimate_fm` changed. The estimators that do not make that approximation hold: `ct` "
      f"{min(med(fam, 'ct', f) for fam in res for f in F):.1f} % or better (median) at every "
      "factor; `dt_exact` (ours) is exact up to x4 but drops at x6 "
      f"({med('mode', 'dt_exact', 6.0):.1f} / {med('random', 'dt_exact', 6.0):.1f} % medians, "
      "mode / random x0) on these x0 families -- a separate finding, not investigated here.")


if __name__ == "__main__":
    main()
