"""The thesis's DT estimator at high viscosity: the method or our implementation? (issue 12)

    python scripts/reports/fe_dt_viscosity.py [--seed 0] [--n 40]

Prints DT and CT accuracy per viscosity factor 1.2/1.5/2/3/4/6 on exact continuous-time
data with the true x0 given, and the diagnostics that locate the collapse at high
viscosity. ``scripts/reports/fe.py`` calls :func:`experiment` and :func:`figure` for its
section of ``reports/fe.md``.

Data (seeded, noise-free): for each factor, ``mu_n -> factor * mu_n``, ``f_m`` from eq. (37)
(``viscosity_to_fm``), ``A_f = A + f_m e3 e3^T`` from ``InkChannelModel().observable(f_m)``
and ``y(k) = C expm(A_f dt)^k x0`` (dt = 0.1 us, 512 samples): exact samples of the
continuous-time model (eq. 26), not of the thesis's eq. (25) approximation. Two x0 families,
``n`` traces each per factor, the true x0 given to the estimators:

* ``"mode"``: on the faulty model's oscillatory mode: ``x0 = Re(a v)`` with ``v`` the
  eigenvector of ``A_f`` of the complex pair, scaled so its volume component is 1 pL
  (``v[0] = 1e-15 m^3``), and ``a = U(0.5, 1.5) exp(i U(0, 2 pi))``: volume amplitude
  0.5-1.5 pL, the neck flows matched to the mode (amplitude and phase), so the trace is
  one damped sinusoid.
* ``"random"``: ``fe_datasets.random_x0`` (volume ``-U(0.5, 1.5)``, flows ``N(0, 0.5) w0``
  times the volume scale) rescaled to a 1 pL volume scale (the data are linear in x0,
  so the scale itself does not change any estimate).
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "inkdiag_core"))

import numpy as np  # noqa: E402
import scipy.linalg as sla  # noqa: E402

from inkdiag_core import InkChannelModel, estimate_fm_batch, viscosity_to_fm  # noqa: E402
from inkdiag_core.fe_datasets import PULSE_V, random_x0  # noqa: E402

FS = 10e6
N_SAMPLES = 512
FACTORS = (1.2, 1.5, 2.0, 3.0, 4.0, 6.0)
VOLUME_M3 = 1e-15  # 1 pL
STEADY = 0.2  # .fm regresses over samples >= 0.2 N (estimate_fm's default steady_frac)
MODEL = InkChannelModel()


# ---------------------------------------------------------------------------- data
def mode_x0(fm, n, rng):
    """Initial states on ``A_f``'s oscillatory mode, volume amplitude 0.5-1.5 pL, shape (n, 3)."""
    A, _, _ = MODEL.observable(fm)
    lam, V = np.linalg.eig(A)
    v = V[:, int(np.argmax(lam.imag))]
    v = v / v[0] * VOLUME_M3
    a = rng.uniform(0.5, 1.5, n) * np.exp(1j * rng.uniform(0, 2 * np.pi, n))
    return (a[:, None] * v[None, :]).real


def exact_states(fm, X0, n_samples=N_SAMPLES):
    """States ``x(k) = expm(A_f dt)^k x0``, shape (n_samples, n, 3) (exact CT samples)."""
    A, _, _ = MODEL.observable(fm)
    AdT = sla.expm(A / FS).T
    X = np.empty((n_samples,) + X0.shape)
    x = X0.copy()
    for k in range(n_samples):  # vectorised over traces
        X[k] = x
        x = x @ AdT
    return X


def dataset(factor, family, n, rng):
    """(fm, x0 (n, 3), states (N, n, 3), y (n, N)) for one viscosity factor."""
    p = MODEL.params
    fm = float(viscosity_to_fm(p, p.mu_n * factor))
    if family == "mode":
        X0 = mode_x0(fm, n, rng)
    else:
        X0 = random_x0(MODEL, n, rng) * (VOLUME_M3 / (p.b * PULSE_V))
    X = exact_states(fm, X0)
    C = MODEL.observable()[1].ravel()
    return fm, X0, X, (X @ C).T


