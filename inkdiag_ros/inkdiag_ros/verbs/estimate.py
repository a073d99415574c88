"""``inkdiag estimate``: f_m, its standard deviation and the nozzle viscosity of recorded traces.

    inkdiag estimate RECORDING --profile HEAD.yaml [--rows ROWS] [--labels LABELS.csv] [--method vp_cal] \
        [--baselines B.npz] --out FM.csv

The fe node's code path on a recording: a :class:`inkdiag_core.DryingTracker` on
the head profile (its model, its "vp_cal" constants, its deeply-dried level)
screens the rows and estimates the valid ones in batches
(:meth:`~inkdiag_core.DryingTracker.estimate_rows`); with stamps, each nozzle's
trend is then fed frame by frame in time order. See docs/cli.md.
"""

from __future__ import annotations

import re

from . import (NO_BASELINE_HINT, check_max_abs_v, invalid_warning, open_csv_out, repeated_pairs, repeated_pairs_warning,
               summary_stream, units_warning)

OUT_STDOUT = True  # --out - writes the CSV to standard output
#: A stamp beyond this many seconds is said to be in other units (nanoseconds since 1970 are about 1.8e18).
MAX_STAMP_S = 1e12
HELP = "estimate the drying fault f_m and the nozzle viscosity of recorded traces"
DESCRIPTION = """\
Estimate the drying-nozzle fault f_m (1/s), its standard deviation and the
nozzle's viscosity increase and viscosity (Pa s) of each selected row of a
recording, on the head of a complete profile (its model, sampling and
"vp_cal" constants; a head other than the default one gets its constants
fitted once, a few seconds, unless the profile's calibration: section holds
them). The same code as the fe node.

Output CSV, one line per selected row, columns:
  row, nozzle, fm, fm_std, d_mu, viscosity,
  frame_id, stamp, fm_trend, fm_rate, eta_deeply_dried_s, method, reason
Units: fm, fm_std, fm_trend 1/s; fm_rate 1/s^2; d_mu, viscosity Pa s;
stamp, eta_deeply_dried_s s. A row that cannot be estimated has empty values
and its reason: non_finite, out_of_range, flat or clipped samples (as fdi
screens them; clipped also two samples at the ADC's end code, with a profile
that states sensor.adc_range_v), below_noise (an AC rms at most 2x the profile's noise_std_v:
no ringing to fit), estimate_not_finite, viscosity_not_positive (an estimate
that means a viscosity of 0 or less: no drying nozzle the channel model
describes, e.g. an empty channel or a bubble), or at_search_bound (the fit
ended at an edge of its interval, a viscosity 16x the ink's or thinner than
the ink: a blocked nozzle, an empty channel), or misfit (the drying model
leaves over 35 % of the trace's rms unexplained, and over 6x the profile's noise:
no drying nozzle, e.g. an air bubble); the others are estimated all the
same. fm_trend and fm_rate are filled when the recording has stamps
(several frames per nozzle).

ROWS: comma-separated indices and ranges START:STOP (STOP excluded, either
may be omitted), e.g. 0:100 or 3,7,9 or 0:10,50; or a class name
(dried = the three dried classes, or one FaultClass value such as
deeply_dried) to take the rows whose label is that: the recording's label
column, or with --labels LABELS.csv the class of each row in that CSV
(`inkdiag label`'s output for this recording, or your own: columns row or
nozzle [, frame_id] and class). Default: every row; with --labels, dried.

Exit status 2 with a one-line message for bad input: a missing or
unreadable file, a nominal profile (run inkdiag calibrate first), a
recording of another sample rate or trace length than the profile's, bad
ROWS."""

_CHUNK = 2048  # rows per estimator batch: bounds memory, keeps numpy's batches large
_BAG_CHUNK_ROWS = 8192  # rows of a bag read at a time (whole frames)

HEADER = ["row", "nozzle", "fm", "fm_std", "d_mu", "viscosity", "frame_id", "stamp", "fm_trend", "fm_rate",
          "eta_deeply_dried_s", "method", "reason"]


