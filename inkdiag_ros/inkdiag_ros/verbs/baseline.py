"""``inkdiag baseline``: a head's per-nozzle healthy baselines from a recording, as record_baseline writes them."""

REPLACES_OUT = True  # its file is written beside --out and renamed over it
MAX_FRAMES = 1000
"""Largest --frames (the record_baseline node's n_frames range)."""

HELP = "record per-nozzle healthy baselines from a recording of a healthy head (.npz or bag)"
DESCRIPTION = """\
Build each nozzle's healthy baseline from a recording of the head while it jets
well (after a purge, at commissioning): the same file the record_baseline node
writes, by the same code (inkdiag_core.BaselineRecorder), for `inkdiag label
--baselines`, `inkdiag estimate --baselines` and the nodes' baseline_path.

Each row's nozzle id is the recording's `nozzle` column (a bag: each frame's
first nozzle and its row); a nozzle's baseline is the median KPIs of its first
--frames valid rows in recording order, plus its healthy reference trace (the
sample-wise median of the same rows, for fdi's healthy gate) and, with
--fm-frames > 0, its healthy f_m reading (the median over its first
--fm-frames rows, for fe). Rows screening refuses (non-finite, beyond
--max-abs-v, flat, clipped) are skipped; if the recording has a label column, only its
healthy_nozzle rows are used. Nozzles with fewer than --min-frames usable rows
get no baseline (the message counts them): fdi and fe treat them as nozzles
without one.

The recording must have the profile's sampling (a complete profile, from
`inkdiag calibrate`); the file records the profile's sha256, and models and
profiles of another head refuse it.

example:
  inkdiag baseline commissioning.npz --profile head.yaml --out baselines.npz
"""


def add_arguments(parser) -> None:
    parser.add_argument("recording", metavar="RECORDING",
                        help="recording (.npz) or rosbag2 bag directory of the healthy head, several frames a nozzle")
    parser.add_argument("--topic", default=None, metavar="TOPIC", help="traces topic of a bag (default: its one "
                        "Float32MultiArray topic ending in /traces)")
    parser.add_argument("--profile", required=True, metavar="HEAD.yaml", help="the head's complete profile")
    parser.add_argument("--out", required=True, metavar="B.npz", help="baselines file to write")
    parser.add_argument("--frames", type=int, default=8, metavar="N",
                        help=f"valid rows per nozzle in its baseline, the median, 1..{MAX_FRAMES} (default 8, as "
                        "record_baseline)")
    parser.add_argument("--min-frames", type=int, default=None, metavar="N",
                        help="fewest usable rows a nozzle's baseline may rest on (default: --frames)")
    parser.add_argument("--fm-frames", type=int, default=None, metavar="N",
                        help="rows per nozzle for its healthy f_m reading, 0..--frames; 0: none "
                        "(about 1 ms of CPU per row; default 3 or --frames if fewer, as record_baseline)")
    parser.add_argument("--max-abs-v", type=float, default=None, metavar="V",
                        help="a row with a sample beyond +-V is not used (default: 5x the profile's ADC range, as fdi)")