# ---------------------------------------------------------------- SI reference
def dt_reference(Y, X0, X_true=None, *, steady=STEADY):
    """Plain SI implementation of eq. (14)-(19), (25), (6), no scaling of any kind.

    ``A_H^DT = expm(A_H dt)``; ``H = B_f (C B_f)^+``, ``F = (I - HC) A_H^DT``,
    ``T = F H`` (eq. 19); ``z(0) = x0 - H y(0)``; ``x_hat = z + H y``;
    ``r(k) = y(k+1) - C A_H^DT x_hat(k)``, ``e(k) = x_hat3(k) dt``;
    ``f = sum e r / sum e^2`` over ``k >= steady N``. With ``X_true`` (N, n, 3) the
    regression uses the true state instead of ``x_hat`` (an oracle UIO).
    Returns (f (n,), x_hat (N, n, 3)).
    """
    A, C, B_f = MODEL.observable()
    C = C.ravel()
    dt = 1.0 / FS
    Ad = sla.expm(A * dt)
    H = B_f.ravel() / float(C @ B_f.ravel())
    F = (np.eye(3) - np.outer(H, C)) @ Ad
    T = F @ H
    n, N = Y.shape
    Xh = np.empty((N, n, 3))
    z = X0 - Y[:, :1] * H
    for k in range(N):
        Xh[k] = z + Y[:, k:k + 1] * H
        z = z @ F.T + Y[:, k:k + 1] * T
    Xr = Xh if X_true is None else X_true
    r = Y[:, 1:] - (Xr[:-1] @ (C @ Ad)).T
    e = Xr[:-1, :, 2].T * dt
    k0 = int(steady * N)
    return np.sum(e[:, k0:] * r[:, k0:], 1) / np.sum(e[:, k0:] ** 2, 1), Xh


def ct_uio_states(Y, X0):
    """x_hat (N, n, 3) from the thesis's continuous-time UIO (section 4.3.3, eq. 14-19 with
    ``A_H^CT``: ``F = (I - HC) A``, ``T = F H``), ``z' = F z + T y`` integrated exactly with
    ``y`` held as the cubic through 4 neighbouring samples (the hold of the "ct" method,
    ``estimation.uio.cubic_hold``). On exact CT data its only error is that of the hold: the
    fault enters along ``B_f`` and is decoupled exactly."""
    from inkdiag_core.estimation.uio import cubic_hold

    A, C, B_f = MODEL.observable()
    C = C.ravel()
    H = B_f.ravel() / float(C @ B_f.ravel())
    F = (np.eye(3) - np.outer(H, C)) @ A
    Phi, Gam = cubic_hold(F, F @ H, 1.0 / FS)
    n, N = Y.shape
    Xh = np.empty((N, n, 3))
    z = X0 - Y[:, :1] * H
    for k in range(N):
        Xh[k] = z + Y[:, k:k + 1] * H
        if k + 1 < N:
            j0 = min(max(k - 1, 0), N - 4)
            z = z @ Phi.T + Y[:, j0:j0 + 4] @ Gam[k - j0]
    return Xh


def uio_eigs(sample_rate_hz=FS):
    """Eigenvalues of the DT UIO's F = (I - HC) expm(A_H dt) (per sample), shape (3,)."""
    A, C, B_f = MODEL.observable()
    H = B_f.ravel() / float((C @ B_f).item())
    return np.linalg.eigvals((np.eye(3) - np.outer(H, C.ravel())) @ sla.expm(A / sample_rate_hz))


def uio_decay(sample_rate_hz=FS):
    """Slowest decay rate of the DT UIO's error, 1/s: ``-ln max|eig F| * sample rate``."""
    return float(-np.log(np.abs(uio_eigs(sample_rate_hz)).max()) * sample_rate_hz)


def slowest_decay(fm):
    """Slowest decay rate of the ring-down, 1/s (min over the eigenvalues of A_f of -Re)."""
    return float(-np.linalg.eigvals(MODEL.observable(fm)[0]).real.max())


def steady_mask(y, n_win=42, floor=0.01):
    """The fe report's steady state: k >= 0.2 N and windowed RMS >= 1 % of its max."""
    n, N = y.shape
    pc = np.cumsum(np.pad(y**2, ((0, 0), (n_win, 0))), axis=1)
    rms = np.sqrt((pc[:, n_win:] - pc[:, :-n_win]) / n_win)
    m = rms >= floor * rms.max(axis=1, keepdims=True)
    m[:, : int(STEADY * N)] = False
    return m


def acc(f_hat, fm):
    return 100 * (1 - np.abs(np.asarray(f_hat) / fm - 1))


