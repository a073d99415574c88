"""Assumed-actuator report: heads whose empty channels ring away from the actuator calibration assumes.

    scripts/report actuator [--heads h20 h12] [--ratios 0.72 0.8 0.9 1.0 1.12] [--spreads 0.085 0.12 0.15]
                            [--seed 0] [--per-class 200] [--empty 50]

Healthy traces never show the actuator alone (an empty channel's mode), so a profile calibrated
without ``--empty`` traces or ``channel.f_act`` assumes an actuator like the default head's at the
fitted ``B_act`` (the rule), with a log-normal spread ``spreads.actuator_resonance_rel`` of
:data:`inkdiag_core.calibration.ASSUMED_ACTUATOR_RESONANCE_REL`. Per head of ``tests/foreign_head.py``
(an independent simulator): 300 healthy traces (seed) calibrated once
(:func:`~inkdiag_core.calibration.calibrate`, the fit ``inkdiag calibrate`` runs); per ``--spreads``
value a detector trained on that profile with that spread (:func:`~inkdiag_core.training.train_detector`,
``inkdiag train``'s defaults, the seed); per ``--ratios`` value a test recording (``--per-class``
traces of every class, seed + 1) of the same head with its dry actuator at that multiple of the rule,
labelled by each of them, and by a detector of a profile calibrated with ``--empty`` traces of that
head (``--empty`` empty_channel_1 traces, seed + 2; 0: not run). Prints and writes
``reports/actuator.md``.
"""

from __future__ import annotations

import argparse
import copy
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

from inkdiag_core import FaultClass, HeadProfile  # noqa: E402
from inkdiag_core.calibration import assumed_f_act_hz, calibrate  # noqa: E402
from inkdiag_core.training import N_PER_CLASS, train_detector  # noqa: E402

EMPTY = ("empty_channel_1", "empty_channel_2")


def _head(name, f_act_hz):
    """``name``'s head dict with its dry actuator at ``f_act_hz`` (the rest of its physics its own)."""
    return dict(copy.deepcopy(fh.FOREIGN_HEADS[name]), physics=dict(fh.FOREIGN_PHYSICS[name], f_act_hz=f_act_hz))


def _scores(det, test):
    truth = np.asarray(test["labels"], dtype=object)
    pred = np.asarray(det.label(test["traces"]).classes, dtype=object)
    per = {c.value: float(np.mean(pred[truth == c.value] == c.value)) for c in FaultClass}
    weakest = min(per, key=per.get)
    wrong = pred[(truth == "empty_channel_1") & (pred != "empty_channel_1")]
    values, counts = np.unique(wrong.astype(str), return_counts=True)
    top = f"{values[counts.argmax()]} {100 * counts.max() / max(1, np.sum(truth == 'empty_channel_1')):.1f}" \
        if counts.size else ""
    return {"fi": float(np.mean(pred == truth)), "per": per, "weakest": weakest, "ec1_as": top}


def rule_hz(profile) -> float:
    """The actuator a calibrated ``profile`` without ``f_act`` assumes: the default head's at its fitted ``B_act``, Hz
    (:func:`inkdiag_core.calibration.calibrate`'s ``report["actuator"]["rule_f_act_hz"]``)."""
    return assumed_f_act_hz(profile.channel["B_act"])


