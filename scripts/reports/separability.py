"""Separability report: how well ANY classifier can tell the classes apart on a head's own traces.

    scripts/report separability [--heads default h20 h16 h5] [--train 400] [--test 200] [--seed 0] [--no-hgb]

Issue 14 asks for FI >= 90 % with every class >= 75 % on independent heads. ``scripts/report
heads`` measures inkdiag's workflow (calibrate on healthy traces, train on simulation, label).
This report asks a different question, to tell the workflow's losses from the data's limits:
trained on the foreign head's OWN labelled traces (``tests/foreign_head.py``, seed ``--seed``
+ 100, tested on seed + 101), with everything about the head known, what per-class accuracy
is possible at all? Per head:

- **kpi_y**, **rich**, **kpi_y+r_modified**: inkdiag's feature sets with its detector's forest
  (``make_fdi_pipeline``, 50 trees, >= 3 traces per leaf, every feature at each split as
  ``FaultDetector``'s ``max_features=None``; the residual filters from the head's true profile);
- **kpi_y, 2 KPIs per split**: the same forest with scikit-learn's default ``max_features="sqrt"``;
- **kpi_y, gradient boosting**: ``HistGradientBoostingClassifier`` (300 iterations) on the KPIs;
- **spectrum + waveform, gradient boosting**: a stronger learner on more of the trace (the
  7 KPIs, log of the first 80 normalised FFT magnitudes, the peak-normalised waveform at
  128 points; scikit-learn's ``HistGradientBoostingClassifier``, 300 iterations), on the
  four classes that overlap (partially_blocked and the dried classes) and healthy, 1,500
  traces per class (``--no-hgb`` skips both boosting columns: ~1 min per head);
- **kpi_y + nozzle baseline**: each trace with its own nozzle's healthy KPIs (a healthy
  twin with the same per-nozzle spreads: ``simulate_foreign`` draws every spread per row in
  a fixed order, so the same seed and row count give the same nozzles), inkdiag's
  ``kpi_y+baseline`` features;
- **kpi_y, no spreads**: the head without its per-nozzle and per-frame spreads
  (geometry, actuator, coupling, drive, gain, offset, temperature: ``FOREIGN_SPREADS`` all 0;
  noise and ADC kept).

Writes ``reports/separability.md``.
"""

from __future__ import annotations

import argparse
import copy
import datetime
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import foreign_head as fh  # noqa: E402
from _common import md_table  # noqa: E402

from inkdiag_core import FaultClass, HeadProfile, extract_kpis, make_fdi_pipeline, with_baseline  # noqa: E402

CLASSES = [c.value for c in FaultClass]
SPECTRUM = "spectrum + waveform, gradient boosting (5 classes)"
OVERLAP = ["healthy_nozzle", "partially_blocked", "slightly_dried", "intermediately_dried", "deeply_dried"]


def _true_profile(head):
    return HeadProfile.from_dict({"schema": "inkdiag.head_profile", "schema_version": 1,
                                  **{k: fh.FOREIGN_HEADS[head][k] for k in ("sampling", "channel", "drive", "sensor")}})


def _per_class(pred, y, classes):
    return {c: float(np.mean(pred[y == c] == c)) for c in classes}


#: The detector's forest (``FaultDetector``'s defaults).
FOREST = {"n_estimators": 50, "min_samples_leaf": 3, "max_features": None}


def _forest(head_spec, features, classes, n_train, n_test, seed, profile=None, **forest):
    tr = fh.simulate_foreign(head_spec, {c: n_train for c in classes}, seed + 100)
    te = fh.simulate_foreign(head_spec, {c: n_test for c in classes}, seed + 101)
    fs = float(tr["sample_rate_hz"])
    pipe = make_fdi_pipeline("rf", features, sample_rate_hz=fs, profile=profile, **{**FOREST, **forest})
    pipe.fit(np.asarray(tr["traces"]), np.asarray(tr["labels"]).astype(str))
    y = np.asarray(te["labels"]).astype(str)
    return _per_class(pipe.predict(np.asarray(te["traces"])), y, classes)


