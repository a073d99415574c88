"""FDI pipeline throughput against the floors of its stages, measured in one run.

    scripts/bench fdi [--n 20000] [--seed 0]

Times, on the same batch of simulated traces (all 12 classes): a bare
``scipy.fft.rfft`` pass (floor of any spectral feature), ``extract_kpis``,
``screen_traces`` (the labelling's invalid-row screening) against one
``max`` pass over the batch (the floor of reading every sample once), a
Random Forest's ``predict_proba`` on 7 ready-made features (floor of the
classifier), and whole fitted pipelines (raw traces -> label probabilities)
for KPI_Y, the rich feature set and KPI_Y + the nozzle's healthy baseline
(rows ``[trace, 7 baseline KPIs]``; the baselines themselves are computed once
per nozzle, not per frame), and ``forest_predict_proba`` against scikit-learn's
``predict_proba`` on the KPI_Y pipeline, and the whole ``FaultDetector.label``
(100 trees like the pipelines here) with and without its open-set layer
(issue 16), as a ratio of the rf/kpi_y pipeline's throughput (the three timed
in turns, best of 5). Then the healthy gate
(:class:`inkdiag_core.HealthyGate`, issue 17): its ``screen`` on a realistic head
frame (``--head-nozzles`` nozzles, ``--faulty`` 2 % faulty by default, half the
healthy rows OK-check; references recorded by ``BaselineRecorder`` from 8 healthy
frames) against one ``max`` pass over the same frame, and ``FrameLabeller.label``
end to end on that frame in 200-nozzle messages (the default detector
``models/fdi_default.joblib``, trained if missing) with the baselines' references
(gate on) and without (gate off), and that per-row stage (screening and the gate) with
the compiled kernels against the numpy passes they replace, on one message and on eight, and
the KPIs compiled (spectrum steps and window fit) against numpy, on the gate's leftovers and on
1,600 rows, the spectrum steps alone, the open-set layer's unexplained fraction and p-values, and
the detector's forests walked by the compiled kernel against one ``tree_.predict`` per tree, and
``FaultDetector.label`` from the KPIs on in one compiled call against its numpy loop.
Prints traces/s and ratios; run it on one core
(``scripts/bench`` sets the thread variables). ``--gate-only`` skips all but the gate.
"""

import argparse
import contextlib
import time

import numpy as np
import scipy.fft

from inkdiag_core import (FaultClass, FaultDetector, baseline_kpis, extract_kpis, healthy_twin_frames,
                          make_fdi_pipeline, simulate, with_baseline)
from inkdiag_core import _kernels, openset, spectral_fit
from inkdiag_core import kpis as kpis_module
from inkdiag_core.fdi import forest_predict_proba
from inkdiag_core.kpis import kpis_of_checked
from inkdiag_core.screening import screen_traces


