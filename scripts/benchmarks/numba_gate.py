"""Would a compiled kernel (numba) earn its place on the labeller's per-row stage? Same data, same run.

    python -m venv /tmp/nb && /tmp/nb/bin/pip install numpy==2.4.6 numba==0.68.1
    OPENBLAS_NUM_THREADS=1 /tmp/nb/bin/python scripts/benchmarks/numba_gate.py

numba is not an inkdiag dependency (issue 17: a kernel goes in only if it wins >= 2x on its
stage), so this runs in a scratch environment with numpy and numba alone. The numpy side
mirrors the passes ``inkdiag_core.screen_traces`` (max, min, the run counts at them) and
``HealthyGate.screen`` (three row-wise products: trace x reference, trace x trace, sum) make
on every row of a frame; the numba side fuses them into one loop per row (two passes over
its samples), without and with ``fastmath`` (which lets LLVM vectorise the reductions but
assumes no NaN, so it could not keep screening's non-finite check as written). Rows: 200 (one
message) and 1,600 (the 8 messages of one classifier pass under load), 512 float32 samples,
simulated damped sinusoids plus noise.
"""

import sys
import time

import numpy as np

try:
    import numba
except ImportError:
    sys.exit("numba_gate: needs numba (not an inkdiag dependency); see the module docstring for a scratch venv")



def frame(n=1600, m=512, seed=0):
    """``n`` traces (damped 237 kHz sinusoids of random amplitude plus noise, float32) and references."""
    rng = np.random.default_rng(seed)
    t = np.arange(m) / 10e6
    ring = np.exp(-0.07 * 2 * np.pi * 237e3 * t) * np.cos(2 * np.pi * 237e3 * t)
    x = (ring * rng.uniform(0.5, 1.5, (n, 1)) + 0.01 * rng.standard_normal((n, m))).astype(np.float32)
    return x, x[rng.permutation(n)].copy()


def numpy_screen(x, clip_run=5, max_abs=10.0):
    """screen_traces' passes: max, min, the samples at each, counted."""
    hi, lo = x.max(axis=1), x.min(axis=1)
    finite = np.isfinite(hi) & np.isfinite(lo)
    flat = finite & ((hi.astype(np.float64) - lo) <= 1e-6)
    out = finite & ((hi > max_abs) | (lo < -max_abs))
    at_hi, at_lo = x == hi[:, None], x == lo[:, None]
    clip = ((np.add.reduce(at_hi.view(np.uint8), axis=1, dtype=np.uint16) >= clip_run)
            | (np.add.reduce(at_lo.view(np.uint8), axis=1, dtype=np.uint16) >= clip_run))
    return finite, flat, out, clip


def numpy_gate(x, r):
    """HealthyGate.screen's passes: row-wise trace x reference, trace x trace, sum."""
    xr = np.matmul(x[:, None, :], r[:, :, None]).reshape(-1).astype(np.float64)
    xx = np.matmul(x[:, None, :], x[:, :, None]).reshape(-1).astype(np.float64)
    return xr, xx, x.sum(axis=1).astype(np.float64)


def _fused(x, r, clip_run, max_abs):
    n, m = x.shape
    finite, flat = np.empty(n, np.bool_), np.empty(n, np.bool_)
    out, clip = np.empty(n, np.bool_), np.empty(n, np.bool_)
    xr, xx, x1 = np.empty(n), np.empty(n), np.empty(n)
    for i in range(n):
        hi, lo, s, ss, sr, fin = -np.inf, np.inf, 0.0, 0.0, 0.0, True
        for j in range(m):
            v = x[i, j]
            if not np.isfinite(v):
                fin = False
            hi = max(hi, v)
            lo = min(lo, v)
            s += v
            ss += v * v
            sr += v * r[i, j]
        n_hi = n_lo = 0
        for j in range(m):
            n_hi += x[i, j] == hi
            n_lo += x[i, j] == lo
        finite[i], flat[i] = fin, fin and (hi - lo) <= 1e-6
        out[i], clip[i] = fin and (hi > max_abs or lo < -max_abs), n_hi >= clip_run or n_lo >= clip_run
        xr[i], xx[i], x1[i] = sr, ss, s
    return finite, flat, out, clip, xr, xx, x1


def best(f, k=200):
    """Best of 5 mean times of ``k`` calls, s."""
    b = np.inf
    for _ in range(5):
        t0 = time.perf_counter()
        for _ in range(k):
            f()
        b = min(b, (time.perf_counter() - t0) / k)
    return b


def main():
    x, ref = frame()
    for fastmath in (False, True):
        fused = numba.njit(fastmath=fastmath)(_fused)
        t0 = time.perf_counter()
        got = fused(x, ref, 5, 10.0)
        print(f"fastmath={fastmath}: compile and first call {time.perf_counter() - t0:.2f} s; screening flags equal "
              f"numpy's: {all(np.array_equal(a, b) for a, b in zip(got[:4], numpy_screen(x)))}")
        for rows in (200, 1600):
            xs, rs = x[:rows], ref[:rows]
            a = best(lambda: (numpy_screen(xs), numpy_gate(xs, rs)))
            b = best(lambda: fused(xs, rs, 5, 10.0))
            print(f"  {rows} rows: numpy screen+gate {1e3 * a:.3f} ms, numba fused {1e3 * b:.3f} ms, "
                  f"numpy / numba {a / b:.2f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