def trace_acc(trace, y, fm):
    """Per trace: 100 (1 - mean |f_hat(k)/f - 1|) over the steady mask (the report's metric)."""
    m = steady_mask(y) & np.isfinite(trace)
    rel = np.where(m, np.abs(trace / fm - 1), 0).sum(1) / np.maximum(m.sum(1), 1)
    return 100 * (1 - rel)


# ---------------------------------------------------------------- experiment
VARIANTS = (
    ("dt", "`dt` (`estimate_fm`, `.fm`)"),
    ("dt_trace", "`dt` per-sample `.trace`, report metric"),
    ("dt_ref", "SI reference of eq. 14-19/25/6, no scaling"),
    ("dt_pf", "`dt` with the pre-filter tau at 1 MHz"),
    ("dt_all", "`dt` regressed over the whole trace (steady_frac 0)"),
    ("dt_ctuio", "eq. 25 regression, x_hat from the CT UIO (eq. 14-19, A_H^CT)"),
    ("dt_oracle", "eq. 25 regression with the true x(k) for x_hat(k)"),
    ("ct", "`ct` (`.fm`)"),
    ("dt_exact", "`dt_exact` (ours, `.fm`)"),
)


def experiment(seed=0, n=40, families=("mode", "random")):
    """Accuracies (%) and diagnostics per family and factor.

    Returns dict ``res[family][factor]`` with, per variant key of :data:`VARIANTS`, the
    per-trace accuracies (n,), plus ``"err_ratio"``: per trace the RMS of the UIO error
    ``x3 - x_hat3`` over the RMS of ``x3`` on samples ``>= 0.2 N``; ``"ref_vs_dt"``: the
    largest relative difference between the SI reference and ``estimate_fm``'s ``dt``.
    """
    rng = np.random.default_rng(seed)
    res = {}
    for fam in families:
        res[fam] = {}
        for fac in FACTORS:
            fm, X0, X, Y = dataset(fac, fam, n, rng)
            row = {}
            est = estimate_fm_batch(Y, MODEL, FS, method="dt", x0=X0)
            row["dt"] = acc(est.fm, fm)
            row["dt_trace"] = trace_acc(est.trace, Y, fm)
            f_ref, Xh = dt_reference(Y, X0)
            row["dt_ref"] = acc(f_ref, fm)
            row["ref_vs_dt"] = float(np.max(np.abs(f_ref / est.fm - 1)))
            row["dt_pf"] = acc(estimate_fm_batch(Y, MODEL, FS, method="dt", x0=X0,
                                                 prefilter_hz=1e6).fm, fm)
            row["dt_all"] = acc(estimate_fm_batch(Y, MODEL, FS, method="dt", x0=X0,
                                                  steady_frac=0.0).fm, fm)
            row["dt_ctuio"] = acc(dt_reference(Y, X0, X_true=ct_uio_states(Y, X0))[0], fm)
            row["dt_oracle"] = acc(dt_reference(Y, X0, X_true=X)[0], fm)
            row["ct"] = acc(estimate_fm_batch(Y, MODEL, FS, method="ct", x0=X0).fm, fm)
            row["dt_exact"] = acc(estimate_fm_batch(Y, MODEL, FS, method="dt_exact", x0=X0).fm, fm)
            k0 = int(STEADY * N_SAMPLES)
            err = X[k0:, :, 2] - Xh[k0:, :, 2]
            row["err_ratio"] = np.sqrt(np.mean(err**2, 0) / np.mean(X[k0:, :, 2] ** 2, 0))
            row["fm"] = fm
            row["decay"] = slowest_decay(fm)
            res[fam][fac] = row
    return res


def hybrid_on_eq25(seed=3):
    """Accuracies (%) of the eq. 25 regression fed by the CT UIO on the thesis's own eq. (25)
    data (``synthetic_set(kind="dt", x0="random")``, 49 levels): (DT UIO, CT UIO) (49,) each."""
    from inkdiag_core.fe_datasets import synthetic_set

    ds = synthetic_set(MODEL, kind="dt", x0="random", n_levels=49, seed=seed)
    a_dt = acc(dt_reference(ds.y, ds.x0)[0], ds.fm)
    a_ct = acc(dt_reference(ds.y, ds.x0, X_true=ct_uio_states(ds.y, ds.x0))[0], ds.fm)
    return a_dt, a_ct


