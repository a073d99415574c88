"""Heads report: inkdiag on printheads other than its own, through the `inkdiag` command.

    scripts/report heads [--heads default h20 h16 h12 h5] [--per-class 150] [--n-per-class N] [--seed 0]
                         [--posterior-draws K]
                         [--other-seeds S [S ...]]

For each head, traces come from the independent simulator ``tests/foreign_head.py``
(its own code, not inkdiag's simulator). The workflow is the one a user runs,
with the documented commands:

1. ``inkdiag calibrate HEALTHY.npz --nominal NOMINAL.yaml --out HEAD.yaml`` on 300
   recorded healthy traces and the nominal profile (sampling, drive, rho, mu, r_n,
   L_n, V_ch, c);
2. ``inkdiag train --profile HEAD.yaml --out MODEL.joblib``;
3. ``inkdiag label TEST.npz --model MODEL.joblib --out LABELS.csv`` on every class;
4. ``inkdiag estimate DRIED.npz --profile HEAD.yaml --out FM.csv`` on the dried classes.

Steps 2-4 run four times per head: with the calibrated profile, with a profile
calibrated with 50 traces of fully blocked nozzles as well (``inkdiag calibrate
--blocked``: they pin the restrictor), with one calibrated with 50 traces of empty
channels as well (``inkdiag calibrate --empty``: the actuator's own resonance), and
with the head's true profile, so that the cost of calibration is visible. A fifth run uses what a
commissioned head also has, each nozzle's healthy baseline: ``inkdiag baseline
COMMISSION.npz --profile HEAD.yaml --out B.npz`` on 8 healthy frames of every
nozzle (the test and dried recordings are later frames of the same nozzles:
``simulate_foreign(..., nozzle_seed=...)``), ``inkdiag train --baseline``, and
``label`` / ``estimate`` with ``--baselines B.npz``, all on the calibrated profile. Writes
``reports/heads.md`` (and keeps the work files under ``reports/heads_work/``
only with ``--keep``). Every run's model also labels :data:`N_ODD` off-class traces (``odd_traces``: damped
sinusoids of no class), for how often the open-set layer says ``unknown`` on that head.

With ``--other-seeds``, the calibrated workflow (steps 1-3) runs again per head for each of
those seeds (other healthy and test recordings, another training seed): how much the
weakest classes move from one calibration to the next.
"""

from __future__ import annotations

import argparse
import csv
import datetime
import os
import shutil
import subprocess
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

from inkdiag_core import FaultClass, HeadProfile, screen_traces  # noqa: E402
from inkdiag_core.calibration import POSTERIOR_DRAWS, UNSEEN_PHYSICS_SPREADS  # noqa: E402
from inkdiag_core.faults import DRIED_CLASSES  # noqa: E402
from inkdiag_core.head_profile import SPREAD_KEYS  # noqa: E402
from inkdiag_core.training import N_PER_CLASS  # noqa: E402
from inkdiag_core.kpis import extract_kpis  # noqa: E402

HEALTHY = {FaultClass.OK_SIGNAL.value, FaultClass.HEALTHY_NOZZLE.value}
BASELINES = "calibrated + baselines"
BLOCKED = "calibrated + blocked"
EMPTY = "calibrated + empty"
KINDS = ("calibrated", BLOCKED, EMPTY, "true", BASELINES)
"""The runs per head, in the order the tables show them."""
COMMISSION_FRAMES = 8
"""Healthy frames of each nozzle in a head's commissioning recording (``inkdiag baseline``'s default)."""
N_BLOCKED = 50
"""Fully blocked traces given to ``inkdiag calibrate --blocked`` (the *calibrated + blocked* run)."""
N_EMPTY = 50
"""Empty-channel traces given to ``inkdiag calibrate --empty`` (the *calibrated + empty* run)."""
N_ODD = 200
"""Off-class traces per head (:func:`odd_traces`), labelled by every run's model: how often the open-set layer says
``unknown`` where no class fits."""
_WORK = [""]  # the work directory, shown as WORK in the report


def _inkdiag(*args, log):
    cmd = [sys.executable, "-m", "inkdiag_ros.cli", *map(str, args)]
    t0 = time.perf_counter()
    r = subprocess.run(cmd, capture_output=True, text=True)
    dt = time.perf_counter() - t0
    shown = " ".join(str(a).replace(_WORK[0], "WORK") if _WORK[0] else str(a) for a in args)
    log.append(f"$ inkdiag {shown}   # {dt:.1f} s, exit {r.returncode}")
    if r.returncode != 0:
        raise SystemExit(f"inkdiag {args[0]} failed (exit {r.returncode}):\n{r.stderr[-2000:]}")
    return r, dt


