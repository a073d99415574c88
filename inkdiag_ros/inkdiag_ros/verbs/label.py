"""``inkdiag label``: classify every row of a recording with a fault detector, as the fdi node does."""

OUT_STDOUT = True  # --out - writes the CSV to standard output
HELP = "label every trace of a recording with a trained fault detector (CSV)"
DESCRIPTION = """\
Label every row of a recording (.npz: traces, sample_rate_hz, optional nozzle,
frame_id, stamp; or a rosbag2 bag directory, its traces topic chosen by --topic)
with a fault detector from `inkdiag train`, by the fdi node's
code path (inkdiag_core.FrameLabeller): rows are screened first (non-finite,
out-of-range, flat, clipped: class 'invalid' with that reason; the other rows
are classified), then one detector call per batch of frames. Rows with the
same frame_id are one frame; with --baselines each row's nozzle id selects its
nozzle's recorded healthy baseline (the model needs a baseline branch:
`inkdiag train --baseline`).

The recording must have the sampling (sample rate, samples per trace) of the
model's head; another is refused (exit status 2), as is a model file that is
missing, tampered with or from other library versions.

CSV columns: row, nozzle, frame_id, class, confidence, reason, baseline
  class       a FaultClass value (healthy_nozzle, ...), 'unknown' (unlike every
              class the model knows) or 'invalid'
  confidence  probability of that class (empty for invalid rows)
  reason      why a row is invalid (non_finite, out_of_range, flat, clipped,
              non_finite_features, labelling_failed); empty for classified rows
  baseline    1 if the row was classified against its nozzle's baseline

A bag is streamed: read, labelled and written a chunk of whole frames at a
time (16384 rows at most), in bounded memory whatever its length; a message
that is not a valid trace frame (or of another sampling than the model's
head) is reported on stderr with its message index and why, and skipped.

example:
  inkdiag label recording.npz --model models/head.joblib --out labels.csv
"""

COLUMNS = ("row", "nozzle", "frame_id", "class", "confidence", "reason", "baseline")
#: Rows labelled per detector call at most (frames are never split).
BATCH_ROWS = 16384


def add_arguments(parser) -> None:
    parser.add_argument("recording", metavar="RECORDING", help="recording (.npz) or rosbag2 bag directory to label")
    parser.add_argument("--topic", default=None, metavar="TOPIC", help="traces topic of a bag (default: its one "
                        "Float32MultiArray topic ending in /traces)")
    parser.add_argument("--model", required=True, metavar="MODEL.joblib",
                        help="FaultDetector file from `inkdiag train` (its .manifest.json beside it)")
    parser.add_argument("--baselines", metavar="B.npz",
                        help="the head's per-nozzle healthy baselines (from inkdiag baseline or record_baseline)")
    parser.add_argument("--out", required=True, metavar="LABELS.csv", help="CSV file to write ('-': stdout)")
    parser.add_argument("--max-abs-v", type=float, default=None, metavar="V",
                        help="largest sample magnitude a sensor can produce, V; a row beyond it is invalid "
                        "(out_of_range). Default: 5x the model head's ADC range")


def frames_of(frame_id):
    """Rows of each frame, frames in order of first appearance: a list of int index arrays."""
    import numpy as np

    uniq, first, inverse = np.unique(frame_id, return_index=True, return_inverse=True)
    order = np.argsort(first, kind="stable")
    rows = np.argsort(inverse, kind="stable")  # rows grouped by frame, in row order within each
    cuts = np.cumsum(np.bincount(inverse, minlength=uniq.size))[:-1]
    groups = np.split(rows, cuts)
    return [groups[k] for k in order]