def add_arguments(parser) -> None:
    parser.add_argument("recording", metavar="RECORDING", help="recording (.npz: traces, sample_rate_hz, ...) or rosbag2 bag directory")
    parser.add_argument("--topic", default=None, metavar="TOPIC", help="traces topic of a bag (default: its one "
                        "Float32MultiArray topic ending in /traces)")
    parser.add_argument("--profile", required=True, metavar="HEAD.yaml",
                        help="complete head profile (from inkdiag calibrate, or the shipped default)")
    parser.add_argument("--out", required=True, metavar="FM.csv", help="CSV file to write ('-': stdout)")
    parser.add_argument("--rows", default=None, metavar="ROWS",
                        help="rows to estimate: 0:100, 3,7,9, dried or a class name (default: all; with "
                             "--labels: dried)")
    parser.add_argument("--labels", default=None, metavar="LABELS.csv",
                        help="the class of each row (inkdiag label's CSV of this recording) for --rows dried or a "
                             "class name, as the fe node estimates what fdi labels dried")
    parser.add_argument("--method", default="vp_cal", choices=("vp_cal", "vp"),
                        help="estimator (default vp_cal, as the fe node; vp: without the mismatch correction)")
    parser.add_argument("--baselines", default=None, metavar="B.npz",
                        help="per-nozzle baselines with healthy f_m (inkdiag baseline, record_baseline): estimates relative to them")
    parser.add_argument("--max-abs-v", type=float, default=None, metavar="V",
                        help="a row with a sample beyond +-V is invalid, out_of_range (default: 5x the profile's "
                             "ADC range, as fdi)")


def select_rows(spec, n: int, labels=None):
    """Row indices (int64, increasing order of the spec) of ``--rows``; see DESCRIPTION.

    Raises
    ------
    inkdiag_core.checks.InputError
        A malformed spec, an index out of range, a class name without labels.
    """
    import numpy as np
    from inkdiag_core import FaultClass
    from inkdiag_core.checks import InputError

    if spec is None:
        return np.arange(n, dtype=np.int64)
    spec = spec.strip()
    classes = {c.value for c in FaultClass}
    if (want := _class_values(spec)) is not None:
        if labels is None:
            raise InputError(f"--rows {spec}: the recording has no label column; give the rows' classes with "
                             "--labels LABELS.csv (inkdiag label's CSV of the recording)")
        return np.flatnonzero(np.isin(labels, sorted(want))).astype(np.int64)
    out = []
    for part in spec.split(","):
        part = part.strip()
        m = re.fullmatch(r"(-?[0-9]+)?\s*:\s*(-?[0-9]+)?", part)  # "-:5" is no number: the error below
        if m:
            lo = int(m.group(1)) if m.group(1) else 0
            hi = int(m.group(2)) if m.group(2) else n
            if not (0 <= lo <= n and 0 <= hi <= n):
                raise InputError(f"--rows {part}: outside 0:{n} (the recording has {n} rows)")
            if lo > hi:
                raise InputError(f"--rows {part}: START {lo} is after STOP {hi} (START:STOP, STOP excluded)")
            out.append(np.arange(lo, hi, dtype=np.int64))
        elif re.fullmatch(r"[0-9]+", part):
            i = int(part)
            if i >= n:
                raise InputError(f"--rows {part}: no such row (the recording has {n} rows)")
            out.append(np.array([i], dtype=np.int64))
        else:
            raise InputError(f"--rows {spec!r}: expected indices and ranges such as 0:100 or 3,7,9, "
                             f"'dried' or a class name ({', '.join(sorted(classes))})")
    return np.concatenate(out) if out else np.empty(0, dtype=np.int64)


def _against(tracker, n_estimated: int, notes) -> str:
    """With f_m baselines in use: how many estimates took their nozzle's healthy reading off (a nozzle
    column that does not match the baselines' ids is said, not silent)."""
    b = tracker.baselines
    if b is None or b.fm is None or notes:  # none given, or not used (a note says why)
        return ""
    k = min(tracker.estimates_with_baseline, n_estimated)
    if k == n_estimated:
        return f"; all {k} relative to their nozzle's healthy f_m"
    return f"; {k} relative to their nozzle's healthy f_m, {n_estimated - k} without one ({NO_BASELINE_HINT})"


def _to(out: str) -> str:
    """The summary line's tail naming where the CSV went."""
    return "" if out == "-" else f" -> {out}"


