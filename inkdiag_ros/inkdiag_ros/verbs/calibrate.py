"""``inkdiag calibrate``: a complete head profile from a nominal one and recorded healthy traces.

    inkdiag calibrate HEALTHY --nominal NOMINAL.yaml --out HEAD.yaml [--blocked BLOCKED [--blocked-labels CSV]]
                      [--empty EMPTY] [--report-dir DIR] [--name NAME]

Reads the recording (:func:`inkdiag_core.load_recording`), fits what the nominal
profile leaves out (:func:`inkdiag_core.calibration.calibrate`), writes the
complete profile and a fit report beside it: ``HEAD.fit.json`` (every number),
``HEAD.fit.md`` (a table for people) and ``HEAD.fit.png`` (recorded and fitted
traces overlaid; needs matplotlib, otherwise the report says it is missing).
See ``docs/calibration.md``.
"""

from __future__ import annotations

HELP = "fit a complete head profile to recorded healthy traces"
DESCRIPTION = """\
Fit what a nominal head profile leaves out (channel r_r, L_r, B_act, b; the sensor
gain, offset and noise; the per-trace gain and offset spreads) to a recording of
healthy nozzles fired with the profile's drive, from the whole waveform, with
scipy.optimize.least_squares. Writes the complete profile (--out) and a fit report
beside it (OUT.fit.json, OUT.fit.md, OUT.fit.png): recorded vs fitted dominant
frequency, damping, amplitude and the RMS residual, and which parameters the data
pinned and which the prior (the default head's design ratios) fixed.

The recording (.npz) must have the nominal profile's sample rate and trace length.
Traces screening refuses (non-finite, out of range, flat, clipped) are dropped and counted; if the recording has a label
column, only its healthy_nozzle rows are used. See docs/calibration.md.

Healthy traces pin the healthy mode, not how the restrictor and the nozzle share it (the
prior does: within +-12 % on the heads of reports/heads.md, -35.3 to +47.7 % off on heads
of other restrictor splits, reports/splits.md). A fit that
needs a restrictor far from the design ratios (an inertance beyond a factor 2.5 of 1.03
I_n, a resistance above 4 times R_n / 2) is refused: a nominal channel that is not the
head's (a nozzle of the wrong size, mu not the ink's at the head's temperature) or
traces that are not healthy nozzles' (dried ones ring damped) fit so. --blocked gives
traces of fully blocked nozzles of the head (an .npz of at least 10; with a label
column, its fully_blocked rows): their ringing is the restrictor with the chamber alone,
and the fit matches their median mode too, which pins the split (within 3.6 % from 50
traces on those heads; record them at the healthy traces' ink temperature). Traces that
are not fully blocked nozzles are refused (their damping, their spread or the restrictor
they would give says so), as are blocked traces that contradict a restrictor the nominal
profile gives. --blocked-labels takes inkdiag label's CSV of the --blocked recording
instead of its own label column: a recording of the head's faults, labelled by a model
trained on the healthy-only profile, gives its fully blocked rows (the class a wrong
split leaves recognisable); on heads of other restrictor splits a second calibration
with them put the restrictor -7.2 to +1.4 % off in 14 of 16 runs (2 refused: too few
rows), against -35.3 to +47.7 % from healthy traces alone (reports/splits.md: keep the
second profile; it was the better one or as good in 12 of 16 runs; docs/calibration.md).

Healthy traces never show the actuator alone, which the empty-channel classes
ring with: without more, its resonance is the default head's actuator scaled to the
fitted B_act, which another head's actuator need not follow (a head whose actuator
rang 15 % below that lost half its empty_channel_1 rows to empty_channel_2).
--empty gives traces of empty channels of the head (an .npz of at least 10, no ink
and no ink film: the head purged dry; with a label column, its empty_channel_1 rows):
their median mode, corrected for the thin film of that class, becomes the profile's
channel.f_act and channel.zeta_act. A
datasheet's value can go in the nominal profile as channel.f_act (Hz) instead.

A rosbag2 bag is streamed: its rows screening accepts are sampled uniformly, at most
10000 (reservoir sampling, seeded by --seed), so memory stays bounded whatever the
bag's length; the message says how many rows were read, screened out and sampled.
A message that is not a valid trace frame is reported on stderr and skipped.

example:
  inkdiag calibrate healthy.npz --nominal nominal.yaml --out head.yaml
  inkdiag calibrate healthy.npz --nominal nominal.yaml --out head.yaml --empty dry.npz
"""


