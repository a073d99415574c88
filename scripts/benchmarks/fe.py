"""Throughput of the f_m estimators on one core, with a baseline measured in the same run.

    python scripts/benchmarks/fe.py [--n 4000]

Baseline: a per-trace scipy.optimize.least_squares fit of (f_m, x0, offset)
started from the healthy model (what one would write without variable projection).

Per-call cost of small batches (the fe node's case: a frame's few drying nozzles):
time per call of "vp" and "vp_cal" on 1, 2, 8 and 64 traces, against the estimator
of an older commit (``--old-ref``, extracted with ``git archive`` into a temporary
directory and imported as its own package), measured in the same run and checked
to give the same bits.

Per frame of the fe node (``--tracker-only``, or before the rest): CPU time of
``DryingTracker.add_traces`` + ``add_drying`` for one 1,024-row frame of the soak's
head (5 % random faults, nozzles 40 and 600 drying) with its two drying rows, this
tree against ``--tracker-ref`` (default: main before the soak-12 changes), same run,
calls interleaved, estimates checked bit-identical.
"""

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_v] = "1"

import argparse  # noqa: E402
import importlib  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tarfile  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "inkdiag_core"))

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


def _old_package(ref, tmp):
    """The ``inkdiag_core`` of commit ``ref``, imported as package ``inkdiag_core_<ref>``."""
    tar = Path(tmp) / "old.tar"
    with open(tar, "wb") as fh:
        subprocess.run(["git", "-C", str(ROOT), "archive", ref, "inkdiag_core/inkdiag_core"],
                       stdout=fh, check=True)
    with tarfile.open(tar) as tf:
        tf.extractall(tmp, filter="data")
    name = f"inkdiag_core_{ref.replace('-', '_').replace('.', '_')}"
    (Path(tmp) / "inkdiag_core" / "inkdiag_core").rename(Path(tmp) / name)
    sys.path.insert(0, tmp)
    return importlib.import_module(name)


def _old_estimator(ref, tmp):
    """``estimate_fm_batch`` of commit ``ref`` and that package's default ``InkChannelModel()``."""
    pkg = _old_package(ref, tmp)
    return pkg.estimate_fm_batch, pkg.InkChannelModel()


def _per_call(fn, repeat):
    """CPU seconds of this process per call, best of ``repeat`` batches of 10 calls (the
    first call warms caches). CPU time, not wall time: on a shared machine waiting for a
    core is not the estimator's cost (one BLAS thread: this process's time is the work)."""
    fn()
    calls = 10
    best = np.inf
    for _ in range(repeat):
        t = time.process_time()
        for _ in range(calls):
            fn()
        best = min(best, (time.process_time() - t) / calls)
    return best


def small_batches(Y, model, fs, ref, sizes=(1, 2, 8, 64), repeat=7):
    """Per-call ms of "vp"/"vp_cal" now and at commit ``ref``, same run; same bits?"""
    with tempfile.TemporaryDirectory() as tmp:
        old, old_model = _old_estimator(ref, tmp)
        print(f"CPU ms per call (best of {repeat} x 10 calls), this tree vs {ref}:")
        for method in ("vp", "vp_cal"):
            for n in sizes:
                y = Y[:n]
                a, b = estimate_fm_batch(y, model, fs, method=method), old(y, old_model, fs, method=method)
                same = all(np.array_equal(getattr(a, f), getattr(b, f), equal_nan=True)
                           for f in ("fm", "std", "x0", "offset", "trace"))
                t_new = _per_call(lambda: estimate_fm_batch(y, model, fs, method=method), repeat)
                t_old = _per_call(lambda: old(y, old_model, fs, method=method), repeat)
                print(f"  {method:6s} {n:3d} traces  {1e3 * t_new:7.2f} vs {1e3 * t_old:7.2f}  "
                      f"ratio {t_old / t_new:4.2f}x  {'bit-identical' if same else 'DIFFERENT'}")


