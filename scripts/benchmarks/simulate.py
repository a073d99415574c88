"""Benchmark of inkdiag_core.simulate against a per-trace solve_ivp baseline, same run.

    OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 python scripts/benchmarks/simulate.py \
        [--n 100000] [--n-baseline 50] [--seed 0] [--repeats 3]

- ``simulate``: all 12 classes, ``--n`` traces in total, default spreads (noise, ADC);
  best of ``--repeats``.
- baseline: the same linear model (each trace's observable-form A and input, the same
  trapezoidal pulse), integrated trace by trace with ``scipy.integrate.solve_ivp``
  (RK45, rtol 1e-8) from rest through the pulse and the sensing window, on the first
  traces of each class (``--n-baseline`` in total), timed and expressed per trace.
Prints traces/s of both, their ratio, and the largest difference between the two
(noise-free) outputs relative to each trace's peak, so that speed is not bought with
accuracy. Run single-threaded (the environment variables above) for the one-core figure.
"""

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from scipy.integrate import solve_ivp

try:
    import inkdiag_core  # noqa: F401
except ImportError:  # running from a checkout without an install
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "inkdiag_core"))

from inkdiag_core import FaultClass, simulate  # noqa: E402
from inkdiag_core.simulator import DriveWaveform, Spreads  # noqa: E402


def baseline(res, rows, drive, n_samples, fs):
    """Per-trace solve_ivp of x' = A x + B u(t); returns y (len(rows), n_samples) in m^3/s."""
    ts = drive.window_start_s
    t_eval = ts + np.arange(n_samples) / fs
    out = np.empty((len(rows), n_samples))
    for j, i in enumerate(rows):
        A = res.A[i]
        b = res.params["b"][i]
        B = np.array([0.0, -A[1, 0] * b, -A[2, 0] * b]) * res.params["drive_v"][i]

        def rhs(t, x, A=A, B=B):
            return A @ x + B * drive.u(t)

        sol = solve_ivp(rhs, (0.0, t_eval[-1]), np.zeros(3), method="RK45", rtol=1e-8,
                        atol=1e-24, t_eval=t_eval, max_step=drive.rise_s / 4)
        out[j] = sol.y[1] + sol.y[2]
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=100_000)
    ap.add_argument("--n-baseline", type=int, default=48)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)

    classes = list(FaultClass)
    per = max(1, args.n // len(classes))
    counts = {c: per for c in classes}
    n = per * len(classes)
    simulate({c: 8 for c in classes}, seed=args.seed)  # warm-up

    best = np.inf
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        res = simulate(counts, seed=args.seed)
        best = min(best, time.perf_counter() - t0)
    rate = n / best

    # baseline on a subset: the same traces without noise/ADC, so outputs can be compared
    per_b = max(1, args.n_baseline // len(classes))
    res0 = simulate({c: per_b for c in classes}, seed=args.seed, spreads=Spreads.none())
    rows = np.arange(len(res0))
    drive = DriveWaveform()
    t0 = time.perf_counter()
    y_ivp = baseline(res0, rows, drive, res0.traces.shape[1], res0.sample_rate_hz)
    t_ivp = time.perf_counter() - t0
    rate_ivp = len(rows) / t_ivp
    y_sim = res0.y_si()
    err = np.max(np.abs(y_sim - y_ivp).max(axis=1) / np.abs(y_ivp).max(axis=1))

    print(f"simulate (linear, vectorised): {n} traces x {res.traces.shape[1]} samples in "
          f"{best:.3f} s -> {rate:,.0f} traces/s (best of {args.repeats})")
    print(f"per-trace solve_ivp (RK45, rtol 1e-8): {len(rows)} traces in {t_ivp:.3f} s -> "
          f"{rate_ivp:,.1f} traces/s")
    print(f"ratio: {rate / rate_ivp:,.0f}x")
    print(f"max |simulate - solve_ivp| / peak (noise-free, {len(rows)} traces): {err:.2e}")
    print(f"target >= 100,000 traces/s on one core: {'met' if rate >= 1e5 else 'NOT met'}")


if __name__ == "__main__":
    main()