def add_arguments(parser) -> None:
    parser.add_argument("healthy", metavar="HEALTHY", help="recording (.npz, or a rosbag2 bag directory) of healthy traces, volts")
    parser.add_argument("--topic", default=None, metavar="TOPIC", help="traces topic of a bag, of every bag given "
                        "(default: its one Float32MultiArray topic ending in /traces)")
    parser.add_argument("--nominal", metavar="NOMINAL.yaml", required=True,
                        help="nominal head profile: sampling, drive, channel rho, mu, r_n, L_n, V_ch, c")
    parser.add_argument("--out", metavar="HEAD.yaml", required=True, help="complete head profile to write")
    parser.add_argument("--blocked", metavar="BLOCKED", default=None,
                        help="recording (.npz, or a bag read whole) of fully blocked nozzles of the head: pins the "
                        "restrictor")
    parser.add_argument("--blocked-labels", metavar="LABELS.csv", default=None,
                        help="inkdiag label's CSV of the --blocked recording: its rows labelled fully_blocked are "
                        "used (a recording of the head's faults labelled by a first model, instead of its own label "
                        "column)")
    parser.add_argument("--empty", metavar="EMPTY", default=None,
                        help="recording (.npz, or a bag read whole) of empty channels of the head (no ink: purged "
                        "dry): the actuator's own resonance, which the empty-channel classes are simulated from")
    parser.add_argument("--report-dir", metavar="DIR", default=None,
                        help="where to write the fit report (default: beside --out)")
    parser.add_argument("--name", default=None, help="name of the calibrated profile (default: the nominal's)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the spread-separating simulation (default 0)")
    parser.add_argument("--no-vp-cal", action="store_true",
                        help="do not fit the head's vp_cal constants into the profile (seconds); `inkdiag estimate` "
                        "and fe then fit them at their first use of the head in each process")


#: A median per-trace residual above this many times the larger of the noise alone and the calibrated head's own
#: simulated traces' residual is warned about: healthy recordings of the heads of tests/foreign_head.py (with 10 % of
#: the rows faulty, doubled spreads, or 0.1 mV noise and a 16-bit ADC) give 0.92-1.01, a recording of every class in
#: equal numbers 5.5-9.6, an unlabelled one of 100 deeply dried and 100 small-bubble nozzles of the default head 2.35
#: (helper-145: under the 2.5 this was, no warning).
MISFIT_WARNING = 2.0

#: Healthy rows of a bag calibration uses at most (a uniform sample: 20 MB at 512 samples a row).
MAX_BAG_ROWS = 10000


def bag_sample(chunks, nominal, *, max_rows: int = MAX_BAG_ROWS, seed: int = 0):
    """A uniform sample of at most ``max_rows`` rows screening accepts, from a stream of chunks.

    Reservoir sampling (Vitter's algorithm R, vectorised per chunk): memory is bounded by
    ``max_rows`` rows and one chunk whatever the length of the stream, and every usable
    row is equally likely to be kept.

    Parameters
    ----------
    chunks : iterable of (int, Recording)
        As :func:`inkdiag_ros.bags.stream_recording` gives.
    nominal : HeadProfile
        Its ADC range sets the screening's out-of-range limit (5x, as calibrate's own).

    Returns
    -------
    traces : ndarray, shape (m, n_samples), float32
        m <= ``max_rows`` rows, V, in stream order.
    n_read : int
        Rows read.
    n_screened : int
        Rows screening refused (non-finite, out of range, flat, clipped).
    """
    import numpy as np

    from inkdiag_core.screening import screen_traces

    rng = np.random.default_rng(seed)
    store = order = None
    n_seen = n_read = n_screened = 0
    for _, rec in chunks:
        ok, _why = screen_traces(rec.traces, sample_rate_hz=rec.sample_rate_hz, max_abs_v=nominal.max_abs_v)
        rows = rec.traces[ok]
        n_read += rec.n_rows
        n_screened += int((~ok).sum())
        if store is None:
            store = np.empty((max_rows, rec.n_samples), np.float32)
            order = np.empty(max_rows, np.int64)
        k = rows.shape[0]
        t = n_seen + np.arange(k)  # each row's index among the usable rows
        fill = t < max_rows
        store[t[fill]], order[t[fill]] = rows[fill], t[fill]
        slot = rng.integers(0, t[~fill] + 1) if (~fill).any() else np.empty(0, np.int64)
        hit = slot < max_rows  # row t replaces a kept one with probability max_rows / (t + 1)
        src = np.flatnonzero(~fill)[hit]
        store[slot[hit]], order[slot[hit]] = rows[src], t[~fill][hit]  # a later row wins a shared slot, as in order
        n_seen += k
    m = min(n_seen, max_rows)
    keep = np.argsort(order[:m], kind="stable")
    return store[:m][keep], n_read, n_screened