def table(res, fam, keys=None):
    """Markdown table: variant x factor, median (P10) accuracy in %."""
    keys = keys or [k for k, _ in VARIANTS]
    names = dict(VARIANTS)
    head = "| | " + " | ".join(f"x{f:g}" for f in FACTORS) + " |"
    lines = [head, "|" + "---|" * (len(FACTORS) + 1)]
    for k in keys:
        cells = [f"{np.median(res[fam][f][k]):.1f} ({np.percentile(res[fam][f][k], 10):.1f})"
                 for f in FACTORS]
        lines.append(f"| {names[k]} | " + " | ".join(cells) + " |")
    cells = [f"{np.median(res[fam][f]['err_ratio']):.2f}" for f in FACTORS]
    lines.append("| UIO error rms(x3 - x_hat3) / rms(x3), k >= 0.2 N (median) | "
                 + " | ".join(cells) + " |")
    cells = [f"{res[fam][f]['decay'] / 1e3:.0f}" for f in FACTORS]
    lines.append("| slowest ring-down decay rate (1/ms) | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def figure(path, seed=0):
    """Per-sample picture at x2 / x4 / x6 (one mode-x0 trace each, the same phase)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    lam_F = np.abs(uio_eigs()).max()
    fig, ax = plt.subplots(3, 1, figsize=(7.5, 8.5), sharex=True)
    t_us = np.arange(N_SAMPLES) / FS * 1e6
    for fac, col in ((2.0, "C0"), (4.0, "C1"), (6.0, "C3")):
        rng = np.random.default_rng(seed)
        fm, X0, X, Y = dataset(fac, "mode", 1, rng)
        _, Xh = dt_reference(Y, X0)
        s = np.abs(X[:, 0, 2]).max()
        ax[0].semilogy(t_us, np.abs(X[:, 0, 2]) / s, color=col, lw=0.8, label=f"|x3|, x{fac:g}")
        ax[0].semilogy(t_us, np.abs(X[:, 0, 2] - Xh[:, 0, 2]) / s, color=col, lw=0.8, ls="--",
                       label=f"|x3 - x_hat3| (UIO error), x{fac:g}")
        est = estimate_fm_batch(Y, MODEL, FS, method="dt", x0=X0)
        ax[1].plot(t_us, est.trace[0] / fm, color=col, lw=0.8, label=f"x{fac:g}")
        ax[2].plot(t_us, X[:, 0, 2] / s, color=col, lw=0.6, label=f"x3, x{fac:g}")
        ax[2].plot(t_us, Xh[:, 0, 2] / s, color=col, lw=0.6, ls=":")
    ax[0].semilogy(t_us, 0.05 * lam_F ** np.arange(N_SAMPLES), "k", lw=0.6,
                   label=f"|eig F_DT|^k = {lam_F:.4f}^k")
    ax[0].axvline(STEADY * N_SAMPLES / FS * 1e6, color="gray", lw=0.5)
    ax[0].set_ylim(1e-8, 2)
    ax[0].set_ylabel("relative to max |x3|")
    ax[0].legend(fontsize=6, ncol=2)
    ax[0].set_title("exact CT data, true x0: the DT UIO's error vs the state it estimates", fontsize=9)
    ax[1].axhline(1, color="k", lw=0.5)
    ax[1].axvline(STEADY * N_SAMPLES / FS * 1e6, color="gray", lw=0.5)
    ax[1].set_ylim(-1, 2)
    ax[1].set_ylabel("dt .trace / f_m")
    ax[1].legend(fontsize=7)
    ax[2].set_ylabel("x3 (solid), x_hat3 (dotted)")
    ax[2].set_xlabel("t (us)")
    ax[2].set_xlim(0, 30)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--n", type=int, default=40, help="traces per factor and x0 family")
    args = ap.parse_args(argv)
    res = experiment(args.seed, args.n)
    print(f"|eig F_DT| = {np.abs(uio_eigs())}")
    for fam in res:
        print(f"\nx0 family {fam!r}, {args.n} traces per factor, seed {args.seed}: "
              "median (P10) accuracy %")
        print(table(res, fam))
        print("max |f_ref / f_dt - 1|:", max(res[fam][f]["ref_vs_dt"] for f in FACTORS))
    a_dt, a_ct = hybrid_on_eq25()
    print(f"\neq. (25) data, random x0, 49 levels: DT UIO min {a_dt.min():.4f} %; "
          f"CT UIO (hybrid) median {np.median(a_ct):.1f} %, best {a_ct.max():.1f} %")


if __name__ == "__main__":
    main()