def _kpi_boosting(head, classes, n_train, n_test, seed):
    from sklearn.ensemble import HistGradientBoostingClassifier

    tr = fh.simulate_foreign(head, {c: n_train for c in classes}, seed + 100)
    te = fh.simulate_foreign(head, {c: n_test for c in classes}, seed + 101)
    fs = float(tr["sample_rate_hz"])
    clf = HistGradientBoostingClassifier(max_iter=300, random_state=seed)
    clf.fit(extract_kpis(np.asarray(tr["traces"]), fs), np.asarray(tr["labels"]).astype(str))
    y = np.asarray(te["labels"]).astype(str)
    return _per_class(clf.predict(extract_kpis(np.asarray(te["traces"]), fs)), y, classes)


def _with_twins(head, classes, n, seed):
    d = fh.simulate_foreign(head, {c: n for c in classes}, seed)
    twin = fh.simulate_foreign(head, {"healthy_nozzle": n * len(classes)}, seed)  # the same nozzles, healthy
    if not np.array_equal(twin["offset_v"], d["offset_v"]):  # the twin must be the same nozzles
        raise RuntimeError("tests/foreign_head.py no longer draws the same spreads per row: no twins")
    fs = float(d["sample_rate_hz"])
    base = extract_kpis(np.asarray(twin["traces"]), fs)
    return with_baseline(np.asarray(d["traces"]), base), np.asarray(d["labels"]).astype(str), fs


def _baseline_forest(head, classes, n_train, n_test, seed):
    Xtr, ytr, fs = _with_twins(head, classes, n_train, seed + 100)
    Xte, yte, _ = _with_twins(head, classes, n_test, seed + 101)
    pipe = make_fdi_pipeline("rf", "kpi_y+baseline", sample_rate_hz=fs, **FOREST).fit(Xtr, ytr)
    return _per_class(pipe.predict(Xte), yte, classes)