def _soak_frames(n_frames=8):
    """Frames (float32 (1024, 512), V) of the soak's head at times spread over its drying."""
    from inkdiag_core.simulation.scenario import HeadScenario, simulate_head

    sc = HeadScenario(n_nozzles=1024, random_fault_fraction=0.05, drying_nozzles=[40, 600],
                      drying_duration_s=60.0, seed=0)
    rng = np.random.default_rng(1)
    out = []
    for t in np.linspace(1.0, 120.0, n_frames):
        classes, mu = sc.at(float(t))
        out.append(simulate_head(classes, mu, sample_rate_hz=10e6, n_samples=512, head_seed=[0, 1],
                                 rng=rng)[0])
    return out


def tracker_frames(ref, repeat=7, calls=40):
    """CPU ms per frame of DryingTracker.add_traces + add_drying, this tree vs ``ref``."""
    from inkdiag_core import DryingTracker

    frames = _soak_frames()
    with tempfile.TemporaryDirectory() as tmp:
        old = _old_package(ref, tmp)
        trackers = {"this tree": DryingTracker(), ref: old.DryingTracker()}
        fid = {k: 0 for k in trackers}

        def frame(key):
            tr, i = trackers[key], fid[key]
            fid[key] += 1
            tr.add_traces(frames[i % len(frames)], first_nozzle=0, frame_id=i, stamp=0.1 * i,
                          sample_rate_hz=10e6)
            return tr.add_drying(i, [40, 600], first_nozzle=0, n_nozzles=1024)

        outs = {k: [frame(k)[0] for _ in range(len(frames))] for k in trackers}  # warm; results
        same = all(np.array_equal(a.columns[c], b.columns[c], equal_nan=True)
                   for a, b in zip(*outs.values()) for c in a.columns)
        fm_a, fm_b = (np.concatenate([r.columns["fm"] for r in rs]) for rs in outs.values())
        rel = float(np.nanmax(np.abs(fm_a / fm_b - 1))) if fm_a.size else 0.0
        best = {k: np.inf for k in trackers}
        for _ in range(repeat):  # interleaved: both see the same machine
            for k in trackers:
                t = time.process_time()
                for _ in range(calls):
                    frame(k)
                best[k] = min(best[k], (time.process_time() - t) / calls)
    new, old_t = best["this tree"], best[ref]
    print(f"DryingTracker, one 1,024-row frame with 2 drying rows (add_traces + add_drying), CPU ms "
          f"per frame, best of {repeat} x {calls}: this tree {1e3 * new:.2f}, {ref} {1e3 * old_t:.2f}, "
          f"ratio {old_t / new:.2f}x; estimates {'bit-identical' if same else f'differ: f_m by {rel:.1e} relative at most'}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--n", type=int, default=4900, help="traces per timed batch")
    ap.add_argument("--n-baseline", type=int, default=10)
    ap.add_argument("--old-ref", default="34832dd",
                    help="commit whose estimator the small-batch per-call times compare with "
                    "(default: before the per-call cost cut)")
    ap.add_argument("--small-only", action="store_true", help="only the small-batch comparison")
    ap.add_argument("--tracker-ref", default="c137b1d",
                    help="commit whose DryingTracker the per-frame times compare with (default: main "
                    "before the soak-12 changes)")
    ap.add_argument("--tracker-only", action="store_true", help="only the per-frame DryingTracker comparison")
    args = ap.parse_args(argv)
    tracker_frames(args.tracker_ref)
    if args.tracker_only:
        return
    model = InkChannelModel()
    fs = 10e6
    reps = max(1, args.n // 49)
    ds = synthetic_set(model, kind="ct", x0="random", n_per_level=reps, snr_db=40, seed=0)
    Y, X0, fm = ds.y, ds.x0, ds.fm
    n = Y.shape[0]
    small_batches(Y, model, fs, args.old_ref)
    if args.small_only:
        return
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