def label_recording(labeller, recording):
    """Label a :class:`inkdiag_core.Recording` frame by frame with a :class:`inkdiag_core.FrameLabeller`.

    Returns
    -------
    classes : ndarray of object, shape (n,)
        FaultClass value or ``"invalid"``.
    confidence : ndarray of float, shape (n,)
        NaN for invalid rows.
    reasons : ndarray of object, shape (n,)
        ``""`` for classified rows.
    baseline : ndarray of bool, shape (n,)
    """
    import numpy as np

    from inkdiag_core import FrameFailure

    n = recording.n_rows
    classes = np.full(n, "invalid", dtype=object)
    confidence = np.full(n, np.nan)
    reasons = np.full(n, "", dtype=object)
    baseline = np.zeros(n, dtype=bool)
    batches, cur, size = [], [], 0
    for rows in frames_of(recording.frame_id):  # whole frames, at most BATCH_ROWS rows a batch (or one frame)
        if cur and size + rows.size > BATCH_ROWS:
            batches.append(cur)
            cur, size = [], 0
        cur.append(rows)
        size += rows.size
    if cur:
        batches.append(cur)
    for batch in batches:
        results = labeller.label([recording.traces[r] for r in batch], [0] * len(batch),
                                 nozzles=[recording.nozzle[r] for r in batch])
        for r, res in zip(batch, results):
            if isinstance(res, FrameFailure):
                reasons[r] = "labelling_failed"
                continue
            ok = res.valid
            classes[r[ok]] = res.classes[ok]
            confidence[r[ok]] = res.confidence[ok]
            reasons[r[~ok]] = res.reasons[~ok]
            if res.baseline is not None:
                baseline[r] = res.baseline
    return classes, confidence, reasons, baseline


def label_stream(labeller, chunks):
    """Label chunks of a recording as they come: the CSV rows of each chunk before the next is read.

    Parameters
    ----------
    labeller : inkdiag_core.FrameLabeller
    chunks : iterable of (int, Recording)
        ``(first_row, chunk)`` as :func:`inkdiag_ros.bags.stream_recording` gives (whole frames a chunk).

    Yields
    ------
    tuple
        One per row, in chunk order: ``(row, nozzle, frame_id, class, confidence, reason, baseline)``
        (:data:`COLUMNS`; confidence NaN for invalid rows, baseline bool).
    """
    for first_row, rec in chunks:
        classes, confidence, reasons, baseline = label_recording(labeller, rec)
        nozzle, frame_id = rec.nozzle.tolist(), rec.frame_id.tolist()
        for i in range(rec.n_rows):
            yield (first_row + i, nozzle[i], frame_id[i], classes[i], float(confidence[i]), reasons[i],
                   bool(baseline[i]))