def best_of(fn, repeats=3):
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=20000, help="traces in the timed batch")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--head-nozzles", type=int, default=2656, help="nozzles of the gate's head frame")
    ap.add_argument("--gate-only", action="store_true", help="only the healthy gate and FrameLabeller rows")
    ap.add_argument("--faulty", type=float, default=0.02, help="faulty fraction of the gate's head (1: worst case)")
    ns = ap.parse_args()
    if ns.gate_only:
        gate_bench(ns.head_nozzles, ns.seed, ns.faulty)
        return
    per = max(ns.n // 12, 1)
    batch = simulate({c: per for c in FaultClass}, seed=ns.seed)
    X = batch.traces
    train = simulate({c: 200 for c in FaultClass}, seed=ns.seed + 1)
    n = X.shape[0]
    print(f"batch: {n} traces x {X.shape[1]} samples (float32, 12 classes); training set "
          f"{len(train)} traces; best of 3")
    rows = {}
    rows["scipy.fft.rfft (floor)"] = best_of(lambda: scipy.fft.rfft(X, axis=1))
    rows["extract_kpis"] = best_of(lambda: extract_kpis(X, 10e6))
    rows["X.max(axis=1) (floor: one read of each sample)"] = best_of(lambda: X.max(axis=1))
    rows["screen_traces (invalid-row screening)"] = best_of(lambda: screen_traces(X))
    kpi_pipe = make_fdi_pipeline("rf", "kpi_y").fit(train.traces, train.label_values())
    feats = kpi_pipe.named_steps["features"].transform(X)
    clf = kpi_pipe.named_steps["classifier"]
    rows["RF predict_proba on 7 features (floor)"] = best_of(lambda: clf.predict_proba(feats))
    rows["pipeline rf/kpi_y (traces -> proba)"] = best_of(lambda: kpi_pipe.predict_proba(X))
    rich = make_fdi_pipeline("rf", "rich").fit(train.traces, train.label_values())
    rows["pipeline rf/rich (traces -> proba)"] = best_of(lambda: rich.predict_proba(X))
    knn = make_fdi_pipeline("knn", "kpi_y").fit(train.traces, train.label_values())
    rows["pipeline knn/kpi_y (traces -> proba)"] = best_of(lambda: knn.predict_proba(X))
    # per-nozzle baselines are computed once per nozzle (at commissioning), not per frame:
    # the per-frame input is [trace, the nozzle's 7 baseline KPIs]
    def with_base(sim, sim_seed):
        _, frames = healthy_twin_frames(len(sim), seed=sim_seed, n_frames=4, noise_std_v=sim.noise_std_v)
        return with_baseline(sim.traces, baseline_kpis(frames, 10e6).astype(np.float32))
    Xb = with_base(batch, ns.seed)
    based = make_fdi_pipeline("rf", "kpi_y+baseline").fit(with_base(train, ns.seed + 1), train.label_values())
    rows["pipeline rf/kpi_y+baseline (rows -> proba)"] = best_of(lambda: based.predict_proba(Xb))
    # the whole FaultDetector.label with its open-set layer (issue 16) vs the same detector without it
    ytr = train.label_values()
    forest = {"n_estimators": 100, "min_samples_leaf": 1, "max_features": "sqrt"}  # the pipelines' forest
    det_open = FaultDetector(**forest, unknown_rate=0.01).fit(train.traces, ytr)
    det_closed = FaultDetector(**forest, unknown_rate=None).fit(train.traces, ytr)
    # timed taking turns with rf/kpi_y (best of 5 each), so a load change on a shared machine hits all three
    turns = {"ref": lambda: kpi_pipe.predict_proba(X), "open": lambda: det_open.label(X),
             "closed": lambda: det_closed.label(X)}
    best = dict.fromkeys(turns, float("inf"))
    for _ in range(5):
        for key, fn in turns.items():
            t0 = time.perf_counter()
            fn()
            best[key] = min(best[key], time.perf_counter() - t0)
    rows["FaultDetector.label rf/kpi_y, open-set layer"] = best["open"]
    rows["FaultDetector.label rf/kpi_y, no open-set layer"] = best["closed"]
    rows["forest_predict_proba, kpi_y pipeline"] = best_of(
        lambda: forest_predict_proba(clf, kpi_pipe.named_steps["features"].transform(X)))
    width = max(len(k) for k in rows)
    for name, t in rows.items():
        print(f"{name:<{width}} : {n / t:>12,.0f} traces/s  ({1e3 * t:8.1f} ms)")
    fft = rows["scipy.fft.rfft (floor)"]
    for name in ("extract_kpis", "pipeline rf/kpi_y (traces -> proba)", "pipeline rf/rich (traces -> proba)"):
        print(f"ratio {name} / rfft: {fft / rows[name]:.3f}")
    print(f"ratio screen_traces / one max pass: "
          f"{rows['X.max(axis=1) (floor: one read of each sample)'] / rows['screen_traces (invalid-row screening)']:.3f}")
    print(f"ratio pipeline rf/kpi_y / RF-on-features floor: "
          f"{rows['RF predict_proba on 7 features (floor)'] / rows['pipeline rf/kpi_y (traces -> proba)']:.3f}")
    print(f"ratio forest_predict_proba / sklearn predict_proba, kpi_y pipeline: "
          f"{rows['pipeline rf/kpi_y (traces -> proba)'] / rows['forest_predict_proba, kpi_y pipeline']:.2f}x faster")
    for name, key in (("FaultDetector.label rf/kpi_y, open-set layer", "open"),
                      ("FaultDetector.label rf/kpi_y, no open-set layer", "closed")):
        print(f"ratio {name} / pipeline rf/kpi_y (timed in turns): {best['ref'] / best[key]:.3f}x the throughput")
    for name, pipe, rows_ in (("rf/rich", rich, X), ("rf/kpi_y+baseline", based, Xb)):
        acc = np.mean(pipe.predict(rows_) == batch.label_values())
        print(f"accuracy of {name} on the timed batch: {100 * acc:.1f}% (trained on {len(train)} traces)")
    gate_bench(ns.head_nozzles, ns.seed, ns.faulty)


def gate_bench(n: int, seed: int, faulty: float = 0.02, repeats: int = 5):
    """The healthy gate against one max pass, and FrameLabeller rows/s with and without references."""
    import dataclasses
    from pathlib import Path

    from inkdiag_core import BaselineRecorder, FrameLabeller, HealthyGate, load_detector, simulate_nozzles
    from inkdiag_core.model_cache import ensure_default_model

    rng = np.random.default_rng(seed)
    from inkdiag_core.faults import HEALTHY_CLASSES, HEALTHY_VALUES

    faults = [c.value for c in FaultClass if c not in HEALTHY_CLASSES]
    classes = np.where(rng.random(n) < 0.5, FaultClass.HEALTHY_NOZZLE.value, FaultClass.OK_SIGNAL.value).astype(object)
    bad = rng.choice(n, size=max(1, round(faulty * n)), replace=False)
    classes[bad] = [faults[i] for i in rng.integers(len(faults), size=bad.size)]
    head = 9_100 + seed
    rec = BaselineRecorder(n_frames=8)
    for f in range(8):
        rec.add(0, simulate_nozzles(["healthy_nozzle"] * n, seed=head, frame_seed=[head, f]).traces)
    base = rec.baselines()
    frame = simulate_nozzles(classes, seed=head, frame_seed=[head, 100]).traces.astype(np.float32)
    gate = HealthyGate(base)
    got = gate.screen(frame, 0)
    t = {"X.max(axis=1) (one read of each sample)": best_of(lambda: frame.max(axis=1), repeats),
         "HealthyGate.screen (whole frame, one call)": best_of(lambda: gate.screen(frame, 0), repeats)}
    root = Path(__file__).resolve().parents[2]
    det = load_detector(ensure_default_model(root / "models" / "fdi_default.joblib"))
    msgs = [frame[a:a + 200] for a in range(0, n, 200)]
    firsts = list(range(0, n, 200))
    with_ref = FrameLabeller(det, base, max_abs_v=10.0)
    without = FrameLabeller(det, dataclasses.replace(base, reference=None), max_abs_v=10.0)

    def per_message(lab):
        for m, f0 in zip(msgs, firsts):
            lab.label([m], [f0])

    t["FrameLabeller.screen (screening, gate, rows left gathered), per 200-nozzle message"] = best_of(
        lambda: [with_ref.screen([m], [f0]) for m, f0 in zip(msgs, firsts)], repeats)
    t["FrameLabeller.screen, all messages in one call"] = best_of(lambda: with_ref.screen(msgs, firsts), repeats)
    t["FrameLabeller, baselines with references (gate), per 200-nozzle message"] = best_of(
        lambda: per_message(with_ref), repeats)
    t["FrameLabeller, baselines without references, per 200-nozzle message"] = best_of(
        lambda: per_message(without), repeats)
    t["FrameLabeller, with references (gate), all messages in one call"] = best_of(
        lambda: with_ref.label(msgs, firsts), repeats)
    t["FrameLabeller, without references, all messages in one call"] = best_of(
        lambda: without.label(msgs, firsts), repeats)
    print(f"\nhealthy gate: head frame of {n} nozzles x {frame.shape[1]} samples, {bad.size} faulty; "
          f"{int(got.cleared.sum())} rows cleared ({100 * got.cleared.mean():.1f} %); best of {repeats}")
    width = max(len(k) for k in t)
    for name, v in t.items():
        print(f"{name:<{width}} : {n / v:>12,.0f} traces/s  ({1e3 * v:8.2f} ms)")
    mx = t["X.max(axis=1) (one read of each sample)"]
    print(f"ratio HealthyGate.screen / one max pass: {mx / t['HealthyGate.screen (whole frame, one call)']:.3f}")
    print(f"ratio FrameLabeller.screen / one max pass (the node's first stage: screening, the gate, the rows left "
          f"copied out): per message {mx / t['FrameLabeller.screen (screening, gate, rows left gathered), per 200-nozzle message']:.3f}"
          f", one call {mx / t['FrameLabeller.screen, all messages in one call']:.3f}")
    a = t["FrameLabeller, baselines with references (gate), per 200-nozzle message"]
    b = t["FrameLabeller, baselines without references, per 200-nozzle message"]
    print(f"ratio FrameLabeller with gate / without, per message: {b / a:.2f}x faster")
    a = t["FrameLabeller, with references (gate), all messages in one call"]
    b = t["FrameLabeller, without references, all messages in one call"]
    print(f"ratio FrameLabeller with gate / without, one call: {b / a:.2f}x faster")
    # the gate labels the rows it clears with its own healthy class; every other row takes the same model
    gl, wl = with_ref.label(msgs, firsts), without.label(msgs, firsts)
    g_cls, w_cls = (np.concatenate([r.classes for r in x]) for x in (gl, wl))
    cleared = np.concatenate([r.gate_cleared for r in gl])
    differ = g_cls != w_cls
    model_fault = cleared & ~np.isin(w_cls, HEALTHY_VALUES)
    sim_healthy = np.isin(classes, HEALTHY_VALUES)
    print(f"labels with the gate against without: {int(differ.sum())} of {n} rows differ, "
          f"{int((differ & ~cleared).sum())} of them among the rows the gate left to the model, "
          f"{int((differ & cleared & ~model_fault).sum())} only in the healthy class; of the {int(cleared.sum())} "
          f"rows the gate cleared the model calls {int(model_fault.sum())} faulty: "
          f"{int((model_fault & sim_healthy).sum())} simulated healthy (the model's false alarms), "
          f"{int((model_fault & ~sim_healthy).sum())} simulated faulty (faults the gate cleared)")
    pass_bench(with_ref, msgs, firsts, frame, gate, base, repeats)
    kernel_bench(frame, gate, repeats)
    forest_bench(det, base, frame, gate, repeats)
    tail_bench(det, base, frame, gate, repeats)


def pass_bench(lab, msgs, firsts, frame, gate, base, repeats: int = 5):
    """What a classifier pass costs for its size: the head's messages labelled in passes of 1, 2, 4, 7 and
    14 messages (``FrameLabeller.label``, the gate on), and the detector's call on the gate's leftovers."""
    print(f"\nFrameLabeller with references, the head's {len(msgs)} messages in passes of k messages "
          f"(best of {repeats}): time per message")
    for k in (1, 2, 4, 7, 14):
        def passes():
            for s in range(0, len(msgs), k):
                lab.label(msgs[s:s + k], firsts[s:s + k])
        print(f"  k = {k:>2}: {1e3 * best_of(passes, repeats) / len(msgs):7.3f} ms")
    left = np.flatnonzero(~gate.screen(frame, 0).cleared)
    det, rounds = lab.detector, 50
    print(f"FaultDetector.label on the gate's leftovers, baseline branch (best of {repeats} x {rounds} calls)")
    for r in (1, 8, 64):
        at = left[np.arange(r) % left.size]
        rows, (_, kp) = np.ascontiguousarray(frame[at]), base.lookup(at)
        t = best_of(lambda: [det.label(rows, baseline_kpis=kp) for _ in range(rounds)], repeats)
        print(f"  {r:>3} rows: {1e3 * t / rounds:7.3f} ms per call")


@contextlib.contextmanager
def numpy_passes():
    """Screening, the gate's row sums, the KPIs' spectrum steps and window fit and the open-set
    layer's unexplained fraction as numpy passes instead of the compiled kernels."""
    from inkdiag_core import gate, kpis, openset, screening, spectral_fit

    saved = (screening._screen_codes, gate._row_sums, kpis._fit_windows, kpis._fit_spectra,
             openset.unexplained_fraction)
    screening._screen_codes, gate._row_sums = screening._screen_codes_numpy, gate._row_sums_numpy
    kpis._fit_windows, kpis._fit_spectra = spectral_fit.fit_windows, kpis._fit_spectra_numpy
    openset.unexplained_fraction = openset._unexplained_fraction_numpy
    try:
        yield
    finally:
        (screening._screen_codes, gate._row_sums, kpis._fit_windows, kpis._fit_spectra,
         openset.unexplained_fraction) = saved


def kernel_bench(frame, gate, repeats: int = 5, rounds: int = 20):
    """The labeller's per-row stage (screen_traces + HealthyGate.screen on every row) with the compiled
    kernels (inkdiag_core._kernels) against the numpy passes they replace, in turns, same rows."""
    rows = {"one message (200 rows)": frame[:200], "a classifier pass (1,600 rows)": frame[:1600]}
    print(f"\nper-row stage, screen_traces + HealthyGate.screen: compiled kernels against numpy passes "
          f"(best of {repeats} x {rounds} calls, in turns)")
    for name, x in rows.items():
        x = np.ascontiguousarray(x)

        def stage():
            for _ in range(rounds):
                screen_traces(x, max_abs_v=10.0)
                gate.screen(x, 0)

        with numpy_passes():
            ref = (screen_traces(x, max_abs_v=10.0)[1], gate.screen(x, 0).cleared)
        got = (screen_traces(x, max_abs_v=10.0)[1], gate.screen(x, 0).cleared)
        t_np, t_k = _in_turns(_with_numpy_passes(stage), stage, repeats)
        same = bool((ref[0] == got[0]).all() and (ref[1] == got[1]).all())
        print(f"  {name:<32}: numpy {1e3 * t_np / rounds:7.3f} ms, kernels {1e3 * t_k / rounds:7.3f} ms, "
              f"ratio {t_np / t_k:.2f}x faster; same reasons and cleared rows: {same}")
    print("the gate's verdict from the row sums (HealthyGate.codes, the labeller's compiled loop, against "
          "HealthyGate.decide's numpy passes)")
    for name, x in rows.items():
        x = np.ascontiguousarray(x)
        pos = gate.positions(np.arange(len(x)))
        sums = _kernels.row_sums(x, gate.references, np.where(pos >= 0, pos, 0))
        same = np.array_equal(gate.codes(*sums, pos) > 0, gate.decide(*sums, pos).cleared)
        t_np, t_k = _in_turns(lambda: [gate.decide(*sums, pos) for _ in range(rounds)],
                              lambda: [gate.codes(*sums, pos) for _ in range(rounds)], repeats)
        print(f"  {name:<32}: numpy {1e3 * t_np / rounds:7.3f} ms, kernel {1e3 * t_k / rounds:7.3f} ms, "
              f"ratio {t_np / t_k:.2f}x faster; same verdicts: {same}")
    # the detector's KPIs on what the gate leaves: ~70 rows per classifier pass of 8 messages (2 % faulty)
    left = np.ascontiguousarray(frame[~gate.screen(frame, 0).cleared])
    print(f"KPIs (kpis_of_checked: rfft, then the peak, the window, its fit and the KPIs) compiled against numpy "
          f"(best of {repeats} x {rounds} calls, in turns)")
    for name, x in ((f"the gate's leftovers ({min(72, len(left))} rows)", left[:72]),
                    ("a classifier pass (1,600 rows)", np.ascontiguousarray(frame[:1600]))):
        with numpy_passes():
            ref = kpis_of_checked(x, 10e6)
        got = kpis_of_checked(x, 10e6)

        def kpis():
            for _ in range(rounds):
                kpis_of_checked(x, 10e6)

        t_np, t_k = _in_turns(_with_numpy_passes(kpis), kpis, repeats)
        rel = float(np.max(np.abs(got - ref) / np.maximum(np.abs(ref), 1e-300)))
        print(f"  {name:<32}: numpy {1e3 * t_np / rounds:7.3f} ms, kernel {1e3 * t_k / rounds:7.3f} ms, "
              f"ratio {t_np / t_k:.2f}x faster; largest relative KPI difference {rel:.1e}")
    print(f"the KPIs' spectrum steps alone (kpis._fit_spectra: _kernels.kpis_of_spectra against numpy's peak, "
          f"window and KPI steps, the window fit compiled in both, same spectra, best of {repeats} x {rounds} calls, "
          "in turns)")
    for x in (left[:72], np.ascontiguousarray(frame[:200]), np.ascontiguousarray(frame[:1600])):
        spec, out = scipy.fft.rfft(x, axis=-1), np.empty((len(x), 7))
        with np.errstate(all="ignore"):
            t_np, t_k = _in_turns(
                lambda: [kpis_module._fit_spectra_numpy(spec, x.shape[1], 10e6, out) for _ in range(rounds)],
                lambda: [kpis_module._fit_spectra(spec, x.shape[1], 10e6, out) for _ in range(rounds)], repeats)
        print(f"  {len(x):>5} rows{'':<22}: numpy {1e3 * t_np / rounds:7.3f} ms, kernel {1e3 * t_k / rounds:7.3f} ms, "
              f"ratio {t_np / t_k:.2f}x faster")
    print(f"the open-set layer's unexplained fraction (openset.unexplained_fraction: _kernels.unexplained against "
          f"numpy's float32 blocks, best of {repeats} x {rounds} calls, in turns)")
    for x in (left[:72], np.ascontiguousarray(frame[:200]), np.ascontiguousarray(frame[:1600])):
        k = kpis_of_checked(x, 10e6)
        got, ref = openset.unexplained_fraction(x, k, 10e6), openset._unexplained_fraction_numpy(x, k, 10e6)
        t_np, t_k = _in_turns(lambda: [openset._unexplained_fraction_numpy(x, k, 10e6) for _ in range(rounds)],
                              lambda: [openset.unexplained_fraction(x, k, 10e6) for _ in range(rounds)], repeats)
        rel = float(np.nanmax(np.abs(got / ref - 1.0)))
        print(f"  {len(x):>5} rows{'':<22}: numpy {1e3 * t_np / rounds:7.3f} ms, kernel {1e3 * t_k / rounds:7.3f} ms, "
              f"ratio {t_np / t_k:.2f}x faster; largest relative difference {rel:.1e} (numpy's float32 sums)")
    print(f"the window fit alone (spectral_fit.fit_windows against _kernels.fit_windows, same windows, "
          f"best of {repeats} x {rounds} calls, in turns)")
    for x in (left[:72], np.ascontiguousarray(frame[:200]), np.ascontiguousarray(frame[:1600])):
        args = _windows(x)
        t_np, t_k = _in_turns(lambda: [spectral_fit.fit_windows(*args) for _ in range(rounds)],
                              lambda: [_kernels.fit_windows(*args) for _ in range(rounds)], repeats)
        print(f"  {len(x):>5} rows{'':<22}: numpy {1e3 * t_np / rounds:7.3f} ms, kernel {1e3 * t_k / rounds:7.3f} ms, "
              f"ratio {t_np / t_k:.2f}x faster")


def forest_bench(det, base, frame, gate, repeats: int = 5, rounds: int = 20):
    """The detector's forests (plain and baseline branch) in one compiled call (``_kernels.forest_proba``)
    against one ``tree_.predict`` call per tree (what ``forest_predict_proba`` did before), in turns, same rows;
    bit-identical: the kernel's against scikit-learn's ``predict_proba``."""
    from inkdiag_core.fdi import flat_forest, _per_tree_proba as _per_tree

    left = np.flatnonzero(~gate.screen(frame, 0).cleared)
    branches = [("plain", det.pipeline_, frame)]
    if det.baseline_pipeline_ is not None:
        _, kp = base.lookup(np.arange(frame.shape[0]))
        branches.append(("baseline", det.baseline_pipeline_, with_baseline(frame, kp.astype(np.float32))))
    print(f"the forest (forest_predict_proba's compiled walk of every tree against one tree_.predict per tree, "
          f"bit-identical, best of {repeats} x {rounds} calls, in turns)")
    for branch, pipe, rows in branches:
        clf = pipe[-1]
        for name, at in ((f"the gate's leftovers ({min(72, left.size)} rows)", left[:72]),
                         ("one message (200 rows)", np.arange(min(200, len(rows)))),
                         ("a classifier pass (1,600 rows)", np.arange(min(1600, len(rows))))):
            F = np.ascontiguousarray(pipe[:-1].transform(rows[at]), dtype=np.float32)
            flat = flat_forest(clf)
            same = np.array_equal(_kernels.forest_proba(F, *flat), clf.predict_proba(F))
            t_np, t_k = _in_turns(lambda: [_per_tree(clf, F) for _ in range(rounds)],
                                  lambda: [_kernels.forest_proba(F, *flat) for _ in range(rounds)], repeats)
            print(f"  {branch:<8} {name:<32}: per tree {1e3 * t_np / rounds:7.3f} ms, kernel {1e3 * t_k / rounds:7.3f} "
                  f"ms, ratio {t_np / t_k:.2f}x faster; bit-identical: {same}")
    print(f"the open-set layer's conformal p-values of the same scores (_kernels.p_values against one searchsorted "
          f"per class; ConformalOpenSet takes the kernel up to {openset._P_KERNEL_MAX_ROWS} rows, numpy beyond; "
          f"best of {repeats} x {rounds} calls, in turns)")
    for branch, pipe, rows in branches:
        layer = det.baseline_openset_ if branch == "baseline" else det.openset_
        if layer is None:
            continue
        for name, at in ((f"the gate's leftovers ({min(72, left.size)} rows)", left[:72]),
                         ("a classifier pass (1,600 rows)", np.arange(min(1600, len(rows))))):
            feats = pipe[0].transform(rows[at])
            with np.errstate(all="ignore"):
                F = det._openset_features(feats, frame[at], branch == "baseline")
            S = layer.scores(F)  # the p-value step alone, on the same scores
            args = (*layer._calibration_table(), np.asarray(layer.modelled_, dtype=bool))
            same = np.array_equal(_kernels.p_values(S, *args), layer._p_of_scores_numpy(S), equal_nan=True)
            t_np, t_k = _in_turns(lambda: [layer._p_of_scores_numpy(S) for _ in range(rounds)],
                                  lambda: [_kernels.p_values(S, *args) for _ in range(rounds)], repeats)
            print(f"  {branch:<8} {name:<32}: numpy {1e3 * t_np / rounds:7.3f} ms, kernel {1e3 * t_k / rounds:7.3f} "
                  f"ms, ratio {t_np / t_k:.2f}x faster; identical: {same}")



def tail_bench(det, base, frame, gate, repeats: int = 5, rounds: int = 20):
    """``FaultDetector.label`` from the KPIs on (the KPIs computed before, the same for both): one compiled
    call per branch (``_kernels.detector_tail``: features, forest, decision, open-set features, scores,
    p-values, unknown score) against the numpy loop it replaces, in turns, same rows; then the whole call."""
    import inkdiag_core.baselines.features as features_module
    import inkdiag_core.detector as detector_module

    left = np.flatnonzero(~gate.screen(frame, 0).cleared)
    if left.size == 0 or not base.lookup(np.arange(frame.shape[0]))[0].all():
        print("FaultDetector.label from the KPIs on: not timed (the gate left no rows, or a nozzle has no baseline)")
        return
    loop = lambda *a, **k: None  # noqa: E731 - the detector's loop: no compiled tail
    print(f"FaultDetector.label from the KPIs on, baseline branch (the compiled tail against the numpy loop; "
          f"the KPIs precomputed for both; best of {repeats} x {rounds} calls, in turns)")
    for whole in (False, True):
        if whole:
            print("the whole FaultDetector.label call (KPIs included), the same rows")
        for r in (8, min(72, left.size), 200, 1600):
            at = left[np.arange(r) % left.size] if r <= left.size else np.arange(r)
            rows, (_, kp) = np.ascontiguousarray(frame[at]), base.lookup(at)
            got = kpis_of_checked(rows, det.sample_rate_hz_)
            fixed = (lambda y, fs: got.copy()) if not whole else kpis_of_checked
            tail = type(det)._label_tail
            saved = features_module.kpis_of_checked, detector_module.kpis_of_checked
            features_module.kpis_of_checked = detector_module.kpis_of_checked = fixed
            try:
                def run(with_tail):
                    type(det)._label_tail = tail if with_tail else loop
                    try:
                        return [det.label(rows, baseline_kpis=kp) for _ in range(rounds)][-1]
                    finally:
                        type(det)._label_tail = tail
                a, b = run(True), run(False)
                same = all(np.array_equal(x, y, equal_nan=x.dtype.kind == "f") for x, y in zip(a, b))
                t_np, t_k = _in_turns(lambda: run(False), lambda: run(True), repeats)
            finally:
                features_module.kpis_of_checked, detector_module.kpis_of_checked = saved
            name = f"{r} rows" + (" (the gate's leftovers)" if r == min(72, left.size) else "")
            print(f"  {name:<40}: numpy {1e3 * t_np / rounds:7.3f} ms, kernel {1e3 * t_k / rounds:7.3f} ms, "
                  f"ratio {t_np / t_k:.2f}x faster; identical labels: {same}")


def _with_numpy_passes(fn):
    """``fn`` run under :func:`numpy_passes`."""
    def run():
        with numpy_passes():
            fn()
    return run


def _in_turns(baseline, kernel, repeats):
    """Best times (s) of two callables timed in turns, ``repeats`` times each."""
    t_np, t_k = float("inf"), float("inf")
    for _ in range(repeats):
        t_np = min(t_np, best_of(baseline, 1))
        t_k = min(t_k, best_of(kernel, 1))
    return t_np, t_k


def _windows(x):
    """The window fit's inputs for traces ``x``, as ``kpis._fit_chunk`` builds them."""
    from inkdiag_core.kpis import _peak_spectrum, _fit_window_inputs

    spec, m_peak, peak_power, _ = _peak_spectrum(x)
    Yw, start, _ = _fit_window_inputs(spec, m_peak, peak_power, x.shape[1])
    return Yw, start, m_peak, x.shape[1]


if __name__ == "__main__":
    main()
