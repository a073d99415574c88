"""Open-set report (issue 16): held-out conditions called ``unknown``, false unknown on known classes, cost.

    scripts/report unknown [--seeds 5] [--n 600] [--quick]

Writes ``reports/unknown.md``. Per seed: a detector trained as the default one
(:func:`inkdiag_core.fdi.train_default_model`'s settings: 400 simulated traces per
class, Random Forest of 50 trees on KPI_Y, FNR <= 0.5 %, ``unknown_rate`` 0.01, plain
branch), then

- per held-out condition (:data:`inkdiag_core.simulation.heldout.HELDOUT_CONDITIONS`,
  never in training) ``--n`` traces over the whole severity range and ``--n`` at its
  mild end (severity 0-0.2): the fraction called ``unknown``, a known fault, healthy;
- ``--n`` new traces of each of the 12 known classes: the fraction called ``unknown``
  (false unknown), and fault detection / isolation with and without the layer on the
  same detector (an ``unknown`` counts as a detected fault for FD, a healthy row called
  ``unknown`` as a false alarm, and a wrongly isolated row for FI);
- throughput: ``FaultDetector.label`` with the layer against the rf/kpi_y pipeline's
  ``predict_proba`` (``scripts/bench fdi``'s reference; 100 trees for both there, the
  default 50 here for both) on the same batch, best of 3, repeated per seed.

Every figure is the mean over the seeds with the min-max range.
"""

from __future__ import annotations

import argparse
import datetime
import sys
import time

import numpy as np
from tqdm import tqdm

from _common import md_table, out_path

from inkdiag_core import FaultClass, FaultDetector, make_fdi_pipeline, simulate
from inkdiag_core.faults import healthy_mask
from inkdiag_core.openset import UNKNOWN

try:
    from inkdiag_core.simulation.heldout import HELDOUT_CONDITIONS, simulate_heldout
except ImportError:  # pragma: no cover - until the held-out conditions land
    sys.exit("scripts/report unknown needs inkdiag_core.simulation.heldout (issue 16, deliverable 3)")

CLASSES = [c.value for c in FaultClass]
MILD = (0.0, 0.2)


def best_of(fn, repeats=3):
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def fractions(classes):
    c = np.asarray(classes, dtype=object)
    unk = c == UNKNOWN
    healthy = healthy_mask(np.where(unk, "fully_blocked", c).astype(str))
    return unk.mean(), (~unk & ~healthy).mean(), healthy.mean()