def run(args) -> int:
    import collections
    import csv
    import itertools
    import sys

    import numpy as np
    from inkdiag_core import FrameLabeller, LabellerConfigError, NozzleBaselines, load_detector
    from inkdiag_core.head_profile import HeadProfile, same_sample_rate
    from ..bags import report_stats, stream_recording
    from . import (NO_BASELINE_HINT, check_max_abs_v, invalid_warning, open_csv_out, repeated_pairs, repeated_pairs_warning,
                   summary_stream, units_warning)

    check_max_abs_v(args.max_abs_v)  # before the model and the recording are read
    detector = load_detector(args.model)  # ModelFileError (a ValueError): missing, tampered, other versions
    head = detector.profile if detector.profile is not None else HeadProfile.default()
    stats, chunks = stream_recording(args.recording, args.topic, max_rows=BATCH_ROWS,  # a bag's others: skipped
                                     sampling=(detector.sample_rate_hz_, detector.n_features_in_,
                                               f"the model's head {head.name!r},"))
    first = next(chunks)  # a bag with no trace frame: RecordingError
    rec = first[1]
    same_rate = same_sample_rate(rec.sample_rate_hz, detector.sample_rate_hz_)  # as check_traces
    if not same_rate or rec.n_samples != detector.n_features_in_:
        raise LabellerConfigError(
            f"{args.recording} is sampled at {rec.sample_rate_hz:.10g} Hz x {rec.n_samples} samples; the model is for "
            f"head {head.name!r} at {detector.sample_rate_hz_:.10g} Hz x {detector.n_features_in_}: label recordings "
            "of the head the model was trained for")
    max_abs_v = args.max_abs_v if args.max_abs_v is not None else head.max_abs_v
    baselines = NozzleBaselines.load(args.baselines) if args.baselines else None
    labeller = FrameLabeller(detector, baselines, sample_rate_hz=detector.sample_rate_hz_, n_samples=rec.n_samples,
                             max_abs_v=max_abs_v)
    del rec
    n_rows = n_invalid = n_failed = n_base = n_out_of_range = 0
    per_class, per_reason = collections.Counter(), collections.Counter()
    keys = []  # each chunk's (nozzle, frame_id, stamp) columns: repeats are said at the end
    current, blocked = [], []  # the chunk being labelled; traces of rows labelled fully blocked (the restrictor check)
    with open_csv_out(args.out) as out:
        w = csv.writer(out, lineterminator="\n")
        w.writerow(COLUMNS)
        for row, nozzle, fid, cls, conf, reason, base in label_stream(labeller, _keys_of(itertools.chain([first], chunks),
                                                                                  keys, current)):
            if cls == "invalid":
                n_invalid += 1
                per_reason[reason] += 1
            else:
                per_class[cls] += 1
                if cls == "fully_blocked" and len(blocked) < MAX_BLOCKED_KEPT:
                    blocked.append(np.array(current[1][row - current[0]]))
            w.writerow((row, nozzle, fid, cls, "" if conf != conf else f"{conf:.6f}", reason, int(base)))
            n_rows += 1
            n_base += bool(base)
    report_stats(args.recording, stats)
    n_failed, n_out_of_range = per_reason["labelling_failed"], per_reason["out_of_range"]
    against = ""
    if baselines is not None:  # a nozzle column that does not match the baselines' ids is said, not silent
        n_plain = n_rows - n_invalid - n_base
        against = (f"; {n_base} against their nozzle's baseline, {n_plain} without one ({NO_BASELINE_HINT})"
                   if n_plain else f"; all {n_base} against their nozzle's baseline")
    failed = f", {n_failed} in frames whose labelling failed" if n_failed else ""
    print(f"inkdiag label: labelled {n_rows - n_invalid} of {n_rows} rows with {detector.model_id} (head "
          f"{head.name!r}); {n_invalid} invalid{failed}" + against + (f"; wrote {args.out}" if args.out != "-" else ""),
          file=summary_stream(args.out))
    if said := units_warning("label", n_out_of_range, n_rows, max_abs_v, given=args.max_abs_v is not None):
        print(said, file=sys.stderr)
    elif said := invalid_warning("label", per_reason, n_rows):
        print(said, file=sys.stderr)
    if keys and (n_repeated := repeated_pairs(*(np.concatenate(c) for c in zip(*keys)))):
        print(repeated_pairs_warning("label", n_repeated, "each is labelled" + (
            " against that nozzle's baseline" if baselines is not None else "")), file=sys.stderr)
    said = _one_fault_class_dominates(per_class, head)
    if said:
        print(f"inkdiag label: warning: {said}", file=sys.stderr)
    if baselines is not None and (said := baselines.gain_mismatch(head)):
        print(f"inkdiag label: warning: {said}", file=sys.stderr)
    if detector.profile is not None and (said := _blocked_mode_warning(head, blocked, detector.sample_rate_hz_, args)):
        print(f"inkdiag label: warning: {said}", file=sys.stderr)
    return 1 if n_failed else 0


def _keys_of(chunks, keys: list, current: list):
    """``chunks`` as they come, each chunk's ``(nozzle, frame_id, stamp)`` columns appended to ``keys``;
    ``current[:] = [first_row, traces]`` of the chunk whose rows are being labelled."""
    for first_row, rec in chunks:
        keys.append((rec.nozzle, rec.frame_id, rec.stamp))
        current[:] = [first_row, rec.traces]
        yield first_row, rec