def _fmt(v) -> str:
    import math

    v = float(v)
    return repr(v) if math.isfinite(v) else ""


def _fit_vp_cal_said(profile) -> None:
    """Fit the head's ``vp_cal`` constants now if they need a fit (seconds), saying so on stderr before and after."""
    import sys

    from inkdiag_core.estimation import vp_cal_fit_seconds, vp_cal_for, vp_cal_needs_fit

    if not vp_cal_needs_fit(profile):
        return
    print(f"inkdiag estimate: fitting the vp_cal constants of head {profile.name!r} (first use of this head "
          f"in this process; roughly {vp_cal_fit_seconds(profile):.0f} s for its traces of "
          f"{profile.n_samples / profile.sample_rate_hz * 1e6:.0f} us; a profile from inkdiag calibrate holds them, "
          "or give --method vp)...", file=sys.stderr, flush=True)
    cal = vp_cal_for(profile)
    if "seconds" in cal:
        print(f"inkdiag estimate: vp_cal fitted in {cal['seconds']:.1f} s on {cal['n_traces']} simulated traces",
              file=sys.stderr, flush=True)


def run(args) -> int:
    import csv
    import itertools
    import sys

    import numpy as np
    from inkdiag_core import BaselineFileError, DryingTracker, HeadProfile, NozzleBaselines
    from inkdiag_core.head_profile import ProfileError

    from ..bags import is_bag, stream_recording

    check_max_abs_v(args.max_abs_v)
    profile = HeadProfile.load(args.profile)
    if not profile.is_complete:
        raise ProfileError(f"{args.profile}: a nominal profile ({', '.join(profile.missing)} missing): run "
                           "inkdiag calibrate first on recorded healthy traces of the head")
    table = _labels_table(args)  # before the recording is read: a bad CSV or --rows costs nothing
    stats, chunks = stream_recording(args.recording, args.topic, max_rows=_BAG_CHUNK_ROWS,  # a bag's others: skipped
                                     sampling=(profile.sample_rate_hz, profile.n_samples, f"profile {profile.name!r},"))
    bag = bool(is_bag(args.recording))
    pick = bag_row_picker(args.rows, table) if bag else None  # before the bag is read: a bad spec costs nothing
    first_row, rec = next(chunks)  # a bag with no trace frame: RecordingError
    profile.check_traces(rec.traces, rec.sample_rate_hz, what=f"{args.recording}")
    if table is not None and not bag:
        from inkdiag_core import labels_from_csv

        rec, n_named = labels_from_csv(rec, table)  # the CSV's classes for the recording's own
        if why := table.coverage_warning(n_named, rec.n_rows, args.recording):
            print(f"inkdiag estimate: warning: {why}", file=sys.stderr)
    rows = None if bag else select_rows(args.rows, rec.n_rows, rec.label)
    baselines = None
    if args.baselines:
        try:
            baselines = NozzleBaselines.load(args.baselines)
            baselines.check_head(profile)
        except BaselineFileError as exc:
            raise ProfileError(str(exc)) from None
    if args.method == "vp_cal":
        _fit_vp_cal_said(profile)
    tracker = DryingTracker(profile=profile, baselines=baselines, method=args.method, max_abs_v=args.max_abs_v)
    if bag:
        return _estimate_bag(args, tracker, profile, pick, itertools.chain([(first_row, rec)], chunks), stats)
    n = rows.size
    cols = {}
    reasons = np.full(n, "", dtype=object)
    notes = set()
    for start in range(0, n, _CHUNK):  # estimates without trends, in large batches
        sel = rows[start:start + _CHUNK]
        r = tracker.estimate_rows(rec.traces[sel], rec.nozzle[sel], stamp=float("nan"),
                                  sample_rate_hz=rec.sample_rate_hz)
        for k, v in r.columns.items():
            cols.setdefault(k, np.empty(n, dtype=v.dtype))[start:start + sel.size] = v
        reasons[start:start + sel.size] = r.reasons
        if r.note:
            notes.add(r.note)
    method = "vp" if args.method == "vp" else "vp_cal"
    if not cols:
        cols = {k: np.empty(0) for k in ("nozzle", "fm", "fm_std", "d_mu", "viscosity", "fm_trend", "fm_rate",
                                         "eta_deeply_dried_s")}
    # trends: each frame's estimates in time order (stamp, then frame_id), as fe would have seen them
    stamps = rec.stamp[rows]
    frames = rec.frame_id[rows]
    left_out = _left_out(args, rec.n_rows, rows)
    unfolded = _trend_steps(tracker, rec, rows, left_out, reasons == "", cols, time_order=True)
    with open_csv_out(args.out) as f:
        w = csv.writer(f, lineterminator="\n")  # as label writes: no "\r\n" in a pipe
        w.writerow(["row", "nozzle", "fm", "fm_std", "d_mu", "viscosity", "frame_id", "stamp", "fm_trend",
                    "fm_rate", "eta_deeply_dried_s", "method", "reason"])
        for i in range(n):  # formatting only
            w.writerow([int(rows[i]), int(rec.nozzle[rows[i]]), _fmt(cols["fm"][i]), _fmt(cols["fm_std"][i]),
                        _fmt(cols["d_mu"][i]), _fmt(cols["viscosity"][i]), int(frames[i]), _fmt(stamps[i]),
                        _fmt(cols["fm_trend"][i]), _fmt(cols["fm_rate"][i]), _fmt(cols["eta_deeply_dried_s"][i]),
                        method, reasons[i]])
    bad = reasons != ""
    why = ", ".join(f"{k} {int(np.sum(reasons == k))}" for k in sorted(set(reasons[bad].tolist())))
    print(f"inkdiag estimate: {n - int(bad.sum())} of {n} rows estimated ({method}, head {profile.name!r})"
          + (f"; not estimated: {why}" if bad.any() else "") + _against(tracker, n - int(bad.sum()), notes)
          + _to(args.out), file=summary_stream(args.out))
    for note in sorted(notes):
        print(f"inkdiag estimate: note: {note}", file=sys.stderr)
    _say_none(args, n)
    _say_after([(rec.nozzle[rows], frames, stamps)], unfolded, {r: int(np.sum(reasons == r)) for r in
                                                                  set(reasons[bad].tolist())}, n, tracker,
               bound_given=args.max_abs_v is not None)
    est = ~bad
    k = int(np.count_nonzero(est & ~np.isfinite(stamps)))
    if k:  # said, not silent: those rows' trend columns are empty
        print("inkdiag estimate: note: " + (
            "no estimated row has a finite stamp (the recording's 'stamp' column is missing or not finite)"
            if k == est.sum() else f"{k} of the {int(est.sum())} estimated rows have no finite stamp")
            + ": fm_trend, fm_rate and eta_deeply_dried_s are empty for them", file=sys.stderr)
    by_index = args.rows is None or _class_values(args.rows) is None  # not rows picked by their class
    if by_index and rec.label is not None and (said := _other_faults_note(rec.label[rows][est])):
        print(f"inkdiag estimate: note: {said}", file=sys.stderr)
    return 0


