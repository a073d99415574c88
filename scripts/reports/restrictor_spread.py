"""Restrictor-spread report: training on the calibrated fit alone against over the restrictors it allows.

    scripts/report restrictor_spread [--heads default h20 h16 h12] [--seeds 3 5] [--per-class 200]
                                     [--draws 1 5]

Healthy traces pin a head's healthy mode but hardly how the restrictor and the nozzle share
it; ``inkdiag calibrate`` leaves that split to a prior, and its error (a few per cent) moves
the modes of the blocked and dried classes the model is trained on (``reports/restrictor.md``,
``reports/heads.md``). ``inkdiag train``'s ``--posterior-draws K`` spreads the simulated rows
over ``K`` restrictors within calibration's own scatter
(:func:`inkdiag_core.calibration.posterior_profiles`; 1: the fit alone).

Per head of ``tests/foreign_head.py`` (an independent simulator) and seed: 300 healthy traces
(seed) calibrated (:func:`~inkdiag_core.calibration.calibrate`, the fit ``inkdiag calibrate`` runs),
then per ``--draws`` value a detector trained on the calibrated profile
(:func:`~inkdiag_core.training.train_detector` with ``inkdiag train``'s defaults, that seed and
that count) labels the same test recording (``--per-class`` traces of every class, seed + 1).
Use seeds the draws' default was not chosen on (it was chosen on 0, 7 and 11).
Prints and writes ``reports/restrictor_spread.md``.
"""

from __future__ import annotations

import argparse
import datetime
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import foreign_head as fh  # noqa: E402
from _common import md_table, out_path  # noqa: E402
from heads import _split_errors  # noqa: E402

from inkdiag_core import FaultClass, HeadProfile  # noqa: E402
from inkdiag_core.calibration import calibrate  # noqa: E402
from inkdiag_core.training import N_PER_CLASS, train_detector  # noqa: E402

SHOWN = ("partially_blocked", "slightly_dried", "intermediately_dried", "deeply_dried")


def run(name, seed, draws, per_class, tmp, n_per_class=N_PER_CLASS):
    """Scores of each draw count on one head and seed: ``(I_r error, {draws: scores})``."""
    fh.write_nominal_yaml(tmp / f"{name}.yaml", name)
    healthy = fh.simulate_foreign(name, {"healthy_nozzle": 300}, seed)
    test = fh.simulate_foreign(name, {c.value: per_class for c in FaultClass}, seed + 1)
    profile = calibrate(HeadProfile.load(tmp / f"{name}.yaml"), healthy["traces"], healthy["sample_rate_hz"]).profile
    ir_err = _split_errors(profile.channel, fh.FOREIGN_HEADS[name]["channel"])["I_r_err"]
    truth = np.asarray(test["labels"], dtype=object)
    out = {}
    for k in draws:
        det, info = train_detector(profile, seed=seed, posterior_draws=k, n_per_class=n_per_class)
        pred = np.asarray(det.label(test["traces"]).classes, dtype=object)
        per = {c.value: float(np.mean(pred[truth == c.value] == c.value)) for c in FaultClass}
        weakest = min(per, key=per.get)
        out[k] = {"fi": float(np.mean(pred == truth)), "per": per, "weakest": weakest,
                  "sd": info["restrictor_sd_log"]}
        print(f"{name} seed {seed} I_r {100 * ir_err:+.1f} % draws {k}: FI {100 * out[k]['fi']:.1f} %, weakest "
              f"{weakest} {100 * per[weakest]:.1f} %", flush=True)
    return ir_err, out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--heads", nargs="+", default=["default", "h20", "h16", "h12"])
    ap.add_argument("--seeds", type=int, nargs="+", default=[3, 5])
    ap.add_argument("--per-class", type=int, default=200, help="test traces per class")
    ap.add_argument("--draws", type=int, nargs="+", default=[1, 5], help="--posterior-draws values compared")
    args = ap.parse_args(argv)
    unknown = [h for h in args.heads if h not in fh.FOREIGN_HEADS]
    if unknown:
        ap.error(f"unknown head {unknown[0]!r}; tests/foreign_head.py has {', '.join(fh.FOREIGN_HEADS)}")
    t0 = time.perf_counter()
    rows, weakest = [], {k: [] for k in args.draws}
    with tempfile.TemporaryDirectory(prefix="inkdiag_spread_") as tmp:
        for name in args.heads:
            for seed in args.seeds:
                ir_err, res = run(name, seed, args.draws, args.per_class, Path(tmp))
                for k in args.draws:
                    r = res[k]
                    weakest[k].append(r["per"][r["weakest"]])
                    rows.append([name if (seed == args.seeds[0] and k == args.draws[0]) else "",
                                 seed if k == args.draws[0] else "", f"{100 * ir_err:+.1f}" if k == args.draws[0]
                                 else "", k, f"{100 * r['sd']:.1f}", f"{100 * r['fi']:.1f}",
                                 f"{r['weakest']} {100 * r['per'][r['weakest']]:.1f}",
                                 *(f"{100 * r['per'][c]:.1f}" for c in SHOWN)])
    elapsed = time.perf_counter() - t0
    cmd = (f"scripts/report restrictor_spread --heads {' '.join(args.heads)} --seeds "
           f"{' '.join(map(str, args.seeds))} --per-class {args.per_class} --draws {' '.join(map(str, args.draws))}")
    summary = "; ".join(f"{k} draw{'s' if k > 1 else ''}: weakest class {100 * min(v):.1f} to {100 * max(v):.1f} %, "
                        f"{sum(x >= 0.75 for x in v)} of {len(v)} runs >= 75 %" for k, v in weakest.items())
    text = "\n".join([
        "# Training over the restrictors calibration allows",
        "",
        f"{datetime.date.today().isoformat()}. `{cmd}` ({elapsed / 60:.1f} min on the shared 2-core machine). "
        "Heads of the independent simulator `tests/foreign_head.py`; per head and seed, 300 healthy traces "
        "calibrated by `inkdiag_core.calibration.calibrate` (the fit `inkdiag calibrate` runs), then one detector "
        "per `--posterior-draws` value (`inkdiag train`'s defaults otherwise, the run's seed) labels the same test "
        "recording. *I_r error*: the "
        "calibrated restrictor inertance against the true head's; *sd*: the spread of `log I_r` the rows were "
        "trained over (`inkdiag_core.calibration.restrictor_spread`, 0: the fit alone). The default of 5 "
        "draws was chosen on seeds 0, 7 and 11 (`reports/heads.md`); the seeds here are others.",
        "",
        md_table(["head", "seed", "I_r error %", "draws", "sd %", "FI %", "weakest class %",
                  *(f"{c} %" for c in SHOWN)], rows),
        "",
        f"Issue 14's class target is 75 %. {summary}.",
        "",
    ])
    print(text)
    out_path("restrictor_spread.md").write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