def run(args) -> int:
    import sys

    import numpy as np
    from inkdiag_core import BaselineRecorder, FaultClass, HeadProfile

    from ..bags import report_stats, stream_recording
    from . import check_max_abs_v, repeated_pairs, repeated_pairs_warning

    if not 1 <= args.frames <= MAX_FRAMES:
        raise ValueError(f"--frames must be in 1..{MAX_FRAMES}, got {args.frames}")
    fm_frames = min(3, args.frames) if args.fm_frames is None else args.fm_frames
    if not 0 <= fm_frames <= args.frames:
        raise ValueError(f"--fm-frames must be in 0..--frames ({args.frames}), got {fm_frames}")
    check_max_abs_v(args.max_abs_v)
    min_frames = args.frames if args.min_frames is None else args.min_frames
    if not 1 <= min_frames <= args.frames:
        raise ValueError(f"--min-frames must be in 1..--frames ({args.frames}), got {min_frames}")
    profile = HeadProfile.load(args.profile)
    recorder = BaselineRecorder(n_frames=args.frames, fm_frames=fm_frames, profile=profile,  # nominal: refused
                                max_abs_v=args.max_abs_v)
    stats, chunks = stream_recording(args.recording, args.topic,  # a bag's frames of another sampling: skipped
                                     sampling=(profile.sample_rate_hz, profile.n_samples, f"profile {profile.name!r},"))
    n_rows = n_used = n_other = 0
    nozzles = np.zeros(0, np.int64)  # every nozzle id the recording has, usable rows or not
    keys = []  # each chunk's (nozzle, frame_id, stamp) columns: repeats are said at the end
    for _, rec in chunks:  # a bag with no trace frame: RecordingError
        profile.check_traces(rec.traces, rec.sample_rate_hz, what=f"{args.recording}")
        keep = np.ones(rec.n_rows, bool)
        if rec.label is not None:
            keep = np.asarray(rec.label).astype(str) == FaultClass.HEALTHY_NOZZLE.value
            n_other += int(np.count_nonzero(~keep))
        n_used += recorder.add_rows(rec.nozzle, rec.traces, keep=keep)
        nozzles = np.union1d(nozzles, rec.nozzle)
        keys.append((rec.nozzle[keep], rec.frame_id[keep], rec.stamp[keep]))  # the rows it may use
        n_rows += rec.n_rows
    report_stats(args.recording, stats)
    baselines = recorder.baselines(min_frames=min_frames)
    n_unlike = recorder.unlike_head[0].size
    short = nozzles.size - len(baselines) - n_unlike
    quiet = recorder.rows_not_ringing
    if not len(baselines):
        raise ValueError(f"{args.recording}: no nozzle has {min_frames} usable healthy rows (of {n_rows} rows, "
                         f"{n_used} usable{f', {n_other} not labelled healthy_nozzle' if n_other else ''}"
                         f"{f', {quiet} not ringing above their noise' if quiet else ''}): "
                         + ("no nozzle id comes twice (a recording without a 'nozzle' column numbers its rows "
                            "0..n-1): give each row's nozzle id, or --frames 1 for one frame"
                            if nozzles.size == n_rows > 1 and min_frames > 1 and n_used else
                            "are they healthy nozzles fired with the head's drive, in volts?" if quiet >= n_rows / 2
                            else "record more frames of each nozzle, or lower --min-frames"))
    baselines.save(args.out)
    print(f"inkdiag baseline: baselines of {len(baselines)} nozzles (head {profile.name!r}) from {n_used} of "
          f"{n_rows} rows"
          + (f" ({n_other} not labelled healthy_nozzle)" if n_other else "")
          + (f" ({quiet} not ringing above their noise: nozzles that did not fire?)" if quiet else "")
          + (f"; {short} nozzles with fewer than {min_frames} usable rows left out" if short else "")
          + (f"; {n_unlike} ringing unlike the others left out" if n_unlike else "")
          + f"; wrote {args.out}", file=sys.stdout)
    ids, fids, stamps = (np.concatenate(c) for c in zip(*keys))
    tells_frames_apart = bool(np.any(fids != 0) or np.any(np.isfinite(stamps)))  # else nozzle ids alone say it
    if tells_frames_apart and (n_repeated := repeated_pairs(ids, fids, stamps)):
        print(repeated_pairs_warning("baseline", n_repeated, "each is counted as one of its nozzle's --frames, so "
                                     "a baseline may rest on fewer distinct frames"), file=sys.stderr)
    if why := recorder.unlike_note():
        print(f"inkdiag baseline: warning: {why}", file=sys.stderr)
    if why := baselines.gain_mismatch(profile):
        print(f"inkdiag baseline: warning: {why}", file=sys.stderr)
    return 0