def _read_csv(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def _true_profile_yaml(name, path):
    """The true profile of head ``name`` (a name of ``tests/foreign_head.py`` or a head dict with its
    ``physics``, as ``splits.split_head`` builds) written to ``path``; returns ``path``."""
    # the head's true channel, drive, sensor and spreads (a dict's own physics and spreads over the
    # simulator's defaults, as it simulates them); and the same training over the physics healthy
    # traces cannot show as a calibrated profile gets, so that the two rows differ by calibration only
    head, physics, all_spreads = fh._head(name)  # physics: the actuator alone (the empty channels' mode)
    spreads = {k: v for k, v in all_spreads.items() if k in SPREAD_KEYS}
    label = name if isinstance(name, str) else "custom"
    doc = {"schema": "inkdiag.head_profile", "schema_version": 1, "name": f"{label}_true", **{
        k: dict(head[k]) for k in ("sampling", "channel", "drive", "sensor")},
        "spreads": {**spreads, **UNSEEN_PHYSICS_SPREADS}}
    doc["channel"].update(f_act=physics["f_act_hz"], zeta_act=physics["zeta_act"])
    HeadProfile.from_dict(doc, source=f"{label} true profile").save(path)
    return path


def _scores(labels_csv, truth):
    rows = _read_csv(labels_csv)
    pred = np.array([r["class"] for r in rows], dtype=object)
    order = np.array([int(r["row"]) for r in rows])
    truth = np.asarray(truth, dtype=object)[order]
    fd = np.mean([(p in HEALTHY) == (t in HEALTHY) and p != "invalid" for p, t in zip(pred, truth)])
    fi = float(np.mean(pred == truth))
    per = {c.value: float(np.mean(pred[truth == c.value] == c.value)) for c in FaultClass
           if (truth == c.value).any()}
    unknown = {c.value: float(np.mean(pred[truth == c.value] == "unknown")) for c in FaultClass
               if (truth == c.value).any()}
    return float(fd), fi, per, int((pred == "invalid").sum()), unknown, _wrong_calls(pred, truth)


def _wrong_calls(pred, truth):
    """Per class: its most frequent wrong label (``invalid`` included, as in the scores) and that label's
    share of the class's rows."""
    out = {}
    for c in FaultClass:
        got = pred[truth == c.value]
        wrong = got[got != c.value]
        if wrong.size:
            labels, counts = np.unique(wrong.astype(str), return_counts=True)
            out[c.value] = (str(labels[np.argmax(counts)]), float(counts.max() / got.size))
    return out


MODE_CLASSES = ("healthy_nozzle", "partially_blocked", "slightly_dried", "intermediately_dried", "deeply_dried",
                "fully_blocked")
"""Classes whose dominant mode the report compares between the recording and the profiles' simulations."""


SPLIT_CLASSES = ("partially_blocked", "intermediately_dried", "deeply_dried")
"""The classes whose accuracy the seed-by-seed table shows (those the restrictor split moves)."""


def _class_modes(traces, labels, fs):
    """Median dominant frequency (Hz) and damping ratio of each of :data:`MODE_CLASSES`' rows that screening
    accepts (a clipped or flat row has no mode to compare; labelling calls it invalid)."""
    y = np.asarray(traces, dtype=np.float64)
    ok, _ = screen_traces(y, sample_rate_hz=fs)
    k = extract_kpis(y[ok], fs)
    labels = np.asarray([getattr(v, "value", v) for v in labels], dtype=object)[ok]
    return {c: (float(np.median(k[labels == c, 1])), float(np.median(k[labels == c, 2])))
            for c in MODE_CLASSES if (labels == c).any()}


def _dmu_errors(fm_csv, d_mu_true):
    rows = _read_csv(fm_csv)
    idx = np.array([int(r["row"]) for r in rows])
    est = np.array([float(r["d_mu"]) if r["d_mu"] not in ("", "nan") else np.nan for r in rows])
    err = np.abs(est - d_mu_true[idx]) / d_mu_true[idx]
    n_nan = int(np.isnan(err).sum())
    err = err[np.isfinite(err)]
    return float(np.median(err)), float(np.percentile(err, 90)), n_nan


def odd_traces(healthy, sensor, n, seed):
    """``n`` single damped sinusoids of no class: ``(traces (n, n_samples) float32 V, sample rate Hz)``.

    Frequency log-uniform in 0.2-5 x the head's healthy mode, damping ratio log-uniform in 0.005-0.3, amplitude
    log-uniform in 0.3-3 x the healthy traces' median but at most 0.8 of the ADC's range, a random phase, offset 0,
    white noise of the head's sensor and its ADC's quantisation (``sensor``: ``noise_std_v``, ``adc_range_v``,
    ``adc_bits``, as ``tests/foreign_head.py`` gives them): most are unlike every class, but a draw can land in a
    class's own region (a sinusoid near the healthy mode with a healthy damping is one), so not all of them should
    be ``unknown``. The healthy mode and amplitude are the recorded healthy traces' (what a user has), not the true
    head's."""
    fs = float(healthy["sample_rate_hz"])
    y = np.asarray(healthy["traces"], dtype=np.float64)
    k = extract_kpis(y, fs)
    f_h, a_h = float(np.median(k[:, 1])), float(np.median(k[:, 3]))
    rng = np.random.default_rng(seed)
    f = f_h * np.exp(rng.uniform(np.log(0.2), np.log(5.0), n))
    zeta = np.exp(rng.uniform(np.log(0.005), np.log(0.3), n))
    a = np.minimum(a_h * np.exp(rng.uniform(np.log(0.3), np.log(3.0), n)), 0.8 * float(sensor["adc_range_v"]))
    phase = rng.uniform(0, 2 * np.pi, n)
    t = np.arange(y.shape[1]) / fs
    w = 2 * np.pi * f
    x = a[:, None] * np.exp(-(zeta * w / np.sqrt(1 - zeta ** 2))[:, None] * t) * np.cos(w[:, None] * t + phase[:, None])
    x += rng.normal(0.0, float(sensor["noise_std_v"]), x.shape)
    if sensor.get("adc_bits") is not None:  # as the head's ADC records them (within its range: not clipped)
        lsb = 2.0 * float(sensor["adc_range_v"]) / 2 ** int(sensor["adc_bits"])
        x = np.round(x / lsb) * lsb
    return x.astype(np.float32), fs


def _unknown_share(labels_csv):
    """``(share of the valid rows called unknown, invalid rows)`` of a labels CSV."""
    classes = [r["class"] for r in _read_csv(labels_csv)]
    valid = [c for c in classes if c != "invalid"]
    return float(np.mean([c == "unknown" for c in valid])) if valid else float("nan"), len(classes) - len(valid)


def _draws(posterior_draws):
    """``inkdiag train``'s ``--posterior-draws`` option when one is given (None: its default)."""
    return [] if posterior_draws is None else ["--posterior-draws", posterior_draws]


def run_head(name, work, *, per_class, n_per_class, seed, log, posterior_draws=None):
    head_dir = work / name
    head_dir.mkdir(parents=True, exist_ok=True)
    nominal = head_dir / "nominal.yaml"
    fh.write_nominal_yaml(nominal, name)
    healthy = fh.simulate_foreign(name, {"healthy_nozzle": 300}, seed)
    fh.write_recording(head_dir / "healthy.npz", healthy)
    odd, fs = odd_traces(healthy, fh.FOREIGN_HEADS[name]["sensor"], N_ODD, seed + 8)
    # one head's nozzles (persistent spreads, nozzle_seed): the test rows are nozzles 0..n_test-1,
    # the dried rows the next ones; the commissioning recording has 8 healthy frames of each
    n_test, n_dried = per_class * len(FaultClass), per_class * len(DRIED_CLASSES)
    test = fh.simulate_foreign(name, {c.value: per_class for c in FaultClass}, seed + 1,
                               nozzles=np.arange(n_test), nozzle_seed=seed + 4)
    fh.write_recording(head_dir / "test.npz", test)
    dried = fh.simulate_foreign(name, {c.value: per_class for c in DRIED_CLASSES}, seed + 2,
                                nozzles=n_test + np.arange(n_dried), nozzle_seed=seed + 4)
    fh.write_recording(head_dir / "dried.npz", dried)
    n_all = n_test + n_dried
    if N_ODD > n_all:
        raise SystemExit(f"--per-class {per_class}: the {N_ODD} off-class rows need as many commissioned nozzles")
    np.savez(head_dir / "odd.npz", traces=odd, sample_rate_hz=fs, nozzle=np.arange(N_ODD))  # baselines: nozzles 0..
    commission = fh.simulate_foreign(name, {"healthy_nozzle": COMMISSION_FRAMES * n_all}, seed + 5,
                                     nozzles=np.tile(np.arange(n_all), COMMISSION_FRAMES), nozzle_seed=seed + 4)
    fh.write_recording(head_dir / "commission.npz", commission)
    del commission
    # the truth: each trace's nozzle viscosity over its own channel's (its ink temperature's)
    d_mu_true = np.asarray(dried["mu_nozzle"], float) - np.asarray(dried["mu"], float)

    _, t_cal = _inkdiag("calibrate", head_dir / "healthy.npz", "--nominal", nominal,
                        "--out", head_dir / "calibrated.yaml", log=log)
    fh.write_recording(head_dir / "blocked.npz", fh.simulate_foreign(name, {"fully_blocked": N_BLOCKED}, seed + 6))
    _inkdiag("calibrate", head_dir / "healthy.npz", "--nominal", nominal, "--blocked", head_dir / "blocked.npz",
             "--out", head_dir / "calibrated_blocked.yaml", log=log)
    fh.write_recording(head_dir / "empty.npz", fh.simulate_foreign(name, {"empty_channel_1": N_EMPTY}, seed + 7))
    _inkdiag("calibrate", head_dir / "healthy.npz", "--nominal", nominal, "--empty", head_dir / "empty.npz",
             "--out", head_dir / "calibrated_empty.yaml", log=log)
    profiles = {"calibrated": head_dir / "calibrated.yaml", BLOCKED: head_dir / "calibrated_blocked.yaml",
                EMPTY: head_dir / "calibrated_empty.yaml", "true": _true_profile_yaml(name, head_dir / "true.yaml")}
    out = {"calibrate_s": t_cal,
           "recorded_modes": _class_modes(test["traces"], test["labels"], float(test["sample_rate_hz"]))}
    for kind, prof in profiles.items():
        tag = kind.replace("calibrated + ", "calibrated_")
        model = head_dir / f"model_{tag}.joblib"
        train_args = ["train", "--profile", prof, "--out", model, "--seed", seed, *_draws(posterior_draws)]
        if n_per_class:
            train_args += ["--n-per-class", n_per_class]
        _, t_train = _inkdiag(*train_args, log=log)
        _inkdiag("label", head_dir / "test.npz", "--model", model, "--out", head_dir / f"labels_{tag}.csv", log=log)
        _inkdiag("label", head_dir / "odd.npz", "--model", model, "--out", head_dir / f"odd_{tag}.csv", log=log)
        _inkdiag("estimate", head_dir / "dried.npz", "--profile", prof, "--out", head_dir / f"fm_{tag}.csv", log=log)
        fd, fi, per, n_invalid, unknown, wrong = _scores(head_dir / f"labels_{tag}.csv", test["labels"])
        med, p90, n_nan = _dmu_errors(head_dir / f"fm_{tag}.csv", d_mu_true)
        # the profile's own simulation of the classes (what its model was trained on), seed of its own
        profile = HeadProfile.load(prof)
        sim = profile.simulate({c: per_class for c in MODE_CLASSES}, seed=seed + 3)
        modes = _class_modes(sim.traces, sim.labels, profile.sample_rate_hz)
        out[kind] = {"fd": fd, "fi": fi, "per": per, "unknown": unknown, "wrong": wrong, "modes": modes,
                     "odd_unknown": _unknown_share(head_dir / f"odd_{tag}.csv"), "invalid": n_invalid, "dmu_median": med,
                     "dmu_p90": p90,
                     "dmu_missing": n_nan, "train_s": t_train}
    # the calibrated profile again, with each nozzle's commissioning baseline
    prof, model, base = profiles["calibrated"], head_dir / "model_baselines.joblib", head_dir / "baselines.npz"
    train_args = ["train", "--profile", prof, "--out", model, "--baseline", "--seed", seed,
                  *_draws(posterior_draws)]
    if n_per_class:
        train_args += ["--n-per-class", n_per_class]
    _, t_train = _inkdiag(*train_args, log=log)
    _inkdiag("baseline", head_dir / "commission.npz", "--profile", prof, "--out", base, log=log)
    _inkdiag("label", head_dir / "test.npz", "--model", model, "--baselines", base,
             "--out", head_dir / "labels_baselines.csv", log=log)
    _inkdiag("label", head_dir / "odd.npz", "--model", model, "--baselines", base, "--out", head_dir / "odd_baselines.csv",
             log=log)
    _inkdiag("estimate", head_dir / "dried.npz", "--profile", prof, "--baselines", base,
             "--out", head_dir / "fm_baselines.csv", log=log)
    fd, fi, per, n_invalid, unknown, wrong = _scores(head_dir / "labels_baselines.csv", test["labels"])
    med, p90, n_nan = _dmu_errors(head_dir / "fm_baselines.csv", d_mu_true)
    out[BASELINES] = {"fd": fd, "fi": fi, "per": per, "unknown": unknown, "wrong": wrong, "invalid": n_invalid,
                      "odd_unknown": _unknown_share(head_dir / "odd_baselines.csv"),
                      "dmu_median": med, "dmu_p90": p90, "dmu_missing": n_nan, "train_s": t_train}
    cal = HeadProfile.load(profiles["calibrated"])
    true = HeadProfile.load(profiles["true"])
    out["mode"] = {"true": true.healthy_mode(), "calibrated": cal.healthy_mode()}
    out["params"] = {k: (true.channel.get(k), cal.channel.get(k)) for k in ("r_r", "L_r", "B_act", "b")}
    out["calibrated_split"] = _split_errors(cal.channel, fh.FOREIGN_HEADS[name]["channel"])
    out["blocked_split"] = _split_errors(HeadProfile.load(profiles[BLOCKED]).channel, fh.FOREIGN_HEADS[name]["channel"])
    out["empty_split"] = _split_errors(HeadProfile.load(profiles[EMPTY]).channel, fh.FOREIGN_HEADS[name]["channel"])
    out["sampling"] = (true.sample_rate_hz, true.n_samples)
    return out


def run_seed(name, work, *, per_class, n_per_class, seed, log, posterior_draws=None):
    """The calibrated workflow alone (calibrate, train, label) on recordings and training of ``seed``."""
    d = work / f"{name}_seed{seed}"
    d.mkdir(parents=True, exist_ok=True)
    fh.write_nominal_yaml(d / "nominal.yaml", name)
    fh.write_recording(d / "healthy.npz", fh.simulate_foreign(name, {"healthy_nozzle": 300}, seed))
    test = fh.simulate_foreign(name, {c.value: per_class for c in FaultClass}, seed + 1)
    fh.write_recording(d / "test.npz", test)
    fh.write_recording(d / "blocked.npz", fh.simulate_foreign(name, {"fully_blocked": N_BLOCKED}, seed + 6))
    fh.write_recording(d / "empty.npz", fh.simulate_foreign(name, {"empty_channel_1": N_EMPTY}, seed + 7))
    out = {}
    for kind, extra in (("calibrated", ()), (BLOCKED, ("--blocked", d / "blocked.npz")),
                        (EMPTY, ("--empty", d / "empty.npz"))):
        tag = kind.replace("calibrated + ", "calibrated_")
        _inkdiag("calibrate", d / "healthy.npz", "--nominal", d / "nominal.yaml", *extra, "--out", d / f"{tag}.yaml",
                 log=log)
        train_args = ["train", "--profile", d / f"{tag}.yaml", "--out", d / f"{tag}.joblib", "--seed", seed,
                      *_draws(posterior_draws)]
        if n_per_class:
            train_args += ["--n-per-class", n_per_class]
        _inkdiag(*train_args, log=log)
        _inkdiag("label", d / "test.npz", "--model", d / f"{tag}.joblib", "--out", d / f"{tag}.csv", log=log)
        fd, fi, per, n_invalid, _, wrong = _scores(d / f"{tag}.csv", test["labels"])
        out[kind] = {"fd": fd, "fi": fi, "per": per, "wrong": wrong, "invalid": n_invalid,
                     **_split_errors(HeadProfile.load(d / f"{tag}.yaml").channel, fh.FOREIGN_HEADS[name]["channel"])}
    return out


def _seed_runs(r, seed):
    """Per seed (the main run's first), ``{"calibrated": ..., BLOCKED: ..., EMPTY: ...}``: scores with the split
    errors."""
    main = {kind: {**r[kind], **r[split]} for kind, split in (("calibrated", "calibrated_split"),
                                                              (BLOCKED, "blocked_split"), (EMPTY, "empty_split"))}
    return {seed: main, **r["seeds"]}


def _split_errors(cal, true):
    """Relative errors of the calibrated restrictor inertance (rho L_r / (pi r_r^2)) and actuator compliance."""
    return {"I_r_err": (cal["L_r"] / true["L_r"]) / (cal["r_r"] / true["r_r"]) ** 2 - 1,
            "B_act_err": cal["B_act"] / true["B_act"] - 1}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--heads", nargs="+", default=["default", "h20", "h16", "h12", "h5"])
    ap.add_argument("--per-class", type=int, default=150, help="test traces per class and head")
    ap.add_argument("--n-per-class", type=int, default=N_PER_CLASS,
                    help="training traces per class (default: %(default)s, inkdiag train's)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--posterior-draws", type=int, default=None,
                    help="inkdiag train --posterior-draws for every model (default: inkdiag train's)")
    ap.add_argument("--other-seeds", type=int, nargs="*", default=[],
                    help="seeds of further calibrated runs per head (calibrate, train, label only)")
    ap.add_argument("--keep", action="store_true", help="keep the work files under reports/heads_work/")
    args = ap.parse_args(argv)
    unknown = [h for h in args.heads if h not in fh.FOREIGN_HEADS]
    if unknown:
        ap.error(f"unknown head {unknown[0]!r}; tests/foreign_head.py has {', '.join(fh.FOREIGN_HEADS)}")
    work = Path(tempfile.mkdtemp(prefix="inkdiag_heads_"))
    _WORK[0] = str(work)
    log: list[str] = []
    results = {}
    t0 = time.perf_counter()
    try:
        for name in args.heads:
            print(f"head {name} ...", file=sys.stderr, flush=True)
            results[name] = run_head(name, work, per_class=args.per_class, n_per_class=args.n_per_class,
                                     posterior_draws=args.posterior_draws,
                                     seed=args.seed, log=log)
            results[name]["seeds"] = {s: run_seed(name, work, per_class=args.per_class, n_per_class=args.n_per_class,
                                                  posterior_draws=args.posterior_draws, seed=s, log=log)
                                        for s in args.other_seeds}
    finally:
        if args.keep:
            dest = out_path("heads_work")
            shutil.rmtree(dest, ignore_errors=True)
            shutil.copytree(work, dest)
        shutil.rmtree(work, ignore_errors=True)
    elapsed = time.perf_counter() - t0
    write_report(results, args, log, elapsed)
    return 0


def _pct(x):
    return f"{100 * x:.1f}"


def _odd_cell(share, n_invalid):
    return _pct(share) + (f" ({n_invalid} invalid)" if n_invalid else "")


def write_report(results, args, log, elapsed):
    today = datetime.date.today().isoformat()
    classes = [c.value for c in FaultClass]
    lines = [
        "# inkdiag on other printheads",
        "",
        f"{today}. `scripts/report heads --heads {' '.join(args.heads)} --per-class {args.per_class} --seed "
        f"{args.seed} --n-per-class {args.n_per_class}"
        + (f" --posterior-draws {args.posterior_draws}" if args.posterior_draws is not None else "")
        + (f" --other-seeds {' '.join(map(str, args.other_seeds))}" if args.other_seeds else "")
        + f"` ({elapsed / 60:.1f} min on the shared 2-core machine). Traces come from the independent "
        "simulator `tests/foreign_head.py`, not from inkdiag's; each head is calibrated from 300 of its "
        "healthy traces and a nominal profile (sampling, drive, rho, mu, r_n, L_n, V_ch, c), then trained, "
        "labelled and estimated with the `inkdiag` command ("
        + ("`inkdiag train` with its defaults but the seed: a calibrated profile's rows spread over "
           f"{POSTERIOR_DRAWS} restrictors within calibration's own scatter"
           if args.posterior_draws is None else f"`inkdiag train --posterior-draws {args.posterior_draws}`")
        + ", `docs/calibration.md`). *calibrated*: the profile `inkdiag calibrate` wrote; *calibrated + blocked*: "
        "`inkdiag calibrate --blocked` with 50 recorded traces of the head's fully "
        "blocked nozzles as well, which pin the restrictor; *calibrated + empty*: `inkdiag calibrate --empty` with 50 "
        "recorded traces of the head's empty (dry) channels as well, which give the actuator's own resonance (the "
        "empty-channel classes); *true*: the head's real channel and sensor, to show what "
        "calibration costs; *calibrated + "
        "baselines*: the calibrated profile, each nozzle's healthy baseline from a commissioning recording (8 "
        "healthy frames of every nozzle, `inkdiag baseline`; the test rows are later frames of the same nozzles), "
        "a model trained with `--baseline`, and `--baselines` for label and estimate.",
        "",
        "Targets (issue 14) with the calibrated profile: FD >= 98 %, FI >= 90 % with every class >= 75 %, "
        "d_mu median relative error <= 10 %.",
        "",
        "## Summary",
        "",
    ]
    rows = []
    for name, r in results.items():
        fs, n = r["sampling"]
        for kind in KINDS:
            k = r[kind]
            worst = min(k["per"], key=k["per"].get)
            rows.append([name if kind == "calibrated" else "", f"{fs / 1e6:g} MHz x {n}" if kind == "calibrated" else "",
                         kind, _pct(k["fd"]), _pct(k["fi"]), f"{worst} {_pct(k['per'][worst])}",
                         _pct(k["dmu_median"]), _pct(k["dmu_p90"]), k["invalid"] + k["dmu_missing"]])
    lines += [md_table(["head", "sampling", "profile", "FD %", "FI %", "weakest class %", "d_mu median err %",
                        "d_mu P90 err %", "invalid / not estimated"], rows), ""]
    lines += ["## FI per class (%)", ""]
    header = ["class"] + [f"{name} {kind}" for name in results for kind in KINDS]
    rows = [[c] + [_pct(results[name][kind]["per"].get(c, float("nan"))) for name in results
                   for kind in KINDS] for c in classes]
    lines += [md_table(header, rows), ""]
    lines += ["## Known classes called `unknown` (%)", "",
              "The open-set layer (`inkdiag train`'s default `--unknown-rate 0.01`) on these heads' known classes: "
              "traces of another generator than the one the layer was calibrated on (our simulator), so its "
              "guarantee (exchangeable rows) does not cover them; a class's rate here is what that shift costs.", ""]
    rows = [[c] + [_pct(results[name][kind]["unknown"].get(c, float("nan"))) for name in results
                   for kind in KINDS] for c in classes]
    lines += [md_table(header, rows), ""]
    lines += ["## Off-class traces called `unknown` (%)", "",
              f"{N_ODD} single damped sinusoids per head (`odd_traces`: frequency 0.2-5 x the recorded healthy mode, "
              "damping ratio 0.005-0.3, amplitude 0.3-3 x the recorded healthy one within the ADC's range, the "
              "head's sensor noise and ADC), labelled by each run's model (*calibrated + baselines*: as nozzles "
              f"0-{N_ODD - 1} with their commissioning baselines, the baseline branch). Most are unlike every class; a draw "
              "near a class's own mode and damping is not, so 100 % is not the ideal. Share of the valid rows; "
              "rows screening refused in brackets where there are any.", ""]
    lines += [md_table(["head"] + list(KINDS), [[name] + [_odd_cell(*results[name][kind]["odd_unknown"]) for kind in KINDS]
                                                for name in results]), ""]
    if args.other_seeds:
        lines += ["## The calibrated profile, seed by seed", "",
                  "The calibrated workflow (calibrate on 300 healthy traces, train, label) on other recordings of "
                  "each head and another training seed (`--other-seeds`; each test row its own nozzle). The "
                  "restrictor inertance (rho L_r / (pi r_r^2)) and the actuator compliance B_act calibration fitted, "
                  "against the true head's: healthy traces pin their combination (the healthy mode), not each "
                  "(`reports/restrictor.md`).", ""]
        rows = []
        for name, r in results.items():
            for seed, runs in _seed_runs(r, args.seed).items():
                for kind, k in runs.items():
                    worst = min(k["per"], key=k["per"].get)
                    rows.append([name if seed == args.seed and kind == "calibrated" else "",
                                 seed if kind == "calibrated" else "", kind, _pct(k["fd"]), _pct(k["fi"]),
                                 f"{worst} {_pct(k['per'][worst])}", *[_pct(k["per"][c]) for c in SPLIT_CLASSES],
                                 f"{100 * k['I_r_err']:+.1f}", f"{100 * k['B_act_err']:+.1f}"])
        lines += [md_table(["head", "seed", "profile", "FD %", "FI %", "weakest class %", *SPLIT_CLASSES,
                            "I_r error %", "B_act error %"], rows), ""]
        lines += ["Which of these classes loses rows follows the sign of the fitted restrictor inertance's error: "
                  "too small, and recorded partially blocked traces look like the model's deeply dried ones; too "
                  "large, and recorded dried traces look like the model's partially blocked ones. " + "; ".join(
                      f"{name}: I_r error {min(ks):+.1f} to {max(ks):+.1f} %, weakest class {min(ws):.1f} to "
                      f"{max(ws):.1f} %" for name, r in results.items()
                      for runs in [[v["calibrated"] for v in _seed_runs(r, args.seed).values()]]
                      for ks, ws in [([100 * k["I_r_err"] for k in runs], [100 * min(k["per"].values()) for k in runs])])
                  + ". With 50 fully blocked traces (`inkdiag calibrate --blocked`): " + "; ".join(
                      f"{name}: I_r error {min(ks):+.1f} to {max(ks):+.1f} %, weakest class {min(ws):.1f} to "
                      f"{max(ws):.1f} %, FI {min(fs):.1f} to {max(fs):.1f} %" for name, r in results.items()
                      for runs in [[v[BLOCKED] for v in _seed_runs(r, args.seed).values()]]
                      for ks, ws, fs in [([100 * k["I_r_err"] for k in runs], [100 * min(k["per"].values()) for k in runs],
                                          [100 * k["fi"] for k in runs])])
                  + ". With 50 empty-channel traces (`inkdiag calibrate --empty`): " + "; ".join(
                      f"{name}: empty_channel_1 {min(es):.1f} to {max(es):.1f} % (calibrated alone: {min(cs):.1f} to "
                      f"{max(cs):.1f} %), weakest class {min(ws):.1f} to {max(ws):.1f} %, FI {min(fs):.1f} to "
                      f"{max(fs):.1f} %" for name, r in results.items()
                      for seeds in [list(_seed_runs(r, args.seed).values())]
                      for es, cs, ws, fs in [([100 * v[EMPTY]["per"]["empty_channel_1"] for v in seeds],
                                              [100 * v["calibrated"]["per"]["empty_channel_1"] for v in seeds],
                                              [100 * min(v[EMPTY]["per"].values()) for v in seeds],
                                              [100 * v[EMPTY]["fi"] for v in seeds])]) + ".", ""]
    lines += ["## Calibration: fitted against true", ""]
    rows = []
    for name, r in results.items():
        (ft, zt), (fc, zc) = r["mode"]["true"], r["mode"]["calibrated"]
        rows.append([name, "healthy mode (kHz)", f"{ft / 1e3:.2f}", f"{fc / 1e3:.2f}", f"{100 * (fc / ft - 1):+.2f}"])
        rows.append(["", "damping ratio", f"{zt:.4f}", f"{zc:.4f}", f"{100 * (zc / zt - 1):+.1f}"])
        for key, (t, c) in r["params"].items():
            rows.append(["", key, f"{t:.4g}", f"{c:.4g}", f"{100 * (c / t - 1):+.1f}"])
        rows.append(["", "calibrate time (s)", "", f"{r['calibrate_s']:.1f}", ""])
    lines += [md_table(["head", "quantity", "true", "calibrated", "error %"], rows), ""]
    lines += ["## Where the errors go", "",
              "Per class: its median dominant mode (frequency kHz / damping ratio, `extract_kpis`, over the rows "
              "screening accepts) in the head's test recording and in the profile's own simulation of that class "
              "(what the model was trained on), and the wrong label given most often, with its share (%) of the "
              "class's rows (`invalid` counts as wrong, as in the scores above).", ""]
    rows = []
    for name, r in results.items():
        for c in MODE_CLASSES:
            rec = r["recorded_modes"].get(c)
            if rec is None:
                continue
            row = [name if c == MODE_CLASSES[0] else "", c, f"{rec[0] / 1e3:.1f} / {rec[1]:.3f}"]
            for kind in ("true", "calibrated"):
                f_sim, z_sim = r[kind]["modes"][c]
                wrong = r[kind]["wrong"].get(c)
                row += [f"{f_sim / 1e3:.1f} / {z_sim:.3f} ({100 * (f_sim / rec[0] - 1):+.1f} %)",
                        f"{wrong[0]} {_pct(wrong[1])}" if wrong else "-"]
            rows.append(row)
    lines += [md_table(["head", "class", "recorded", "simulated, true profile (freq. vs recorded)",
                        "most frequent wrong label (%), true", "simulated, calibrated profile (freq. vs recorded)",
                        "most frequent wrong label (%), calibrated"], rows), ""]
    lines += [
        "## Reading it",
        "",
        "- *invalid / not estimated*: rows screening refused (for instance a trace clipped at the ADC's rails, "
        "which the 10-bit +-2 V sensor of h5 produces) or whose estimate is not finite. In FD and FI an "
        "invalid row counts as wrong; the d_mu errors leave out the rows not estimated.",
        "- *true*: the head's true channel, drive, sensor and spreads (`tests/foreign_head.py`), plus the "
        "spreads a calibrated profile trains over for the physics healthy traces cannot show (the empty "
        "channel's actuator, `calibration.UNSEEN_PHYSICS_SPREADS`), and the head's actuator resonance and "
        "damping (`channel.f_act`, `zeta_act`): the two rows differ by calibration only (which assumes the "
        "actuator and so trains over a wider resonance spread, `calibration.ASSUMED_ACTUATOR_RESONANCE_REL`). The foreign "
        "simulator's other fault constants (the ink film's loss, the ink-temperature law) stay unknown to both.",
        "- partially_blocked (a particle in the bore: resistance and inertance) and the dried classes "
        "(resistance only) overlap in frequency and damping where the head's spreads between nozzles and "
        "frames are wide. `reports/separability.md` (`scripts/report separability`) trains classifiers on "
        "each head's own traces: from single traces none reaches 75 % on h5's partially_blocked (42.0-57.0 %, "
        "gradient-boosted classifiers included), and h5's FI stays at 87.5-88.6 %; on h20's, inkdiag's forest "
        "gets 71.0 % (63.5 % with scikit-learn's default of 2 KPIs per split, the forest inkdiag had before "
        "2026-11-26), a gradient-boosted classifier on the KPIs 78.5 %; without the spreads every class is "
        "97.5-100 %; with each nozzle's own "
        "healthy baseline, 68.0 % (h5) and 85.5 % (h20). Per-nozzle baselines (`inkdiag train --baseline`, "
        "`inkdiag label --baselines`) are the remedy where a head has them: the *calibrated + baselines* rows "
        "are that remedy as a user gets it, the baseline branch trained on inkdiag's simulation of the "
        "calibrated head (a simulated nozzle against its simulated healthy twin), not on the head's own "
        "traces, and applied to the foreign head's commissioning baselines.",
        "- d_mu with baselines: `estimate --baselines` takes each nozzle's healthy f_m reading (the raw `vp` "
        "estimate, `inkdiag_core.baselines.FM_METHOD`: the nozzle's own offset) off its `vp_cal` estimate. "
        "d_mu median / P90 error (%), calibrated -> calibrated + baselines: " + "; ".join(
            f"{name} {r['calibrated']['dmu_median'] * 100:.1f} / {r['calibrated']['dmu_p90'] * 100:.1f} -> "
            f"{r[BASELINES]['dmu_median'] * 100:.1f} / {r[BASELINES]['dmu_p90'] * 100:.1f}"
            for name, r in results.items()) + ".",
        "- d_mu truth: each trace's nozzle viscosity over its own channel's ink viscosity (at its "
        "temperature).",
        "- *Where the errors go*: partially_blocked and the dried classes overlap on these heads even with the "
        "true profile (the *true* columns: each loses up to about a third of its rows to the other). What a "
        "calibrated profile adds is its restrictor error (healthy traces pin the healthy mode, not how the "
        "restrictor and the nozzle share it: `reports/restrictor.md`), which moves the modes of the blocked "
        "and dried classes, mostly in one direction per head; the fully blocked mode (the restrictor ringing "
        "with the chamber) shows it most directly. Where the calibrated deeply dried and partially blocked "
        "modes sit below the recorded ones, recorded deeply dried traces fall between the two and are often "
        "called partially_blocked; where they sit above, recorded partially blocked traces look like the "
        "model's deeply dried, and the loss moves from one class to the other.",
        "",
        "## Commands run",
        "",
        "`WORK` is a temporary directory; `tests/foreign_head.py` wrote its recordings and nominal profiles.",
        "",
        "```",
        *log,
        "```",
        "",
    ]
    out_path("heads.md").write_text("\n".join(lines))
    print(f"wrote {out_path('heads.md')}", file=sys.stderr)


if __name__ == "__main__":
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    sys.exit(main())