def run(name, ratios, spreads, seed, per_class, n_empty, tmp, n_per_class=N_PER_CLASS):
    """One head: ``{"own", "rule_hz", "report_rule_hz", "rows", "models", "f_act"}``: its own dry actuator over the
    rule, the rule (Hz; and calibrate's own figure of it), ``[(ratio, how, scores)]``, the detector per spread and
    the ``f_act`` (Hz) each ``--empty`` calibration measured, per ratio."""
    fh.write_nominal_yaml(tmp / f"{name}.yaml", name)
    nominal = HeadProfile.load(tmp / f"{name}.yaml")
    own = fh.FOREIGN_PHYSICS[name]["f_act_hz"]
    healthy = fh.simulate_foreign(_head(name, own), {"healthy_nozzle": 300}, seed)
    fit = calibrate(nominal, healthy["traces"], healthy["sample_rate_hz"])
    profile = fit.profile
    rule = rule_hz(profile)
    models, f_act = {}, {}
    for s in spreads:
        p = profile.replace(spreads_overrides={**profile.spreads_overrides, "actuator_resonance_rel": s})
        models[s], _ = train_detector(p, seed=seed, n_per_class=n_per_class)
    rows = []
    for r in ratios:
        test = fh.simulate_foreign(_head(name, r * rule), {c.value: per_class for c in FaultClass}, seed + 1)
        for s in spreads:
            rows.append((r, f"assumed, spread {s:g}", _scores(models[s], test)))
        if n_empty:
            dry = fh.simulate_foreign(_head(name, r * rule), {"empty_channel_1": n_empty}, seed + 2)
            measured = calibrate(nominal, healthy["traces"], healthy["sample_rate_hz"], empty=dry["traces"]).profile
            f_act[r] = float(measured.channel["f_act"])
            det, _ = train_detector(measured, seed=seed, n_per_class=n_per_class)
            rows.append((r, f"--empty ({n_empty} traces)", _scores(det, test)))
        for _, how, sc in rows[-(len(spreads) + bool(n_empty)):]:
            print(f"{name} actuator {r:.2f} x rule, {how}: FI {100 * sc['fi']:.1f} %, empty_channel_1 "
                  f"{100 * sc['per']['empty_channel_1']:.1f} %, empty_channel_2 {100 * sc['per']['empty_channel_2']:.1f} "
                  f"%, weakest {sc['weakest']} {100 * sc['per'][sc['weakest']]:.1f} %", flush=True)
    return {"own": own / rule, "rule_hz": rule, "report_rule_hz": fit.report["actuator"]["rule_f_act_hz"],
            "rows": rows, "models": models, "f_act": f_act}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--heads", nargs="+", default=["h20", "h12"])
    ap.add_argument("--ratios", type=float, nargs="+", default=[0.72, 0.8, 0.9, 1.0, 1.12],
                    help="the test heads' dry actuator resonance, in multiples of the rule")
    ap.add_argument("--spreads", type=float, nargs="+", default=[0.085, 0.12, 0.15],
                    help="actuator_resonance_rel values trained with")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--per-class", type=int, default=200, help="test traces per class")
    ap.add_argument("--empty", type=int, default=50, help="empty-channel traces for the --empty rows (0: none)")
    args = ap.parse_args(argv)
    unknown = [h for h in args.heads if h not in fh.FOREIGN_HEADS]
    if unknown:
        ap.error(f"unknown head {unknown[0]!r}; tests/foreign_head.py has {', '.join(fh.FOREIGN_HEADS)}")
    t0 = time.perf_counter()
    table, owns = [], []
    with tempfile.TemporaryDirectory(prefix="inkdiag_actuator_") as tmp:
        for name in args.heads:
            res = run(name, args.ratios, args.spreads, args.seed, args.per_class, args.empty, Path(tmp))
            rows = res["rows"]
            owns.append(f"{name} {res['own']:.2f} (rule {res['rule_hz'] / 1e3:.0f} kHz)")
            for i, (r, how, sc) in enumerate(rows):
                first = i == 0 or rows[i - 1][0] != r
                table.append([name if i == 0 else "", f"{r:.2f}" if first else "", how, f"{100 * sc['fi']:.1f}",
                              *(f"{100 * sc['per'][c]:.1f}" for c in EMPTY), sc["ec1_as"],
                              f"{sc['weakest']} {100 * sc['per'][sc['weakest']]:.1f}"])
            print(f"{name}: its own actuator is {res['own']:.2f} x the rule", flush=True)
    elapsed = time.perf_counter() - t0
    cmd = (f"scripts/report actuator --heads {' '.join(args.heads)} --ratios {' '.join(f'{r:g}' for r in args.ratios)} "
           f"--spreads {' '.join(f'{s:g}' for s in args.spreads)} --seed {args.seed} --per-class {args.per_class} "
           f"--empty {args.empty}")
    text = "\n".join([
        "# Empty channels when the actuator is assumed",
        "",
        f"{datetime.date.today().isoformat()}. `{cmd}` ({elapsed / 60:.1f} min on the shared 2-core machine). "
        "Heads of the independent simulator `tests/foreign_head.py`, each calibrated once from 300 healthy traces "
        "(`inkdiag_core.calibration.calibrate`, no `--empty`: the actuator assumed like the default head's at the "
        "fitted `B_act`, the *rule*), then trained (`inkdiag train`'s defaults, the run's seed) with the assumed "
        "actuator's spread `spreads.actuator_resonance_rel` at each value shown (calibrate writes 0.085); each test "
        "recording is the same head with its dry actuator (the simulator's `f_act_hz`) at the multiple of the rule "
        "shown. *--empty*: calibrated with traces of that test head's empty channels as well (the measured actuator), "
        "then trained. FI counts `ok_signal` and `healthy_nozzle` apart, as reports/heads.md does. *empty_channel_1 "
        "labelled as*: the most frequent wrong label of that class and its share of the class (blank: none wrong). "
        f"The heads' own dry actuators, as multiples of their rule: {'; '.join(owns)}.",
        "",
        md_table(["head", "actuator / rule", "profile", "FI %", *(f"{c} %" for c in EMPTY),
                  "empty_channel_1 labelled as (%)", "weakest class %"], table),
        "",
    ])
    print(text)
    out_path("actuator.md").write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