def _other_faults_note(labels) -> str:
    """What to say when rows estimated (their ``label`` values) include faults other than drying, else ""."""
    import collections

    from inkdiag_core import FaultClass
    from inkdiag_core.faults import DRIED_VALUES, HEALTHY_VALUES

    faults = {c.value for c in FaultClass} - set(DRIED_VALUES) - set(HEALTHY_VALUES)
    other = collections.Counter(v for v in labels.tolist() if v in faults)
    if not other:
        return ""
    shown = ", ".join(f"{c} {k}" for c, k in sorted(other.items()))
    return (f"{sum(other.values())} estimated rows are labelled a fault other than drying in the recording's label "
            f"column ({shown}): their f_m is no ink viscosity; --rows dried estimates the dried rows only")


def _class_values(spec):
    """The class values ``--rows`` names (``dried``: the three dried classes), or None: ``spec`` names rows."""
    from inkdiag_core import FaultClass
    from inkdiag_core.faults import DRIED_VALUES

    spec = spec.strip().lower()  # class names without case, as a labels CSV's
    if spec == "dried":
        return set(DRIED_VALUES)
    return {spec} if spec in {c.value for c in FaultClass} else None


def _labels_table(args):
    """``--labels``'s CSV read and checked (None without it); ``args.rows`` defaults to ``dried`` with it.

    Raises
    ------
    inkdiag_core.checks.InputError
        A CSV :func:`inkdiag_core.read_labels_csv` refuses, or ``--rows`` indices beside it.
    """
    from inkdiag_core import read_labels_csv
    from inkdiag_core.checks import InputError

    if args.labels is None:
        return None
    if args.rows is None:
        args.rows = "dried"
    elif _class_values(args.rows) is None:
        raise InputError(f"--rows {args.rows} with --labels: --labels picks rows by their class; give --rows dried "
                         "or a class name, or leave out --labels to give row indices")
    return read_labels_csv(args.labels)


