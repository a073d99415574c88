"""Benchmark of inkdiag_core.kpis.extract_kpis against two baselines measured in the same run.

    python scripts/benchmarks/kpis.py [--n 20000] [--seed 0] [--n-curve-fit 200] [--repeats 5]

- a bare ``scipy.fft.rfft`` pass over the same float32 batch (the cost floor: the
  extractor does one such pass plus the fit);
- a per-trace ``scipy.optimize.curve_fit`` of the same damped-sinusoid model on a subset,
  initialised from the FFT peak, timed and extrapolated per trace.

It also times the extractor's own spectrum pass alone (rfft, power spectrum, peak bin and
Parseval sum, in the extractor's chunks, no fit): the floor of any FFT-peak method built
from numpy calls, whose ratio bounds what the fit can reach.

Prints traces/s of each, the ratios, and the accuracy reached on the batch, so that speed
is not bought with accuracy. Single-threaded numpy/scipy defaults; best of ``--repeats``.
"""

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import scipy.fft
import scipy.optimize

try:
    from inkdiag_core import kpis as kpis_module
except ImportError:  # running from a checkout without an install
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "inkdiag_core"))
    from inkdiag_core import kpis as kpis_module

extract_kpis = kpis_module.extract_kpis

FS = 10e6
N_SAMPLES = 512


def make_batch(n, seed, n_samples=N_SAMPLES, fs=FS):
    """Seeded damped sinusoids: f_d log-uniform 150 kHz - 2.2 MHz, zeta 0.02 - 0.4,
    random phase, amplitude log-uniform 0.1 - 10, DC within +-amplitude; float32."""
    rng = np.random.default_rng(seed)
    f_d = np.exp(rng.uniform(np.log(150e3), np.log(2.2e6), n))
    zeta = rng.uniform(0.02, 0.4, n)
    phi = rng.uniform(-np.pi, np.pi, n)
    amp = np.exp(rng.uniform(np.log(0.1), np.log(10.0), n))
    dc = rng.uniform(-1.0, 1.0, n) * amp
    t = np.arange(n_samples) / fs
    w_d = 2 * np.pi * f_d
    decay = zeta * w_d / np.sqrt(1 - zeta**2)
    y = dc[:, None] + amp[:, None] * np.exp(-decay[:, None] * t) * np.cos(
        w_d[:, None] * t + phi[:, None]
    )
    return y.astype(np.float32), np.column_stack([dc, f_d, zeta, amp, phi])


def best_time(fn, repeats):
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def _model(t, dc, amp, decay, w_d, phi):
    return dc + amp * np.exp(-decay * t) * np.cos(w_d * t + phi)


def curve_fit_batch(traces, fs):
    """Per-trace baseline: FFT-peak start, then scipy.optimize.curve_fit (LM)."""
    n_samples = traces.shape[1]
    t = np.arange(n_samples) / fs
    out = np.full((len(traces), 5), np.nan)
    for i, y in enumerate(traces.astype(np.float64)):
        spec = np.abs(np.fft.rfft(y - y.mean()))
        m = int(np.argmax(spec[1:])) + 1
        w = 2 * np.pi * m * fs / n_samples
        p0 = (y.mean(), np.ptp(y) / 2, 0.1 * w, w, 0.0)
        try:
            p, _ = scipy.optimize.curve_fit(_model, t, y, p0=p0, maxfev=2000)
            out[i] = p
        except RuntimeError:
            pass
    return out


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=20000, help="traces in the batch")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--n-curve-fit", type=int, default=200, help="subset for curve_fit")
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args(argv)

    traces, truth = make_batch(args.n, args.seed)
    print(f"batch: {args.n} traces x {N_SAMPLES} samples, float32, fs = {FS / 1e6:g} MHz, "
          f"seed {args.seed}; best of {args.repeats}")

    extract_kpis(traces[:100], FS)  # warm-up
    t_ours = best_time(lambda: extract_kpis(traces, FS), args.repeats)
    t_fft = best_time(lambda: scipy.fft.rfft(traces, axis=-1), args.repeats)

    def spectrum_pass():
        for i in range(0, len(traces), kpis_module._CHUNK):
            kpis_module._peak_spectrum(traces[i : i + kpis_module._CHUNK])

    t_floor = best_time(spectrum_pass, args.repeats)
    subset = traces[: args.n_curve_fit]
    t_cf = best_time(lambda: curve_fit_batch(subset, FS), max(1, min(args.repeats, 2)))

    rate_ours = args.n / t_ours
    rate_fft = args.n / t_fft
    rate_cf = len(subset) / t_cf
    print(f"extract_kpis      : {rate_ours:12,.0f} traces/s  ({t_ours * 1e3:8.1f} ms)")
    print(f"scipy.fft.rfft    : {rate_fft:12,.0f} traces/s  ({t_fft * 1e3:8.1f} ms)")
    print(f"spectrum pass only: {args.n / t_floor:12,.0f} traces/s  ({t_floor * 1e3:8.1f} ms;"
          " rfft + |Y|^2 + peak + Parseval, no fit)")
    print(f"curve_fit/trace   : {rate_cf:12,.0f} traces/s  ({t_cf * 1e3:8.1f} ms for "
          f"{len(subset)} traces)")
    print(f"ratio ours / rfft      : {rate_ours / rate_fft:8.2f}")
    print(f"ratio spectrum pass / rfft: {t_fft / t_floor:5.2f}  (the ceiling of the ratio above "
          "with a zero-cost fit)")
    print(f"fit share of our time  : {1 - t_floor / t_ours:8.0%}")
    print(f"ratio ours / curve_fit : {rate_ours / rate_cf:8.0f}")

    kpis = extract_kpis(traces, FS)
    rel = {
        "frequency": np.abs(kpis[:, 1] / truth[:, 1] - 1),
        "damping": np.abs(kpis[:, 2] / truth[:, 2] - 1),
        "amplitude": np.abs(kpis[:, 3] / truth[:, 3] - 1),
    }
    for name, err in rel.items():
        print(f"accuracy {name:9s}: median rel err {np.median(err):.2e}, "
              f"p95 {np.percentile(err, 95):.2e}, max {err.max():.2e}")
    cf = curve_fit_batch(subset, FS)
    cf_err = np.abs(np.abs(cf[:, 3]) / (2 * np.pi) / truth[: len(subset), 1] - 1)
    cf_err = np.where(np.isfinite(cf_err), cf_err, np.inf)
    print(f"curve_fit frequency: median rel err {np.median(cf_err):.2e}, "
          f"p95 {np.percentile(cf_err, 95):.2e} (on its {len(subset)}-trace subset)")


if __name__ == "__main__":
    main()
