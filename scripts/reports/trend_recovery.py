"""How many frames without a nozzle end its f_m trend: fe's ``recovery_frames`` measured.

    scripts/report trend_recovery [--nozzles 200] [--frames 100] [--seed 3] [--end-factor 9.0]

A simulated head (``HeadScenario``, the default head, no fixed fault) whose every other nozzle dries from 2.4 to
``--end-factor`` times the ink's viscosity over 20 s, one frame every 0.2 s. Each frame is labelled by the
default model (``models/fdi_default.joblib``, no baselines: every trace by its KPIs alone) and given to a
:class:`inkdiag_core.DryingTracker` as fe takes it (its traces, then its range's drying list) for each
``recovery_frames`` K. The drying nozzles never recover, so every trend that ends is a misclassification's
(a frame that labelled the nozzle something other than dried); a trend that ends loses its rate and its time to
the deeply dried level until it has two estimates again. Prints and writes ``reports/trend_recovery.md``.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import datetime  # noqa: E402
import sys  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, os.path.dirname(__file__))
from _common import md_table, out_path  # noqa: E402

FRAME_S = 0.2
KS = (1, 2, 3, 4)


def run(n_nozzles: int, n_frames: int, seed: int, end_factor: float):
    """``{K: (drying nozzles' trend restarts, estimates, estimates with a rate, their rates' relative errors)}`` and
    the labels' share of dried rows among the drying nozzles (a restart: an estimate with no rate, its nozzle's
    trend new, after the nozzle's first). A rate's error is against the true f_m's slope (its change over
    the frames either side, 1/s^2)."""
    from inkdiag_core import DryingTracker
    from inkdiag_core.faults import DRIED_VALUES
    from inkdiag_core.model_cache import ensure_default_model
    from inkdiag_core.persistence import load_model
    from inkdiag_core.simulation.scenario import HeadScenario

    det = load_model(ensure_default_model(), as_pipeline=False)[0]
    drying = np.arange(0, n_nozzles, 2)
    sc = HeadScenario(n_nozzles=n_nozzles, fault_nozzles=[], fault_classes=[], drying_nozzles=drying.tolist(),
                      drying_start_factor=2.4, drying_end_factor=end_factor, drying_duration_s=20.0, seed=seed)
    rng = np.random.default_rng(seed)
    frames, fm_true = [], []
    for k in range(n_frames):
        traces, _, fm, _ = sc.frame(k * FRAME_S, head_seed=[seed, 1], rng=rng)
        dried = np.isin(np.asarray(det.label(traces).classes, dtype=str), list(DRIED_VALUES))
        frames.append((traces, np.flatnonzero(dried)))
        fm_true.append(fm)
    slope = np.gradient(np.array(fm_true), FRAME_S, axis=0)  # (frames, nozzles), 1/s^2
    share = float(np.mean([np.isin(drying, d).mean() for _, d in frames]))
    out = {}
    for K in KS:
        tr = DryingTracker(recovery_frames=K, max_estimates=n_nozzles)
        n_est, n_rate, err, seen, restarts = 0, 0, [], set(), 0
        for k, (traces, dried) in enumerate(frames):
            tr.add_traces(traces, first_nozzle=0, frame_id=k, stamp=k * FRAME_S,
                          sample_rate_hz=sc.profile.sample_rate_hz)
            for e in tr.add_drying(k, dried, first_nozzle=0, n_nozzles=n_nozzles):
                on = np.isin(e.columns["nozzle"], drying)
                n_est += int(on.sum())
                rate, ids = e.columns["fm_rate"][on], e.columns["nozzle"][on].astype(int)
                restarts += sum(1 for i, r in zip(ids.tolist(), rate) if i in seen and not np.isfinite(r))
                seen.update(ids.tolist())
                ok = np.isfinite(rate) & (ids < n_nozzles)
                n_rate += int(ok.sum())
                err.append(np.abs(rate[ok] / slope[k, ids[ok]] - 1))
        out[K] = (restarts, n_est, n_rate, np.concatenate(err) if err else np.zeros(0))
    return out, share


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--nozzles", type=int, default=200, help="nozzles of the head; every other one dries")
    ap.add_argument("--frames", type=int, default=100, help="frames, one every 0.2 s")
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--end-factor", type=float, default=9.0, help="viscosity factor the drying nozzles reach at 20 s")
    args = ap.parse_args(argv)
    res, share = run(args.nozzles, args.frames, args.seed, args.end_factor)
    rows = [[K, ended, n, f"{100 * rate / n:.1f}", f"{100 * np.median(err):.0f}", f"{100 * np.percentile(err, 90):.0f}"]
            for K, (ended, n, rate, err) in res.items()]
    table = md_table(["recovery_frames", "drying nozzles' trend restarts", "estimates", "with a rate %",
                      "rate error median %",
                      "rate error P90 %"], rows)
    cmd = (f"scripts/report trend_recovery --nozzles {args.nozzles} --frames {args.frames} --seed {args.seed} "
           f"--end-factor {args.end_factor:g}")
    text = (f"# f_m trends and misclassified frames\n\n{datetime.date.today().isoformat()}. `{cmd}`: "
            f"{args.nozzles // 2} nozzles drying from 2.4 to {args.end_factor:g} times the ink's viscosity over 20 s, "
            f"{args.frames} frames at 5 frames/s, labelled by the default model without baselines "
            f"({100 * share:.1f} % of the drying nozzles' rows labelled dried); none recovers, so every trend that "
            "ends is a misclassification's (counted here on the drying nozzles only: a restart is an estimate "
            "with no rate after the nozzle's first). fe's `recovery_frames` (inkdiag_core.DryingTracker) is 3.\n\n"
            + table + "\n")
    out_path("trend_recovery.md").write_text(text, encoding="utf-8")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