def bag_row_picker(spec, labels=None):
    """``--rows`` for a streamed bag, whose row count is not known in advance.

    Parameters
    ----------
    spec : str or None
        ``--rows``.
    labels : inkdiag_core.recording.LabelTable, optional
        ``--labels``'s CSV, whose ``row`` column names the bag's rows (``spec``: a class).

    Returns
    -------
    callable
        ``pick(start, n)`` -> the selected indices (int64, increasing) among rows
        ``start .. start + n - 1``; its method ``beyond(n_rows)`` says what the spec (or the
        CSV) names past a bag of ``n_rows`` rows (None: nothing), checked at the end; its method
        ``check(start, nozzle, frame_id)`` refuses a CSV whose ``nozzle`` or ``frame_id`` is not
        that of rows ``start ..`` (another recording's).

    Raises
    ------
    inkdiag_core.checks.InputError
        A malformed spec, a class name without ``labels`` (a bag has no label column), a CSV
        that names rows by nozzle.
    """
    import numpy as np
    from inkdiag_core.checks import InputError

    if labels is not None:
        return _labelled_picker(spec, labels)
    parts, last = [], []  # last: each part's largest row (as select_rows: STOP <= n) and its error
    if spec is not None:
        spec = spec.strip()
        if _class_values(spec) is not None:
            raise InputError(f"--rows {spec}: a bag has no label column; give the rows' classes with --labels "
                             "LABELS.csv (inkdiag label's CSV of the bag)")
        for part in spec.split(","):
            part = part.strip()
            m = re.fullmatch(r"(-?[0-9]+)?\s*:\s*(-?[0-9]+)?", part)
            if m:
                lo = int(m.group(1)) if m.group(1) else 0
                hi = int(m.group(2)) if m.group(2) else None
                if lo < 0 or (hi is not None and hi < 0):  # as select_rows: no negative (from the end) indices
                    raise InputError(f"--rows {part}: outside 0:N, a row of the bag (rows count from 0)")
                if hi is not None and lo > hi:
                    raise InputError(f"--rows {part}: START > STOP")
                parts.append((lo, hi))
                last.append((part, (lo if hi is None else hi) - 1, "outside 0:{n}"))
            elif re.fullmatch(r"[0-9]+", part):
                parts.append((int(part), int(part) + 1))
                last.append((part, int(part), "no such row"))
            else:
                raise InputError(f"--rows {spec!r}: expected indices and ranges such as 0:100 or 3,7,9")

    def pick(start, n):
        idx = np.arange(start, start + n, dtype=np.int64)
        if spec is None:
            return idx
        keep = np.zeros(n, dtype=bool)
        for lo, hi in parts:
            keep |= (idx >= lo) & (idx < (hi if hi is not None else start + n))
        return idx[keep]

    def beyond(n_rows):  # the first part, in the order given, that names a row past the end; as select_rows says it
        return next((f"--rows {part}: {why.format(n=n_rows)}" for part, hi, why in last if hi >= n_rows), None)

    pick.beyond = beyond
    pick.check = lambda start, nozzle, frame_id: None
    return pick