#: Traces of the rows labelled fully blocked that ``inkdiag label`` keeps to check the model's restrictor, at most.
MAX_BLOCKED_KEPT = 400


def _blocked_mode_warning(head, blocked, sample_rate_hz, args) -> str:
    """A warning when the rows labelled fully blocked ring away from the model profile's fully blocked nozzles
    (:func:`inkdiag_core.calibration.blocked_mode_offset`): its restrictor, which healthy traces leave to a prior,
    is likely off, and the second pass pins it. "" otherwise."""
    from collections.abc import Mapping

    from inkdiag_core.calibration import BLOCKED_MODE_WARNING, blocked_mode_offset

    got = blocked_mode_offset(head, blocked, sample_rate_hz) if len(blocked) else None
    if got is None or abs(got["offset_rel"]) <= BLOCKED_MODE_WARNING:
        return ""
    said = (f"the rows labelled fully_blocked ({got['n_traces']} usable of the first {MAX_BLOCKED_KEPT} at most) ring "
            f"at {got['recorded_hz'] / 1e3:.1f} kHz, the model's fully blocked nozzles at {got['model_hz'] / 1e3:.1f} "
            f"kHz ({100 * got['offset_rel']:+.1f} %; a well calibrated head's within {100 * BLOCKED_MODE_WARNING:g} %)")
    cal = head.calibration if isinstance(head.calibration, Mapping) else {}
    if "blocked_mode_hz" in cal:  # a second pass made this profile already: the restrictor is not what is off
        return (f"{said}, though the model's profile was calibrated with {cal.get('n_blocked_traces', 'some')} fully "
                f"blocked traces ringing at {float(cal['blocked_mode_hz']) / 1e3:.1f} kHz: are these rows fully "
                "blocked nozzles of that head, recorded at the same ink temperature?")
    topic = f" --topic {args.topic}" if args.topic else ""
    return (f"{said}: the profile's restrictor, which healthy traces leave to a prior, is likely off, and then "
            "partially blocked and dried nozzles are labelled as each other. The second pass pins it: inkdiag "
            f"calibrate HEALTHY.npz --nominal NOMINAL.yaml{topic} --blocked {args.recording} --blocked-labels "
            f"{args.out if args.out != '-' else 'THESE.csv'} --out HEAD2.yaml, then train on HEAD2.yaml")


#: ``inkdiag label`` warns when one fault class (or ``unknown``) is more than this share of the labelled rows.
DOMINANT_SHARE = 0.5
#: ... and at least this many rows.
DOMINANT_MIN_ROWS = 20


def _one_fault_class_dominates(per_class, head) -> str:
    """A warning when one fault class or ``unknown`` is most of the labelled rows, else "".

    A working head has few faulty nozzles, and faulty ones of several kinds; a model of another
    head with the same sampling labels every healthy trace as one fault (a 213 kHz head's healthy
    traces all came out intermediate_air_bubble with a 169 kHz head's model). A recording of every
    class in equal numbers, or a head failing in several ways, is not warned about.
    """
    from inkdiag_core.faults import HEALTHY_VALUES

    n = sum(per_class.values())
    faults = [(k, c) for c, k in per_class.items() if c not in HEALTHY_VALUES]
    if n < DOMINANT_MIN_ROWS or not faults:
        return ""
    k, cls = max(faults)
    if k <= DOMINANT_SHARE * n:
        return ""
    f_hz, _ = head.healthy_mode()
    return (f"{k} of {n} labelled rows ({100 * k / n:.0f} %) are {cls}: a working head has few faulty nozzles. "
            f"If this recording is of a working head, is the model for this head? It was trained for head "
            f"{head.name!r}, healthy mode {f_hz / 1e3:.1f} kHz; another head's model with the same sampling labels "
            "its healthy traces as one fault (a recording of faulty nozzles made on purpose can ignore this)")