def _fault_rows(path, option, cls, labels_csv=None, topic=None):
    """The recording at ``path`` (an .npz, or a bag read whole, its rows numbered as ``inkdiag label`` numbers
    them) given as ``option``, its rows labelled ``cls`` where it has labels: those of ``labels_csv`` (``inkdiag
    label``'s CSV of that recording) when given, else its own label column (a bag has none: every row)."""
    from ..bags import is_bag, load_recording

    rec = load_recording(path, topic=topic if is_bag(path) else None)  # --topic: of every bag given
    label = rec.label if labels_csv is None else _csv_classes(labels_csv, rec, f"{option} {path}")
    if label is not None:
        keep = label == cls
        if not keep.any():
            raise ValueError(f"{path}: its label column has no {cls} row" if labels_csv is None else
                             f"{labels_csv}: no row of {path} is labelled {cls}")
        rec = type(rec).from_arrays(rec.traces[keep], rec.sample_rate_hz, source=rec.source)
    return rec


def _csv_classes(labels_csv, rec, what):
    """Each row's ``class`` from ``inkdiag label``'s CSV of the recording ``rec`` (columns ``row`` and ``class``;
    every row once; its ``nozzle`` and ``frame_id`` columns, where present, the recording's), as an (n,) object
    array."""
    import csv

    import numpy as np

    n = rec.n_rows
    try:
        with open(labels_csv, newline="", encoding="utf-8-sig") as f:
            reader = csv.DictReader(f)
            columns = set(reader.fieldnames or ())
            if not {"row", "class"} <= columns:
                raise ValueError(f"{labels_csv}: not a labels CSV of inkdiag label (needs the columns row and "
                                 f"class, has {reader.fieldnames})")
            table = list(reader)
    except UnicodeDecodeError as exc:
        raise ValueError(f"{labels_csv}: not a text CSV (inkdiag label's labels): {exc.reason}") from None
    except csv.Error as exc:
        raise ValueError(f"{labels_csv}: not a readable CSV ({exc})") from None
    try:
        rows = np.array([int(r["row"]) for r in table], dtype=np.int64)
    except (TypeError, ValueError, OverflowError):
        raise ValueError(f"{labels_csv}: its row column must hold integers (the recording's row numbers)") from None
    if rows.size != n or not np.array_equal(np.sort(rows), np.arange(n)):
        raise ValueError(f"{labels_csv} labels {rows.size} rows, not each of the {n} rows of {what} once: "
                         "the labels of another recording?")
    for col, have in (("nozzle", rec.nozzle), ("frame_id", rec.frame_id)):
        if col in columns:
            try:
                same = np.array_equal(np.array([int(r[col]) for r in table], dtype=np.int64), have[rows])
            except (TypeError, ValueError, OverflowError):
                same = False
            if not same:
                raise ValueError(f"{labels_csv}: its {col} column is not that of {what}: the labels of another "
                                 "recording?")
    label = np.empty(n, dtype=object)
    label[rows] = [r["class"] for r in table]
    return label


def _with_vp_cal(profile):
    """The profile with its ``calibration: vp_cal:`` constants fitted (not the default head's: shipped), and a note.

    The constants are fitted on the calibrated head's own simulated dried nozzles
    (:func:`inkdiag_core.estimation.vp_cal_for`); stored in the profile, ``inkdiag estimate``
    and the fe node read them instead of fitting them again in every process."""
    import sys
    import time

    from inkdiag_core import HeadProfile
    from inkdiag_core.estimation import vp_cal_fit_seconds, vp_cal_for

    if profile.sha256 == HeadProfile.default().sha256:
        return profile, ""
    if (eta := vp_cal_fit_seconds(profile)) > 30.0:  # long traces: say so before the wait
        print(f"inkdiag calibrate: fitting the vp_cal constants (roughly {eta:.0f} s for traces of "
              f"{profile.n_samples / profile.sample_rate_hz * 1e6:.0f} us; --no-vp-cal leaves them out)...",
              file=sys.stderr, flush=True)
    t0 = time.perf_counter()
    try:
        cal = vp_cal_for(profile)
    except Exception as exc:  # noqa: BLE001 - the calibration itself is done: written without them, said why
        return (profile,
                f"; vp_cal constants not fitted ({type(exc).__name__}: {exc}; inkdiag estimate and fe fit them at "
                "their first use of the head)")
    stored = {k: v for k, v in cal.items() if k != "seconds"}  # a wall time: the same inputs, another profile file
    return (profile.replace(calibration={"vp_cal": stored}),
            f"; vp_cal constants fitted in {time.perf_counter() - t0:.1f} s")


def extra_outputs(args) -> list:
    """The fit report's files (``.fit.json``, ``.fit.md``, ``.fit.png``) for ``--out`` and ``--report-dir`` (cli
    refuses them over an input)."""
    from pathlib import Path

    out = Path(args.out)
    report_dir = Path(args.report_dir) if args.report_dir else out.parent
    stem = out.name.removesuffix(".yaml").removesuffix(".yml")
    return [report_dir / f"{stem}.fit.{ext}" for ext in ("json", "md", "png")]