def _labelled_picker(spec, table):
    """:func:`bag_row_picker` of the rows ``table`` (a labels CSV naming rows by ``row``) gives a class of ``spec``."""
    import numpy as np
    from inkdiag_core.checks import InputError

    if table.key != "row":
        raise InputError(f"--labels {table.source}: names rows by {table.key.replace('+', ' and ')}; on a bag the "
                         "labels CSV names each row by its row number (a 'row' column, as inkdiag label writes)")
    order = np.argsort(table.row, kind="stable")
    named = table.row[order]  # increasing, distinct (read_labels_csv refuses a row named twice)
    wanted = named[np.isin(table.classes[order], sorted(_class_values(spec)))]

    def pick(start, n):
        return wanted[np.searchsorted(wanted, start):np.searchsorted(wanted, start + n)]

    def check(start, nozzle, frame_id):
        lo, hi = np.searchsorted(named, [start, start + len(nozzle)])
        for name, have in (("nozzle", nozzle), ("frame_id", frame_id)):
            col = getattr(table, name)
            if col is None:
                continue
            j = order[lo:hi]
            got = have[named[lo:hi] - start]
            bad = np.flatnonzero((col[j] != np.iinfo(np.int64).min) & (col[j] != got))  # int64 min: a cell left empty
            if bad.size:
                k = j[bad[0]]
                raise InputError(f"{table.source}:{table.lines[k]}: row {table.row[k]} is {name} {got[bad[0]]} in "
                                 f"the bag, the CSV says {col[k]}: labels of another recording?")

    def beyond(n_rows):  # the CSV's first row past the end, and how many more
        past = named[np.searchsorted(named, n_rows):]
        if past.size:
            return (f"--labels {table.source}: row {past[0]}" + (f" (and {past.size - 1} more)" if past.size > 1
                                                                   else "") + " is past the end")
        return None

    pick.beyond = beyond
    pick.check = check
    return pick


def _estimate_bag(args, tracker, profile, pick, chunks, stats) -> int:
    """``inkdiag estimate`` on a bag: chunk by chunk, each chunk's rows written before the next is read."""
    import csv
    import sys

    import numpy as np
    from inkdiag_core.checks import InputError

    from ..bags import report_stats

    method = "vp" if args.method == "vp" else "vp_cal"
    n = n_bad = n_seen = 0
    unfolded = (0, 0)
    seen = []  # each chunk's (nozzle, frame_id, stamp) of the rows selected: repeats are said at the end
    why, notes = {}, set()
    with open_csv_out(args.out) as f:
        w = csv.writer(f, lineterminator="\n")  # as label writes: no "\r\n" in a pipe
        w.writerow(HEADER)
        for first_row, rec in chunks:
            n_seen = first_row + rec.n_rows
            pick.check(first_row, rec.nozzle, rec.frame_id)
            sel = pick(first_row, rec.n_rows) - first_row
            left_out = _left_out(args, rec.n_rows, sel)
            if not sel.size:
                unfolded = np.add(unfolded, _trend_steps(tracker, rec, sel, left_out, np.zeros(0, bool), {},
                                                         time_order=False))
                continue
            cols, reasons = {}, np.empty(sel.size, dtype=object)
            for s0 in range(0, sel.size, _CHUNK):
                part = sel[s0:s0 + _CHUNK]
                r = tracker.estimate_rows(rec.traces[part], rec.nozzle[part], stamp=float("nan"),
                                          sample_rate_hz=rec.sample_rate_hz)
                for k, v in r.columns.items():
                    cols.setdefault(k, np.empty(sel.size, dtype=v.dtype))[s0:s0 + part.size] = v
                reasons[s0:s0 + part.size] = r.reasons
                if r.note:
                    notes.add(r.note)
            stamps, frames = rec.stamp[sel], rec.frame_id[sel]
            seen.append((rec.nozzle[sel], frames, stamps))
            # each frame's trend update in bag order (one message is one frame's range)
            unfolded = np.add(unfolded, _trend_steps(tracker, rec, sel, left_out, reasons == "", cols,
                                                     time_order=False))
            for i in range(sel.size):  # formatting only
                w.writerow([first_row + int(sel[i]), int(rec.nozzle[sel[i]]), _fmt(cols["fm"][i]),
                            _fmt(cols["fm_std"][i]), _fmt(cols["d_mu"][i]), _fmt(cols["viscosity"][i]),
                            int(frames[i]), _fmt(stamps[i]), _fmt(cols["fm_trend"][i]), _fmt(cols["fm_rate"][i]),
                            _fmt(cols["eta_deeply_dried_s"][i]), method, reasons[i]])
                if reasons[i]:
                    why[reasons[i]] = why.get(reasons[i], 0) + 1
            n += sel.size
            n_bad += int((reasons != "").sum())
    report_stats(args.recording, stats)
    if why_past := pick.beyond(n_seen):
        raise InputError(f"{why_past} (the bag has {n_seen} rows; {n} rows estimated into "
                         f"{'stdout' if args.out == '-' else args.out})"
                         + (": labels of another recording?" if args.labels else ""))
    print(f"inkdiag estimate: {n - n_bad} of {n} rows estimated ({method}, head {profile.name!r})"
          + (f"; not estimated: {', '.join(f'{k} {v}' for k, v in sorted(why.items()))}" if n_bad else "")
          + _against(tracker, n - n_bad, notes) + _to(args.out), file=summary_stream(args.out))
    for note in sorted(notes):
        print(f"inkdiag estimate: note: {note}", file=sys.stderr)
    _say_none(args, n)
    _say_after(seen, unfolded, why, n, tracker, bound_given=args.max_abs_v is not None)
    return 0


