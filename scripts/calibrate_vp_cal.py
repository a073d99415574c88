"""Fit the constants of the "vp_cal" fault estimator (``estimation.VP_CAL``) for a head.

    python scripts/calibrate_vp_cal.py [--seeds 11 19] [--n-per-class 100] [--profile HEAD.yaml]

"vp" fits the nominal linear model, whose only free parameter is f_m; a real nozzle
differs from it (ink temperature, geometry and piezo tolerances, meniscus stiffness,
nozzle entrance loss) and "vp" reads part of that as a fault. The ring-down's own
damping and frequency, refitted freely around the "vp" solution, deviate from the
model's by ``(d_sigma, d_omega)``; the procedure
(:func:`inkdiag_core.estimation.calibrate_vp_cal`) learns how the fault error goes
with those deviations on physics-based simulations of the head
(``fe_datasets.nonlinear_set``: the simulator's nonlinear variant, the head's spreads
and noise) with seeds DISJOINT from the fault-estimation report's evaluation set
(seed 100) and from the tests:

    (f_true - f_vp) / |f_true| ~ [(a_s + b_s x) d_sigma + (a_w + b_w x) d_omega] / |f_true|,

``x = f_vp / w0`` (w0 the nominal healthy angular frequency), least squares, no
intercept: the correction vanishes on data the nominal linear model explains. Prints
the constants (for the default head: to paste into ``VP_CAL``) and the fit's
hold-out accuracy (last seed). Without ``--profile``: the default head, as
``VP_CAL`` was made (seeds 11-19, 100 traces per class and seed).
"""

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "inkdiag_core"))

from inkdiag_core import HeadProfile  # noqa: E402
from inkdiag_core.estimation import calibrate_vp_cal  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, nargs=2, default=(11, 19), help="first, last (inclusive)")
    ap.add_argument("--n-per-class", type=int, default=100)
    ap.add_argument("--profile", default=None, help="a complete head profile (default: the default head)")
    args = ap.parse_args(argv)
    profile = HeadProfile.load(args.profile) if args.profile else None
    cal = calibrate_vp_cal(profile, seeds=args.seeds, n_per_class=args.n_per_class,
                           progress=lambda s, n: print(f"seed {s}: {n} traces", flush=True))
    h = cal["holdout"]
    print(f"hold-out seed {h['seed']} (fit on the others): .fm median {h['vp_median']:.2f} -> "
          f"{h['vp_cal_median']:.2f} %, P10 {h['vp_p10']:.2f} -> {h['vp_cal_p10']:.2f} %")
    print(f"all {cal['seeds'][1] - cal['seeds'][0] + 1} seeds: relative residual std {cal['residual_rel_std']:.4f}; "
          f"{cal['seconds']:.1f} s")
    print("VP_CAL = {")
    print(f'    "a_sigma": {cal["a_sigma"]:.6g}, "b_sigma": {cal["b_sigma"]:.6g},')
    print(f'    "a_omega": {cal["a_omega"]:.6g}, "b_omega": {cal["b_omega"]:.6g},')
    print(f'    "seeds": ({cal["seeds"][0]}, {cal["seeds"][1]}), "n_traces": {cal["n_traces"]},')
    print("}")


if __name__ == "__main__":
    main()