def run(args) -> int:
    import itertools
    import json
    import math
    import sys
    from pathlib import Path

    from inkdiag_core.calibration import MODE_MISFIT_WARNING, calibrate
    from inkdiag_core.training import empty_channel_mode_hz
    from inkdiag_core.head_profile import HeadProfile
    from ..bags import is_bag, report_stats, stream_recording

    if not 0 <= args.seed < 2**32:
        raise ValueError(f"--seed must be in 0..2**32-1, got {args.seed}")
    if args.name is not None and not args.name:  # before the recording is read
        raise ValueError("--name must be a non-empty name, got ''")
    nominal = HeadProfile.load(args.nominal)
    # before a long bag is read
    if args.blocked_labels and not args.blocked:
        raise ValueError("--blocked-labels needs --blocked: the recording those labels are of")
    blocked = (_fault_rows(args.blocked, "--blocked", "fully_blocked", args.blocked_labels, args.topic)
               if args.blocked else None)
    if blocked is not None:
        nominal.check_traces(blocked.traces, blocked.sample_rate_hz, what=f"{args.blocked}")
    empty = _fault_rows(args.empty, "--empty", "empty_channel_1", topic=args.topic) if args.empty else None
    if empty is not None:
        nominal.check_traces(empty.traces, empty.sample_rate_hz, what=f"{args.empty}")
    stats, chunks = stream_recording(args.healthy, args.topic,  # a bag's frames of another sampling: skipped
                                     sampling=(nominal.sample_rate_hz, nominal.n_samples, f"profile {nominal.name!r},"))
    _, rec = next(chunks)  # a bag with no trace frame: RecordingError
    nominal.check_traces(rec.traces, rec.sample_rate_hz, what=f"{args.healthy}")
    fs, traces, note, left_out = rec.sample_rate_hz, rec.traces, "", 0
    if is_bag(args.healthy):  # streamed: a bounded sample of its healthy rows
        traces, n_read, n_screened = bag_sample(itertools.chain([(0, rec)], chunks), nominal, max_rows=MAX_BAG_ROWS,
                                                   seed=args.seed)
        del rec
        report_stats(args.healthy, stats)
        note = (f"; {n_screened} of the bag's {n_read} rows screened out" if n_screened else "") + (
            f"; a uniform sample of {traces.shape[0]} of its {n_read - n_screened} usable rows"
            if n_read - n_screened > traces.shape[0] else "")
    elif rec.label is not None:  # a labelled recording: its healthy rows only
        keep = rec.label == "healthy_nozzle"
        if not keep.any():
            raise ValueError(f"{args.healthy}: its label column has no healthy_nozzle row to calibrate from")
        traces = rec.traces[keep]
        left_out = int((~keep).sum())
        note = f"; {left_out} rows labelled otherwise left out" if left_out else ""
    out = Path(args.out)
    report_dir = Path(args.report_dir) if args.report_dir else out.parent
    if report_dir.exists() and not report_dir.is_dir():  # mkdir's own error: '[Errno 17] File exists: ...'
        raise OSError(f"--report-dir {report_dir}: is a file, not a directory")
    _refuse_an_assumed_adc_that_clips(nominal, traces, args.nominal)
    report_dir.mkdir(parents=True, exist_ok=True)
    result = calibrate(nominal, traces, fs, name=args.name, seed=args.seed,
                       blocked=None if blocked is None else blocked.traces,
                       empty=None if empty is None else empty.traces)
    profile = result.profile.replace(calibration={"vp_cal": None})  # not a nominal's (another head's)
    profile, vp_note = (profile, "") if args.no_vp_cal else _with_vp_cal(profile)
    profile.save(out)
    stem = report_dir / out.name.removesuffix(".yaml").removesuffix(".yml")
    png = stem.with_name(stem.name + ".fit.png")
    report = dict(result.report, recording=str(args.healthy), nominal=str(args.nominal), profile=str(out),
                  blocked=None if blocked is None else str(args.blocked),
                  blocked_labels=None if blocked is None else args.blocked_labels,
                  empty=None if empty is None else str(args.empty),
                  profile_sha256=result.profile.sha256, n_rows_left_out_by_label=left_out)
    try:
        _plot(result, png)
        report["figure"] = png.name
    except ImportError:
        report["figure"] = None
        report["figure_note"] = "matplotlib is not installed: no PNG overlay (pip install matplotlib)"
    stem.with_name(stem.name + ".fit.json").write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
    stem.with_name(stem.name + ".fit.md").write_text(_markdown(report), encoding="utf-8")
    mt, hm, rr = report["mean_trace_recorded_vs_fitted"], report["healthy_mode"], report["residual_rel"]
    quiet = f", {n} left out: not ringing above their noise" if (n := report["n_dropped_not_ringing"]) else ""
    quiet += f", {n} left out: repeating another sample for sample" if (n := report["n_dropped_repeated"]) else ""
    print(f"inkdiag calibrate: {out} ({report['n_traces']} traces, {report['n_dropped_nonfinite']} dropped{quiet}{note}); "
          f"healthy mode {hm['frequency_hz'] / 1e3:.1f} kHz, damping {hm['damping_ratio']:.3f}; mean trace "
          f"recorded/fitted {mt['dominant_frequency_hz'][0] / 1e3:.1f}/{mt['dominant_frequency_hz'][1] / 1e3:.1f} kHz; "
          f"residual {100 * rr['per_trace_median']:.1f} % of the trace RMS (noise alone "
          f"{100 * rr['noise_floor']:.1f} %)" + ("" if not (fb := report["blocked_mode"]) else
          f"; blocked mode recorded/fitted {fb['frequency_hz_recorded'] / 1e3:.1f}/"
          f"{fb['frequency_hz_fitted'] / 1e3:.1f} kHz ({fb['n_traces']} traces)")
          + ("" if not (fe := report["empty_mode"]) else
             f"; actuator (empty channels) {fe['frequency_hz'] / 1e3:.1f} kHz, damping {fe['damping_ratio']:.3f} "
             f"({fe['n_traces']} traces)")
          + vp_note + f"; report {stem}.fit.md", file=sys.stdout)
    if "channel.r_r" not in report["fitted"]:  # the nominal profile's restrictor, kept
        print(f"inkdiag calibrate: the restrictor (channel.r_r, channel.L_r) is the nominal profile's, not "
              f"fitted: leave both out of {args.nominal} to fit them (a profile inkdiag calibrate wrote keeps its "
              "earlier fit)", file=sys.stdout)
    elif not report["blocked_mode"]:  # fitted to healthy traces alone: how far the restrictor rests on the prior
        ir = report["identifiability"]["parameters"]["I_r"]
        if ir["determined_by"] != "data":
            print(f"inkdiag calibrate: note: the restrictor's share of the channel's inertance (I_r = "
                  f"{ir['ratio_to_I_n']:.2f} I_n) is set by the {ir['determined_by']} (centred on the design ratio "
                  f"{report['prior']['I_r/I_n']} I_n, one standard deviation a factor "
                  f"{math.exp(report['prior']['sd_log']):.2f}): "
                  "healthy traces pin it weakly, "
                  "and it decides where partially blocked and dried nozzles ring (inkdiag train spreads its rows over "
                  "a few per cent of it). 50 traces of fully blocked nozzles (--blocked BLOCKED.npz) pin it from the "
                  "data (reports/restrictor.md measures both ways); without such a recording, label one of the head's "
                  "faults with a model of this profile and calibrate again with --blocked THAT.npz --blocked-labels "
                  "ITS.csv, and keep that profile (heads of other restrictor splits: reports/splits.md)",
                  file=sys.stdout)
    act = report["actuator"]
    if act["warning"]:
        print(f"inkdiag calibrate: warning: {act['warning']}", file=sys.stderr)
    elif (not report["empty_mode"] and act["source"].startswith("assumed")
          and fs < 2.0 * empty_channel_mode_hz(result.profile)):  # what train refuses
        print(f"inkdiag calibrate: warning: the empty channels' actuator is assumed like the default head's, "
              f"{act['f_act_hz'] / 1e3:.0f} kHz at this B_act, above the Nyquist frequency {fs / 2e3:.0f} kHz of this "
              f"sampling: inkdiag train refuses this profile (the empty-channel classes cannot be simulated). If the "
              f"actuator's datasheet puts its resonance below that, give it as channel.f_act (Hz) in {args.nominal} "
              "(or --empty DRY.npz, traces of the head's empty channels) and calibrate again; if above, the head "
              "needs a higher sample rate", file=sys.stderr)
    elif not report["empty_mode"] and act["source"].startswith("assumed"):
        print(f"inkdiag calibrate: note: the empty channels' actuator is assumed like the default head's, "
              f"{act['f_act_hz'] / 1e3:.0f} kHz at this B_act (another head's may differ: give --empty DRY.npz, or "
              "channel.f_act from a datasheet)", file=sys.stdout)
    _adc_notes(nominal, traces, args.nominal, report.get("n_dropped_clipped", 0))
    _quiet_warning(report)
    mt = report["mean_trace_recorded_vs_fitted"]
    if abs(mt["mode_misfit_rel"]) > MODE_MISFIT_WARNING:
        f_rec, f_fit = mt["dominant_frequency_hz"]
        print(f"inkdiag calibrate: warning: the fitted mean trace rings {100 * mt['mode_misfit_rel']:+.1f} % off the "
              f"recorded one ({f_fit / 1e3:.1f} against {f_rec / 1e3:.1f} kHz; healthy traces fired with the head's "
              "drive fit within 0.1 %): are they healthy nozzles (dried or partially blocked ones ring lower and "
              "damped), and is the profile's drive the head's (a rise and fall off by a half moves it 1-2 %)? The "
              "profile is written; check the fit report before training on it", file=sys.stderr)
    ref = max(rr["noise_floor"], rr["simulated_per_trace_median"])  # what a healthy trace of this head leaves
    if rr["per_trace_median"] > MISFIT_WARNING * ref:
        print(f"inkdiag calibrate: warning: the median trace leaves {100 * rr['per_trace_median']:.1f} % of its RMS "
              f"unexplained, {rr['per_trace_median'] / ref:.1f} times what the calibrated head's own simulated traces "
              "leave: most traces are not what one healthy channel fired with the profile's drive gives. Are they all "
              "healthy nozzles (not a recording of mixed or faulty ones)? The profile is written; check the fit report "
              "before training on it", file=sys.stderr)
    if report["figure"] is None:
        print(f"inkdiag calibrate: {report['figure_note']}", file=sys.stderr)
    return 0