def _say_none(args, n: int) -> None:
    """A warning when ``--rows`` or ``--labels`` selected no row (the CSV holds its header only)."""
    import sys

    if n == 0 and (args.rows is not None or args.labels):
        what = f"--rows {args.rows}" + (f" of --labels {args.labels}" if args.labels else "")
        print(f"inkdiag estimate: warning: {what} selects no row of {args.recording}: the CSV holds its header only",
              file=sys.stderr)


def _left_out(args, n: int, selected):
    """Rows (of ``n``) a class ``--rows`` leaves out, whose nozzles fe would take as recovered (their drying lists
    leave them out); none for row indices or every row (an int64 array)."""
    import numpy as np

    if args.rows is None or _class_values(args.rows) is None:
        return np.zeros(0, dtype=np.int64)
    keep = np.ones(n, dtype=bool)
    keep[selected] = False
    return np.flatnonzero(keep)


def _trend_steps(tracker, rec, rows, left_out, estimated, cols, *, time_order: bool) -> tuple:
    """The trend steps of the frames of ``rec``'s rows ``rows`` (their ``estimated`` ones folded in; ``cols``:
    their columns, filled) and ``left_out`` (whose nozzles' trends end, as fe ends a nozzle's trend when its
    range's list leaves it out: :meth:`inkdiag_core.DryingTracker.end_recovered` of the nozzles not folded in that
    frame), frame by frame: in time order (stamp, frame_id: an .npz) or in the rows' order (a bag, its frames
    as received). Rows without a finite stamp take no step. Returns ``(left out, restarted)`` as
    :func:`_fold_frame`."""
    import numpy as np

    trends = tracker.trends
    # only nozzles that have a trend, or may get one here (a bag's earlier chunks gave the bank its trends)
    left_out = left_out[np.isin(rec.nozzle[left_out], np.union1d(trends.ids, rec.nozzle[rows]))]
    n = len(rows)
    at = np.concatenate([np.asarray(rows, dtype=np.int64), left_out])  # recording rows; the first n: ``cols``'
    fold = np.zeros(at.size, dtype=bool)
    fold[:n] = estimated
    use = np.flatnonzero(np.isfinite(rec.stamp[at]))  # the selected rows (estimated or not) and the left out
    stamps, frames = rec.stamp[at[use]], rec.frame_id[at[use]].astype(float)
    use = use[np.lexsort((frames, stamps)) if time_order else np.argsort(at[use], kind="stable")]
    keys = np.stack([rec.stamp[at[use]], rec.frame_id[at[use]].astype(float)], axis=1)
    unfolded = (0, 0)
    for grp in np.split(use, np.flatnonzero(np.any(keys[1:] != keys[:-1], axis=1)) + 1):  # one step per frame
        if grp.size:
            listed, t = grp[grp < n], float(rec.stamp[at[grp[0]]])
            gone = at[grp[grp >= n]]
            gone = gone[~np.isin(rec.nozzle[gone], rec.nozzle[at[listed]])]  # not a nozzle listed in this frame
            tracker.end_recovered(rec.nozzle[gone], rec.traces[gone], stamp=t, sample_rate_hz=rec.sample_rate_hz)
            trends.heard(rec.nozzle[at[listed]], t)  # as fe: a listed nozzle, estimated or not, is no miss
            mine = listed[fold[listed]]
            if mine.size:
                unfolded = np.add(unfolded, _fold_frame(trends, t, mine, cols))
    return unfolded