def _spectrum_features(traces, fs):
    X = np.asarray(traces, dtype=np.float64)
    k = extract_kpis(X, fs)
    S = np.abs(np.fft.rfft(X - X.mean(axis=1, keepdims=True), axis=1))
    S /= S.max(axis=1, keepdims=True)
    wave = X / np.abs(X).max(axis=1, keepdims=True)
    return np.hstack([k, np.log(S[:, :80] + 1e-6), wave[:, ::max(1, X.shape[1] // 128)]])


def _boosting(head, n_train, n_test, seed):
    from sklearn.ensemble import HistGradientBoostingClassifier

    tr = fh.simulate_foreign(head, {c: n_train for c in OVERLAP}, seed + 100)
    te = fh.simulate_foreign(head, {c: n_test for c in OVERLAP}, seed + 101)
    fs = float(tr["sample_rate_hz"])
    clf = HistGradientBoostingClassifier(max_iter=300, random_state=seed)
    clf.fit(_spectrum_features(tr["traces"], fs), np.asarray(tr["labels"]).astype(str))
    y = np.asarray(te["labels"]).astype(str)
    return _per_class(clf.predict(_spectrum_features(te["traces"], fs)), y, OVERLAP)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--heads", nargs="+", default=["default", "h20", "h16", "h5"])
    ap.add_argument("--train", type=int, default=400, help="training traces per class (the forests)")
    ap.add_argument("--test", type=int, default=200, help="test traces per class")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-hgb", action="store_true", help="skip the gradient-boosting columns")
    ns = ap.parse_args()
    unknown = [h for h in ns.heads if h not in fh.FOREIGN_HEADS]
    if unknown:
        ap.error(f"unknown head {unknown[0]!r}; tests/foreign_head.py has {', '.join(fh.FOREIGN_HEADS)}")
    t0 = time.perf_counter()
    cols = ["kpi_y", "kpi_y, 2 KPIs per split", "rich", "kpi_y+r_modified", "kpi_y + nozzle baseline",
            "kpi_y, no spreads"]
    if not ns.no_hgb:
        cols[2:2] = ["kpi_y, gradient boosting"]
        cols.insert(5, SPECTRUM)
    results = {}
    for head in ns.heads:
        prof = _true_profile(head)
        r = {"kpi_y": _forest(head, "kpi_y", CLASSES, ns.train, ns.test, ns.seed),
             "kpi_y, 2 KPIs per split": _forest(head, "kpi_y", CLASSES, ns.train, ns.test, ns.seed,
                                                max_features="sqrt")}
        for feats in ("rich", "kpi_y+r_modified"):
            r[feats] = _forest(head, feats, CLASSES, ns.train, ns.test, ns.seed, profile=prof)
        if not ns.no_hgb:
            r["kpi_y, gradient boosting"] = _kpi_boosting(head, CLASSES, ns.train, ns.test, ns.seed)
            r[SPECTRUM] = _boosting(head, 1500, 2 * ns.test, ns.seed)
        r["kpi_y + nozzle baseline"] = _baseline_forest(head, CLASSES, ns.train, ns.test, ns.seed)
        still = copy.deepcopy(fh.FOREIGN_HEADS[head])
        still["spreads"] = {k: 0.0 for k in fh.FOREIGN_SPREADS}
        r["kpi_y, no spreads"] = _forest(still, "kpi_y", CLASSES, ns.train, ns.test, ns.seed)
        results[head] = r
        print(f"{head}: done ({time.perf_counter() - t0:.0f} s)", file=sys.stderr)

    today = datetime.date.today().isoformat()
    lines = [f"# Separability of the classes on other heads (issue 14) - {today}", "",
             f"`scripts/report {' '.join(['separability'] + (['--no-hgb'] if ns.no_hgb else []))}` "
             f"(heads {', '.join(ns.heads)}; {ns.train} training and {ns.test} test traces per class, seeds "
             f"{ns.seed + 100} / {ns.seed + 101}; {time.perf_counter() - t0:.0f} s on the shared 2-core machine). "
             "Every classifier here is trained on the foreign head's OWN labelled traces "
             "(`tests/foreign_head.py`), not on inkdiag's simulation: what any classifier with these inputs "
             "can reach on that head, against which `reports/heads.md` (inkdiag's calibrate -> train on "
             "simulation -> label workflow) can be read. Per-class accuracy, %.", "",
             "Columns: inkdiag's feature sets with its detector's forest (50 trees, at least 3 traces per leaf, "
             "every feature at each split; the residual filters from the head's true profile); the same forest "
             "on kpi_y with scikit-learn's default of 2 of the 7 KPIs per split; a gradient-boosted classifier "
             "(300 iterations) on kpi_y; one on the 7 KPIs, the first 80 log-normalised FFT "
             "magnitudes and the normalised waveform at 128 points, on the five classes that overlap (1,500 "
             "training traces each); each trace with its own nozzle's healthy KPIs (one frame of a healthy twin of "
             "the same nozzle at the same temperature; a commissioning baseline is the median of 8 frames, at "
             "another temperature); the head without its "
             "per-nozzle and per-frame spreads (geometry, actuator, coupling, drive, gain, offset, "
             "temperature; noise and ADC kept).", ""]
    for head in ns.heads:
        h = fh.FOREIGN_HEADS[head]["sampling"]
        lines += [f"## {head} ({h['sample_rate_hz'] / 1e6:g} MHz x {h['n_samples']})", ""]
        rows = []
        for c in CLASSES:
            rows.append([c] + [f"{100 * results[head][col][c]:.1f}" if c in results[head][col] else ""
                               for col in cols])
        rows.append(["**FI (12 classes)**"] + [f"{100 * np.mean(list(results[head][col].values())):.1f}"
                                               if len(results[head][col]) == len(CLASSES) else "" for col in cols])
        lines += [md_table(["class"] + cols, rows), ""]
    lines += ["## Reading it", "",
              "- Where the *no spreads* column is ~100 % and the *kpi_y* column is not, the classes are told apart "
              "by the physics but blurred by the spread between nozzles and frames: a single trace cannot "
              "resolve them, whatever the training data; a nozzle's own baseline removes what is per nozzle.",
              "- A class below 75 % in every column with spreads is below issue 14's per-class target on that "
              "head for any classifier trained on these inputs, inkdiag's included.", ""]
    out = ROOT / "reports" / "separability.md"
    out.write_text("\n".join(lines))
    print(f"wrote {out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