def _plot(result, path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t_us = result.t_s * 1e6
    k = result.examples_recorded.shape[0]
    fig, axes = plt.subplots(k + 1, 1, figsize=(8, 1.8 * (k + 1)), sharex=True)
    axes[0].plot(t_us, result.mean_recorded, lw=1.2, label="recorded (mean)")
    axes[0].plot(t_us, result.mean_fitted, lw=1.0, ls="--", label="fitted")
    axes[0].legend(loc="upper right", fontsize=8)
    axes[0].set_ylabel("V")
    axes[0].set_title(f"{result.profile.name}: mean of the {result.report['n_typical']} typical of "
                      f"{result.report['n_traces']} healthy traces")
    for ax, row, rec, fit in zip(axes[1:], result.example_rows, result.examples_recorded, result.examples_fitted):
        ax.plot(t_us, rec, lw=0.8, label=f"recorded row {int(row)}")
        ax.plot(t_us, fit, lw=0.8, ls="--", label="fitted")
        ax.legend(loc="upper right", fontsize=8)
        ax.set_ylabel("V")
    axes[-1].set_xlabel("time from the first sensed sample (us)")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _beyond_adc(nominal, traces):
    """``(k, n, peak)``: of the ``n`` healthy traces, ``k`` reach past the ADC range the profile has (the highest
    at ``peak`` V)."""
    import numpy as np

    peaks = np.abs(np.where(np.isfinite(traces), traces, 0.0)).max(axis=1, initial=0.0)
    return int(np.count_nonzero(peaks > nominal.adc_range_v)), int(peaks.size), float(peaks.max(initial=0.0))


#: Healthy traces beyond the profile's ADC range, as a share, from which calibrate says so (not a glitch).
BEYOND_ADC_SHARE = 0.1


#: Healthy traces left out as not ringing above their noise, as a share of those screening kept, from which calibrate
#: warns: h20 of tests/foreign_head.py at 6 dB SNR left out 25 of 300 and its drive coupling ``b`` read 3 % high; at
#: 5 dB 122 of 300, ``b`` 7.5 % high and the gain spread half the 0.075 of the noise-free recording.
QUIET_SHARE = 0.1


def _quiet_warning(report) -> None:
    """A warning when a tenth or more of the screened-in traces do not ring above their noise: the fit rests on the
    louder others, so the traces' amplitude reads high and their spread low."""
    import sys

    quiet = report["n_dropped_not_ringing"]
    kept = quiet + report["n_traces"] + report["n_dropped_repeated"]
    if kept and quiet >= QUIET_SHARE * kept:
        print(f"inkdiag calibrate: warning: {quiet} of the {kept} healthy traces screening kept do not ring above "
              "their noise and are left out: nozzles that did not fire, or noise as large as the ringing. If the "
              "nozzles fired, the fit rests on the louder traces, so the profile's amplitude reads high and its "
              "spread of amplitudes low (a recording at 5 dB SNR: 7.5 % high, half the spread). Check that every "
              "nozzle fired, and the sensing's noise", file=sys.stderr)


def _refuse_an_assumed_adc_that_clips(nominal, traces, nominal_path) -> None:
    """ValueError (exit 2) when the nominal profile gives no ADC range and a tenth of the healthy traces or more
    reach past the one it would assume (the default head's): the profile written would simulate the head's own
    healthy traces clipped, and a model trained on it misses most of them (helper-111: 52 % of rows right)."""
    if "adc_range_v" in nominal.sensor:
        return
    k, n, peak = _beyond_adc(nominal, traces)
    if n and k >= BEYOND_ADC_SHARE * n:
        scale = ("are the traces in volts (not millivolts or ADC counts)? If they are, give sensor.adc_range_v (V) "
                 "from the head's datasheet" if peak > nominal.max_abs_v else "give sensor.adc_range_v (V) from the "
                 "head's datasheet, or check the recording's scale (volts, not millivolts or ADC counts)")
        raise ValueError(f"{k} of the {n} healthy traces reach past +-{nominal.adc_range_v:g} V (up to {peak:.3g} V), "
                         f"the ADC range the profile would assume (the default head's: sensor.adc_range_v is not in "
                         f"{nominal_path}); training would simulate this head's healthy traces clipped: {scale}")


def _adc_notes(nominal, traces, nominal_path, n_clipped: int = 0) -> None:
    """A note when the nominal profile gives no ADC (the default head's is assumed: healthy traces cannot tell it,
    docs/calibration.md); a warning when the healthy traces (one in ten or more: not a glitch) reach past the
    ADC's range the profile has, or when that many were clipped (``n_clipped``, left out by screening)."""
    import sys

    k, n, peak = _beyond_adc(nominal, traces)
    missing = [key for key in ("adc_range_v", "adc_bits") if key not in nominal.sensor]
    if missing:
        print(f"inkdiag calibrate: note: the ADC is assumed like the default head's, +-{nominal.adc_range_v:g} V"
              + (f", {nominal.adc_bits} bits" if nominal.adc_bits is not None else "")
              + f" ({', '.join('sensor.' + k for k in missing)} not in {nominal_path}: healthy traces cannot tell "
              f"them; training simulates this ADC's clipping and quantisation, and labelling calls a sample beyond "
              f"{nominal.max_abs_v:g} V out_of_range): give the head's from its datasheet", file=sys.stdout)
    if k and "adc_range_v" in missing:  # fewer than a tenth (more: refused): the profile clips them all the same
        print(f"inkdiag calibrate: warning: {k} of the {n} healthy traces reach past +-{nominal.adc_range_v:g} V "
              f"(up to {peak:.3g} V), the ADC range the profile assumes: it simulates such traces clipped. Give "
              f"sensor.adc_range_v (V) in {nominal_path} from the head's datasheet", file=sys.stderr)
    elif n and k >= BEYOND_ADC_SHARE * n:
        print(f"inkdiag calibrate: warning: {k} of the {n} healthy traces reach past the ADC range of "
              f"+-{nominal.adc_range_v:g} V the profile has (up to {peak:.3g} V), which an ADC cannot read: check "
              f"sensor.adc_range_v (V) in {nominal_path} against the head's datasheet, and the recording's scale "
              "(volts, not millivolts or ADC counts)", file=sys.stderr)
    if n and n_clipped >= BEYOND_ADC_SHARE * n:
        print(f"inkdiag calibrate: warning: {n_clipped} of the {n} healthy traces are clipped at the ADC and left out: "
              "the fit rests on the others, the smaller ones, so the sensor gain (the traces' amplitude) reads low. "
              "Lower the sense gain or the drive so that healthy traces stay inside the ADC's range, and record "
              "again", file=sys.stderr)


def _markdown(r) -> str:
    rv, rr, hm = r["recorded_vs_fitted"], r["residual_rel"], r["healthy_mode"]
    mt = r["mean_trace_recorded_vs_fitted"]
    lines = [
        f"# Calibration fit report: {r['profile']}",
        "",
        f"Recording `{r['recording']}`: {r['n_traces']} healthy traces used, {r['n_dropped_nonfinite']} dropped "
        f"(screened out: non-finite, out of range, flat or clipped), {r['n_dropped_not_ringing']} left out (not "
        f"ringing above their own noise: nozzles that did not fire?)"
        + (f", {n} left out (repeating another trace sample for sample)" if (n := r["n_dropped_repeated"]) else "")
        + f"; {r['sample_rate_hz'] / 1e6:g} MHz x {r['n_samples']} samples. Nominal profile "
        f"`{r['nominal']}`. Profile sha256 `{r['profile_sha256'][:16]}`.",
        "",
        "| quantity | recorded | fitted |",
        "|---|---|---|",
        f"| mean trace: dominant frequency (kHz) | {mt['dominant_frequency_hz'][0] / 1e3:.2f} | "
        f"{mt['dominant_frequency_hz'][1] / 1e3:.2f} |",
        f"| mean trace: damping ratio | {mt['damping_ratio'][0]:.4f} | {mt['damping_ratio'][1]:.4f} |",
        f"| mean trace: amplitude (V) | {mt['amplitude_v'][0]:.4g} | {mt['amplitude_v'][1]:.4g} |",
        f"| per trace: dominant frequency (median, kHz) | {rv['dominant_frequency_hz'][0] / 1e3:.2f} | "
        f"{rv['dominant_frequency_hz'][1] / 1e3:.2f} |",
        f"| per trace: damping ratio (median) | {rv['damping_ratio'][0]:.4f} | {rv['damping_ratio'][1]:.4f} |",
        f"| per trace: amplitude (median, V) | {rv['amplitude_v'][0]:.4g} | {rv['amplitude_v'][1]:.4g} |",
        f"| frequency spread (robust std, kHz; fitted = calibrated head simulated) | "
        f"{rv['frequency_std_hz'][0] / 1e3:.2f} | {rv['frequency_std_hz'][1] / 1e3:.2f} |",
        f"| damping spread (robust std) | {rv['damping_std'][0]:.4f} | {rv['damping_std'][1]:.4f} |",
        f"| amplitude spread (robust std of log amplitude) | {rv['amplitude_log_std'][0]:.4f} | "
        f"{rv['amplitude_log_std'][1]:.4f} |",
        "",
        f"Healthy mode of the calibrated channel: {hm['frequency_hz'] / 1e3:.2f} kHz, damping ratio "
        f"{hm['damping_ratio']:.4f}. The empty channels' actuator: {r['actuator']['f_act_hz'] / 1e3:.1f} kHz, "
        f"damping ratio {r['actuator']['zeta_act']:.3f} ({r['actuator']['source']}).",
        "",
        *([] if not (fb := r.get("blocked_mode")) else [
            f"Fully blocked nozzles (`{r.get('blocked')}`, {fb['n_traces']} traces): their mode recorded "
            f"{fb['frequency_hz_recorded'] / 1e3:.2f} kHz (standard error "
            f"{fb['frequency_hz_std_error'] / 1e3:.2f} kHz, damping ratio {fb['damping_ratio_recorded']:.3f}), "
            f"the calibrated channel's {fb['frequency_hz_fitted'] / 1e3:.2f} kHz (damping ratio "
            f"{fb['damping_ratio_fitted']:.3f}): it pins the restrictor.", ""]),
        *([] if not (fe := r.get("empty_mode")) else [
            f"Empty channels (`{r.get('empty')}`, {fe['n_traces']} traces): their median mode "
            f"{fe['frequency_hz_recorded'] / 1e3:.1f} kHz (robust spread {100 * fe['frequency_spread_rel']:.1f} %), "
            f"damping ratio {fe['damping_ratio_recorded']:.3f}; without the ink film of mass ratio "
            f"{fe['film_mass_ratio']:g} they are taken to carry, the actuator alone: "
            f"{fe['frequency_hz'] / 1e3:.1f} kHz, "
            f"damping ratio {fe['damping_ratio']:.3f}, the profile's channel.f_act and channel.zeta_act, which the "
            "empty-channel classes are simulated from.", ""]),
        f"RMS residual relative to the trace RMS: mean trace {100 * rr['mean_trace']:.2f} %, per trace median "
        f"{100 * rr['per_trace_median']:.2f} % (P90 {100 * rr['per_trace_p90']:.2f} %); the white noise alone is "
        f"{100 * rr['noise_floor']:.2f} %.",
        "",
        "| fitted | value |",
        "|---|---|",
    ]
    lines += [f"| {k} | {v:.6g} |" for k, v in r["fitted"].items()]
    if capped := r.get("spreads_capped"):
        lines += ["", f"Capped at the largest value a profile takes (the recording's spread is wider, or the spread "
                  f"scales' fit pushed them; the report's spread_scales are the fit's, before the cap): "
                  f"{', '.join(capped)}."]
    lines += ["", f"Amplitude convention (only b x gain is identified): {r['amplitude_convention']}.", "",
              "| parameter | value | posterior sd (log) | prior sd (log) | determined by |", "|---|---|---|---|---|"]
    for p, d in r["identifiability"]["parameters"].items():
        prior = "-" if d["prior_sd_log"] is None else f"{d['prior_sd_log']:.3f}"
        lines.append(f"| {p} | {d['value']:.4g} | {d['sd_log']:.3g} | {prior} | {d['determined_by']} |")
    lines += ["", f"Prior: I_r/I_n = {r['prior']['I_r/I_n']}, R_r/R_n = {r['prior']['R_r/R_n']}, log-normal sd "
              f"{r['prior']['sd_log']:.3f}. Optimiser: {r['optimiser']['method']}, {r['optimiser']['nfev']} "
              f"evaluations of the best start, status {r['optimiser']['status']} ({r['optimiser']['message']}).", ""]
    if r.get("figure"):
        lines += [f"![recorded and fitted traces]({r['figure']})", ""]
    else:
        lines += [f"No figure: {r.get('figure_note', 'not written')}.", ""]
    return "\n".join(lines)