def _fold_frame(trends, t, grp, cols) -> tuple:
    """One frame's estimates (rows ``grp`` of ``cols``, stamp ``t``, s) folded into ``trends`` as fe's tracker folds
    them (:meth:`inkdiag_core.FmTrendBank.fold_newer`: each nozzle once, only after its last update; a frame
    ``CLOCK_RESET_S`` or more before the latest one starts a new clock, and each nozzle's trend restarts at its
    next frame). The rows left out keep NaN trend columns. Returns ``(left out, restarted)``."""
    import numpy as np

    trend, rate, eta, folded, restarted = trends.fold_newer(t, cols["nozzle"][grp], cols["fm"][grp],
                                                            cols["fm_std"][grp])
    cols["fm_trend"][grp], cols["fm_rate"][grp], cols["eta_deeply_dried_s"][grp] = trend, rate, eta
    return int(grp.size - np.count_nonzero(folded)), int(np.count_nonzero(restarted))


def _say_after(keys, unfolded, why, n, tracker, bound_given=False) -> None:
    """The warnings and notes after the CSV (both paths): rows repeating a (nozzle, frame_id, stamp) of ``keys``
    (chunks of those columns), rows not folded into or restarting trends (``unfolded``), a recording in other
    units (``why``: rows not estimated per reason), estimates mostly thinner than the ink (another head's profile?),
    stamps in other units. ``bound_given``: the out-of-range bound is the user's ``--max-abs-v``."""
    import sys

    import numpy as np
    from inkdiag_core.drying_tracker import BELOW_NOISE_FACTOR, BELOW_NOISE_REASON

    if keys and (n_repeated := repeated_pairs(*(np.concatenate(c) for c in zip(*keys)))):
        print(repeated_pairs_warning("estimate", n_repeated, "each is estimated"), file=sys.stderr)
    stale, restarted = unfolded
    if stale:
        print(f"inkdiag estimate: note: {stale} row(s) estimated but not folded into their nozzle's trend (fm_trend, "
              "fm_rate empty): their nozzle's trend was already updated, or ended as recovered, at that stamp or later "
              "(listed twice in a frame, frames of one stamp, or in a bag a frame out of time order)", file=sys.stderr)
    if restarted:
        from inkdiag_core.trend import CLOCK_RESET_S

        print(f"inkdiag estimate: note: {restarted} nozzle trend(s) restarted where the bag's stamps went back "
              f"{CLOCK_RESET_S:g} s or more (a restarted clock)", file=sys.stderr)
    if said := (units_warning("estimate", why.get("out_of_range", 0), n, tracker.max_abs_v, given=bound_given)
                or invalid_warning("estimate", why, n)):
        print(said, file=sys.stderr)
    if (thin := tracker.estimates_thinner) >= max(8, tracker.estimates / 2):
        from inkdiag_core.drying_tracker import THIN_FACTOR

        mu = tracker.model.params.mu
        print(f"inkdiag estimate: warning: {thin} of {tracker.estimates} estimated rows come out thinner than the "
              f"profile's ink (a viscosity below {THIN_FACTOR:g}x its mu, {THIN_FACTOR * mu:.3g} Pa s), which no "
              "nozzle does: is the profile this head's, and its mu the ink's at the head's temperature?",
              file=sys.stderr)
    st = np.concatenate([c[2] for c in keys]) if keys else np.zeros(0)
    if ((st := st[np.isfinite(st)]) > MAX_STAMP_S).any():
        print(f"inkdiag estimate: warning: stamps up to {st.max():.4g} s, more than {MAX_STAMP_S:g} s (about "
              "30,000 years) after 1970: in nanoseconds or milliseconds? A recording's stamps are seconds; the trend "
              "columns (fm_rate, eta_deeply_dried_s) take them as such", file=sys.stderr)
    if (quiet := why.get(BELOW_NOISE_REASON, 0)) and quiet >= n / 2:
        print(f"inkdiag estimate: warning: {quiet} of {n} rows do not ring above the profile's sensor noise (an AC rms "
              f"of {tracker.min_ac_rms_v:.3g} V or less, {BELOW_NOISE_FACTOR:g}x its noise_std_v): traces in other "
              "units (kilovolts?), or nozzles that did not fire or hold no ink?", file=sys.stderr)