def one_seed(seed, n, n_train):
    sim = simulate({c: n_train for c in FaultClass}, seed=seed)
    det = FaultDetector(n_estimators=50, min_samples_leaf=3, fnr_target=0.005, unknown_rate=0.01,
                        random_state=seed).fit(sim.traces, sim.label_values())
    out = {"held": {}, "mild": {}, "false": {}}
    for k, cond in enumerate(HELDOUT_CONDITIONS):
        for key, sev in (("held", None), ("mild", MILD)):
            h = simulate_heldout(cond, n, seed=10_000 * (seed + 1) + 10 * k + (key == "mild"), severity=sev)
            out[key][cond] = fractions(det.label(h.traces).classes)
    test = simulate({c: n for c in FaultClass}, seed=1000 + seed)
    y = test.label_values()
    got = det.label(test.traces)
    for c in CLASSES:
        out["false"][c] = float(np.mean(got.classes[y == c] == UNKNOWN))
    # FD / FI with and without the layer, same detector (the layer only relabels rows as unknown)
    layer, det.openset_ = det.openset_, None  # the classifier alone: what the rows were called before
    closed = det.label(test.traces).classes
    det.openset_ = layer
    is_fault = ~healthy_mask(y)
    for name, cls in (("with", got.classes), ("without", closed)):
        unk = cls == UNKNOWN
        flagged = unk | ~healthy_mask(np.where(unk, "fully_blocked", cls).astype(str))
        out[f"fd_fnr_{name}"] = float(np.mean(~flagged[is_fault]))
        out[f"fd_fpr_{name}"] = float(np.mean(flagged[~is_fault]))
        out[f"fi_{name}"] = float(np.mean(cls == y))
    # throughput, same batch, same run
    X = simulate({c: max(n // 2, 50) for c in FaultClass}, seed=2000 + seed).traces
    ref = make_fdi_pipeline("rf", "kpi_y", random_state=seed, n_estimators=50,
                            min_samples_leaf=3).fit(sim.traces, sim.label_values())
    t_ref = best_of(lambda: ref.predict_proba(X))
    t_open = best_of(lambda: det.label(X))
    out["tput_ref"], out["tput_open"] = X.shape[0] / t_ref, X.shape[0] / t_open
    out["tput_ratio"] = t_ref / t_open
    return out


def rng_cell(values, scale=100.0, digits=1):
    v = np.asarray(values, float) * scale
    if v.size == 1:
        return f"{v[0]:.{digits}f}"
    return f"{v.mean():.{digits}f} ({v.min():.{digits}f}-{v.max():.{digits}f})"


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--n", type=int, default=600, help="traces per held-out condition/range and per known class")
    ap.add_argument("--quick", action="store_true", help="2 seeds, 150 traces: a smoke run")
    ns = ap.parse_args()
    seeds, n, n_train = (2, 150, 400) if ns.quick else (ns.seeds, ns.n, 400)
    runs = [one_seed(s, n, n_train) for s in tqdm(range(seeds), desc="seeds")]
    today = datetime.date.today().isoformat()
    lines = [f"# Open-set `unknown` (issue 16) - {today}", "",
             f"`scripts/report unknown` ({seeds} seeds, {n} traces per held-out condition and range and per known "
             "class; detector as the default: 400 simulated traces per class, RF 50 trees on KPI_Y, "
             "`unknown_rate` 0.01, plain branch). Cells: mean over the seeds (min-max), %.", "",
             "The layer (`FaultDetector`, `inkdiag_core.openset`): per known class a robust Mahalanobis "
             "distance on the 7 KPIs (scale ones in log, phase as cos/sin) and log10 of the energy fraction "
             "the KPI sinusoid leaves unexplained; conformal p-values per class, class models fitted on the "
             "validation split, calibrated on the training split; `unknown` when every class's p-value is "
             "<= 0.01 (a known trace is `unknown` with probability <= 1 %).", "",
             "## Held-out conditions (never in training)", ""]
    for key, title in (("held", "whole severity range"), ("mild", f"mild end (severity {MILD[0]}-{MILD[1]})")):
        lines += [f"### {title}", ""]
        rows = []
        for cond in HELDOUT_CONDITIONS:
            vals = np.array([r[key][cond] for r in runs])  # (seeds, 3)
            rows.append([cond] + [rng_cell(vals[:, j]) for j in range(3)])
        lines += [md_table(["condition", "unknown", "a known fault", "healthy"], rows), ""]
    lines += ["## False unknown on the known classes", ""]
    rows = [[c, rng_cell([r["false"][c] for r in runs], digits=2)] for c in CLASSES]
    allf = np.array([[r["false"][c] for c in CLASSES] for r in runs])
    rows.append(["**all 12 (mean)**", rng_cell(allf.mean(axis=1), digits=2)])
    rows.append(["**worst class per seed**", rng_cell(allf.max(axis=1), digits=2)])
    lines += [md_table(["class", "called unknown"], rows), ""]
    lines += ["## Fault detection and isolation on the known classes, with and without the layer", "",
              "Same detector, same traces. An `unknown` is a fault for FD (a healthy row called `unknown` is a "
              "false alarm) and a wrong class for FI.", ""]
    rows = [[what, rng_cell([r[f"{key}_without"] for r in runs], digits=2),
             rng_cell([r[f"{key}_with"] for r in runs], digits=2)]
            for what, key in (("FD missed faults", "fd_fnr"), ("FD false alarms", "fd_fpr"),
                              ("FI accuracy", "fi"))]
    lines += [md_table(["", "without the layer", "with the layer"], rows), ""]
    lines += ["## Throughput (one process, same batch, best of 3 per seed)", "",
              md_table(["", "traces/s"],
                       [["pipeline rf/kpi_y `predict_proba` (reference)",
                         rng_cell([r["tput_ref"] for r in runs], scale=1.0, digits=0)],
                        ["`FaultDetector.label` with the open-set layer",
                         rng_cell([r["tput_open"] for r in runs], scale=1.0, digits=0)],
                        ["ratio (target >= 0.8)", rng_cell([r["tput_ratio"] for r in runs], scale=1.0, digits=3)]]),
              "", "`scripts/bench fdi` prints the same ratio with 100-tree forests (its own rf/kpi_y line).", ""]
    path = out_path("unknown.md")
    path.write_text("\n".join(lines) + "\n")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
