"""Throughput of the f_m estimators on one core, with a baseline measured in the same run.

    python scripts/benchmarks/fe.py [--n 4000]

Baseline: a per-trace scipy.optimize.least_squares fit of (f_m, x0, offset)
started from the healthy model (what one would write without variable projection).
"""

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_v] = "1"

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "inkdiag_core"))

import numpy as np  # noqa: E402
from scipy.optimize import least_squares  # noqa: E402

from inkdiag_core import InkChannelModel, estimate_fm_batch  # noqa: E402
from inkdiag_core.fe_datasets import synthetic_set  # noqa: E402


def _baseline(y, model, fs):
    """Per-trace nonlinear least squares on (f_m, x0, offset) in scaled units."""
    N = y.size
    c = np.sqrt(np.mean(y**2))
    s = np.array([1e-6, 1.0, 1.0]) * c  # volumes ~ flow * 1 us

    def model_y(theta):
        fm = theta[0] * 1e6
        Ad = model.discretize(fs, fm)
        x = theta[1:4] * s
        out = np.empty(N)
        for k in range(N):
            out[k] = x[1] + x[2]
            x = Ad @ x
        return out / c + theta[4]

    th0 = np.array([0.0, -1.0, 0.0, 0.0, 0.0])
    sol = least_squares(lambda th: model_y(th) - y / c, th0, method="lm")
    return sol.x[0] * 1e6


def _rate(fn, n, repeat=1):
    """Traces per second, best of ``repeat`` runs (the first run also warms memory)."""
    best = np.inf
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return n / best


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--n", type=int, default=4900, help="traces per timed batch")
    ap.add_argument("--n-baseline", type=int, default=10)
    args = ap.parse_args(argv)
    model = InkChannelModel()
    fs = 10e6
    reps = max(1, args.n // 49)
    ds = synthetic_set(model, kind="ct", x0="random", n_per_level=reps, snr_db=40, seed=0)
    Y, X0, fm = ds.y, ds.x0, ds.fm
    n = Y.shape[0]
    estimate_fm_batch(Y[:49], model, fs, method="vp")  # warm the grid cache
    r_dt = _rate(lambda: estimate_fm_batch(Y, model, fs, method="dt", x0=X0), n, 3)
    r_ct = _rate(lambda: estimate_fm_batch(Y, model, fs, method="ct", x0=X0), n, 3)
    res = {}
    r_vp = _rate(lambda: res.__setitem__("vp", estimate_fm_batch(Y, model, fs, method="vp")), n, 3)
    r_vc = _rate(lambda: res.__setitem__("vp_cal", estimate_fm_batch(Y, model, fs, method="vp_cal")),
                 n, 3)
    nb = args.n_baseline
    idx = np.linspace(0, n - 1, nb).astype(int)
    bl = []
    r_bl = _rate(lambda: bl.extend(_baseline(Y[i], model, fs) for i in idx), nb)
    acc_vp = 100 * (1 - np.median(np.abs(res["vp"].fm / fm - 1)))
    acc_vc = 100 * (1 - np.median(np.abs(res["vp_cal"].fm / fm - 1)))
    acc_bl = 100 * (1 - np.median(np.abs(np.array(bl) / fm[idx] - 1)))
    print(f"traces: {n} (random x0, 40 dB SNR), one core, best of 3 batches")
    print(f"dt  (thesis, needs x0)        {r_dt:10.0f} traces/s")
    print(f"ct  (thesis, needs x0)        {r_ct:10.0f} traces/s")
    print(f"vp  (x0-free)                 {r_vp:10.0f} traces/s  median accuracy {acc_vp:.2f} %")
    print(f"vp_cal (x0-free, auto)        {r_vc:10.0f} traces/s  median accuracy {acc_vc:.2f} %")
    print(f"baseline least_squares/trace  {r_bl:10.1f} traces/s  median accuracy {acc_bl:.2f} %")
    print(f"ratios vs baseline: dt {r_dt / r_bl:.0f}x, vp {r_vp / r_bl:.0f}x, "
          f"vp_cal {r_vc / r_bl:.0f}x")
    print(f"targets: dt >= 10000 traces/s: {'met' if r_dt >= 1e4 else 'NOT met'}; "
          f"vp >= 1000 traces/s: {'met' if r_vp >= 1e3 else 'NOT met'}; "
          f"vp_cal >= 1000 traces/s: {'met' if r_vc >= 1e3 else 'NOT met'}")


if __name__ == "__main__":
    main()
