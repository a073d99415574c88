"""``inkdiag train``: a FaultDetector for one head, from its complete profile (and labelled recordings)."""

HELP = "train a fault detector for a head from its complete profile"
REPLACES_OUT = True  # its file is written beside --out and renamed over it
MAKES_OUT_DIR = True  # save_detector creates the model's directory: cli does not require it to exist
DESCRIPTION = """\
Train a fault detector (FaultDetector .joblib + .manifest.json) for the head of
a complete profile: every fault class is simulated on the head's calibrated
model (the same physical mechanisms as the default head's, scaled to its
geometry, ink, drive and sampling), a quarter held out for the detection
threshold and the validation scores. For a profile `inkdiag calibrate` wrote,
the simulated traces are spread over --posterior-draws restrictors within a few
per cent of the fitted one, which healthy traces pin only that well (it decides
where partially blocked and dried nozzles ring).

The detector also gets an open-set layer (--unknown-rate, default 0.01): a
trace unlike every known class is labelled 'unknown', and a trace of a known
class is called 'unknown' with probability at most that rate, for the model
this run trains, with 90 % confidence (per-class training-conditional
conformal p-values; a class needs (1 - R)**n <= 0.1 calibration rows n, 230
for the default rate: the training three quarters of --n-per-class >= 307).
Traces that ring below 3 noise sigmas are judged by that weakness alone: for
a class weak in about R of its rows the bound is about 2 R with 80 %
confidence (docs/cli.md).

With --data, the head's own labelled recordings join the simulated rows: an
.npz with a 'label' array, or any recording (.npz or rosbag2 bag) with
--labels LABELS.csv (a 'class' per 'row', as `inkdiag label` writes it and you
corrected it, or per 'nozzle' from an inspection): a quarter of each recorded class is held out for
validation; the rest is replicated up to the simulated rows of its class, so a
recorded class weighs as much as its simulated one.

The manifest records the profile (and its sha256: the fdi node refuses the model
for another head's profile; `inkdiag label` refuses it for a recording of another
sampling), the training configuration and the
validation scores, which are printed at the end.

A nominal profile (only a datasheet's values) is refused: run `inkdiag
calibrate` on recorded healthy traces first.

example:
  inkdiag train --profile head.yaml --out models/head.joblib
  inkdiag train --profile head.yaml --out models/head.joblib --baseline --n-per-class 600
  inkdiag train --profile head.yaml --out models/head.joblib --unknown-rate 0.005
  inkdiag train --profile head.yaml --out models/head.joblib --data bags/run3 --labels run3_checked.csv
"""

FEATURES = ("kpi_y", "kpi_r", "kpi_r_modified", "kpi_y+r_modified", "rich")


#: The largest simulated training set ``--n-per-class`` may ask for (its float32 traces), bytes.
_MAX_TRAINING_BYTES = 4 * 2**30


def add_arguments(parser) -> None:
    parser.add_argument("--profile", required=True, metavar="HEAD.yaml", help="complete head profile (YAML)")
    parser.add_argument("--out", required=True, metavar="MODEL.joblib",
                        help="model file to write (its manifest is written beside it)")
    parser.add_argument("--features", default="kpi_y", choices=FEATURES,
                        help="feature set of the plain branch (default: %(default)s)")
    parser.add_argument("--kind", default="rf", choices=("rf", "knn"),
                        help="classifier: random forest or k-nearest neighbours (default: %(default)s)")
    parser.add_argument("--baseline", action="store_true",
                        help="also train the per-nozzle baseline branch (for fdi's / label's --baselines)")
    parser.add_argument("--data", metavar="RECORDING",
                        help="a labelled recording of this head to train on as well: an .npz with a 'label' per "
                        "row, or an .npz or rosbag2 bag with --labels")
    parser.add_argument("--labels", metavar="LABELS.csv",
                        help="each --data row's class: a CSV with 'class' and 'row' (as `inkdiag label` writes) or "
                        "'nozzle' (every row of it; with 'frame_id', of that frame) columns; rows it does not name "
                        "are left out")
    parser.add_argument("--topic", default=None, metavar="TOPIC",
                        help="traces topic of a bag given as --data (default: the one trace topic it has)")
    parser.add_argument("--n-per-class", type=int, default=5000, metavar="N",  # training.N_PER_CLASS (a test pins it)
                        help="simulated traces per class (default: %(default)s; >= 8); the forest's leaves hold "
                        "at least 3 per 1,000 of them")
    parser.add_argument("--seed", type=int, default=0, help="seed of the simulation, split and forest "
                        "(default: %(default)s)")
    parser.add_argument("--unknown-rate", type=float, default=0.01, metavar="R",
                        help="open-set layer: a trace of a known class is called 'unknown' with probability <= R "
                        "(conformal, per class; default: %(default)s; 0: no layer, never 'unknown')")
    parser.add_argument("--posterior-draws", type=int, default=5, metavar="K",  # calibration.POSTERIOR_DRAWS
                        help="spread the simulated traces over K restrictors a calibrated profile's healthy traces "
                        "allow, within calibration's own scatter (the restrictor against the actuator compliance, "
                        "with the healthy mode kept): a model that leans less on the fitted restrictor; see "
                        "docs/cli.md (default: %(default)s; 1: the profile alone; no effect on a profile "
                        "calibration did not write or whose restrictor it did not fit)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def extra_outputs(args) -> list:
    """The model's manifest, written beside ``--out`` (cli refuses it over an input)."""
    from inkdiag_core.persistence import manifest_path

    return [manifest_path(args.out)]


def _progress(quiet):
    """A progress callable and a close function: tqdm on stderr if available, else a plain line per stage."""
    import sys

    if quiet:
        return (lambda step, total, message: None), (lambda: None)
    try:
        from tqdm import tqdm
    except ImportError:  # a plain bar
        def plain(step, total, message):
            bar = "#" * step + "." * (total - step)
            print(f"[{bar}] {step}/{total} {message}", file=sys.stderr, flush=True)

        return plain, (lambda: None)
    bar = tqdm(total=4, file=sys.stderr, desc="inkdiag train", unit="stage", leave=True)

    def step(step, total, message):
        bar.set_postfix_str(message)
        bar.update(step - bar.n)

    return step, bar.close


def run(args) -> int:
    import math
    import sys
    from pathlib import Path

    import numpy as np

    from inkdiag_core import labels_from_csv, read_labels_csv
    from inkdiag_core.recording import NOT_CLASSES
    from inkdiag_core.head_profile import HeadProfile, ProfileError
    from inkdiag_core.calibration import assumed_actuator_warning, restrictor_spread
    from inkdiag_core.persistence import save_detector
    from ..bags import is_bag, load_and_report
    from inkdiag_core.training import train_detector

    profile = HeadProfile.load(args.profile)
    try:
        restrictor_spread(profile)  # a malformed calibration.posterior: refused before anything is loaded
    except ProfileError as exc:
        raise ProfileError(f"{args.profile}: {exc}") from None
    if not profile.is_complete:
        raise ProfileError(f"{args.profile}: a nominal profile ({', '.join(profile.missing)} missing): run "
                           "`inkdiag calibrate` first to fit them to recorded healthy traces")
    if args.n_per_class < 8:
        raise ValueError(f"--n-per-class must be >= 8, got {args.n_per_class}")
    from inkdiag_core import FaultClass

    most = _MAX_TRAINING_BYTES // (len(FaultClass) * profile.n_samples * 4)  # float32 traces of every class
    if args.n_per_class > most:
        raise ValueError(f"--n-per-class must be at most {most} for {profile.n_samples}-sample traces (the training "
                         f"set's traces within {_MAX_TRAINING_BYTES / 2**30:g} GiB), got {args.n_per_class}")
    if args.posterior_draws < 1:
        raise ValueError(f"--posterior-draws must be >= 1, got {args.posterior_draws}")
    from inkdiag_core.calibration import posterior_profiles

    if args.posterior_draws > args.n_per_class and len(posterior_profiles(profile, 2)) > 1:  # else no effect
        raise ValueError(f"--posterior-draws ({args.posterior_draws}) must not exceed --n-per-class "
                         f"({args.n_per_class}): each restrictor simulates --n-per-class / --posterior-draws traces "
                         "per class")
    if not 0 <= args.unknown_rate < 1:
        raise ValueError(f"--unknown-rate must be in [0, 1) (0: no 'unknown'), got {args.unknown_rate!r}")
    if not 0 <= args.seed < 2**32:
        raise ValueError(f"--seed must be in 0..2**32-1, got {args.seed}")
    if args.labels and not args.data:
        raise ValueError("--labels names the classes of --data's rows: give --data RECORDING too")
    if args.data and is_bag(args.data) and not args.labels:  # refused before reading it
        raise ValueError(f"{args.data}: a rosbag2 bag has no per-row labels: give each row's class with "
                         "--labels LABELS.csv (columns row, class, as `inkdiag label` writes them)")
    if args.data and args.baseline:
        raise ValueError("--baseline with --data: recorded rows have no per-nozzle baselines; train the baseline "
                         "branch on simulated rows only (leave out --data) or train without --baseline")
    table = read_labels_csv(args.labels) if args.labels else None  # checked before a large recording is read
    data = None
    if args.data:  # a bag's frames of another sampling: skipped, as label skips them (its CSV's rows)
        data = load_and_report(args.data, args.topic,
                               sampling=(profile.sample_rate_hz, profile.n_samples, f"profile {profile.name!r},"))
    if data is not None:
        profile.check_traces(data.traces, data.sample_rate_hz, what=args.data)
        if table is not None:
            had = data.label is not None
            data, n_named = labels_from_csv(data, table)
            n_class = int(np.isin(data.label, NOT_CLASSES, invert=True).sum())
            print(f"{args.labels}: {n_named} of the {data.n_rows} rows of {args.data} named, {n_class} with a class"
                  + (" (in place of the recording's own 'label')" if had else ""))
            if why := table.coverage_warning(n_named, data.n_rows, args.data):
                print(f"inkdiag train: warning: {why}", file=sys.stderr)
        if data.label is None:
            raise ValueError(f"{args.data}: no 'label' array: --data needs each row's class (or give them with "
                             "--labels LABELS.csv)")
    out = Path(args.out)
    if out.is_dir():
        raise IsADirectoryError(f"--out {out} is a directory; give the model file's name")
    if out.name.endswith(".manifest.json"):  # over another model's: that model would no longer load
        raise ValueError(f"--out {out} names a model's manifest, which train writes beside the model: give the "
                         f"model file's name ({out.name[:-len('.manifest.json')] or 'head.joblib'})")
    if why := assumed_actuator_warning(profile):
        print(f"inkdiag train: warning: {why}", file=sys.stderr)
    report, close = _progress(args.quiet)
    try:
        det, info = train_detector(profile, features=args.features, kind=args.kind, baseline=args.baseline,
                                   n_per_class=args.n_per_class, data=data, seed=args.seed,
                                   unknown_rate=args.unknown_rate or None, posterior_draws=args.posterior_draws,
                                   progress=report)
        info["profile_file"] = str(args.profile)
        for key, path in (("data", args.data), ("labels", args.labels)):  # what was read, not only where
            if path:
                info[f"{key}_file"], info[f"{key}_sha256"] = str(path), content_sha256(path)
        mpath = save_detector(det, out, config=info)
        report(4, 4, f"saved {out}")
    finally:
        close()
    s = det.scores_
    print(f"model {det.model_id} for head {profile.name!r} (profile sha256 {profile.sha256[:12]})")
    print(f"validation ({s['n_validation']} rows): FI accuracy {100 * s['validation_fi_accuracy']:.1f} %, "
          f"at the FD threshold {det.fd_threshold_:.3f}: FI {100 * s['validation_fi_accuracy_at_threshold']:.1f} %, "
          f"faults missed {100 * s['validation_fd_fnr']:.2f} %, false alarms {100 * s['validation_fd_fpr']:.2f} %")
    if why := _poor_validation(s, profile):
        print(f"inkdiag train: warning: {why}", file=sys.stderr)
    if data is None:
        print("note: the validation rows are simulated on this profile, so these scores leave out how far the "
              "profile is from the head; labelling a recording of nozzles of known classes measures that")
    else:
        _recorded_rows(info, s)
    if det.baseline_scores_:
        b = det.baseline_scores_
        print(f"baseline branch: FI accuracy {100 * b['validation_fi_accuracy']:.1f} %, faults missed "
              f"{100 * b['validation_fd_fnr']:.2f} %, false alarms {100 * b['validation_fd_fpr']:.2f} %")
    if det.openset_ is not None:
        layer = det.openset_
        n_cal = [c.size for c in layer.calibration_]
        silent = [str(c) for c, a in zip(layer.classes_, layer.levels_) if a == 0]  # or without a model
        need = math.ceil(math.log(layer.delta) / math.log1p(-layer.rate))
        print(f"open-set layer: a trace of a known class is 'unknown' with probability <= {layer.rate:g} "
              f"(with {100 * (1 - layer.delta):g} % confidence); calibration rows per class {min(n_cal)}-{max(n_cal)}"
              + (f"; {len(silent)} classes have fewer than {need} ({', '.join(silent)}): with them the layer "
                 "never calls a trace unknown; raise --n-per-class" if silent else ""))
    print(f"wrote {out} and {mpath}")
    return 0


#: Validation scores below which the model is said to be poor: the heads of reports/heads.md validate at FI
#: 90-97 % with 0-0.5 % of faults missed and of false alarms; profiles with a value in other units trained
#: silently to FI 8-70 % with 8-100 % false alarms (helper-125).
POOR_FI, POOR_FD_RATE = 0.80, 0.02
#: Fewer validation rows than this (``--n-per-class`` below 200) may score poorly for their own sake: said too.
FEW_VALIDATION_ROWS = 600


def _poor_validation(scores, profile) -> str | None:
    """What to warn of when the model tells the profile's own simulated classes apart poorly, or None."""
    from inkdiag_core.head_profile import implausible_values

    fi, fnr, fpr = (scores[k] for k in ("validation_fi_accuracy", "validation_fd_fnr", "validation_fd_fpr"))
    if fi >= POOR_FI and fnr <= POOR_FD_RATE and fpr <= POOR_FD_RATE:
        return None
    odd = implausible_values(profile.channel)
    n_val = int(scores.get("n_validation", 0))
    few = (f"; or too few traces: {n_val} validation rows, raise --n-per-class" if n_val < FEW_VALIDATION_ROWS
           else "")
    return (f"the model tells the profile's own simulated classes apart poorly (FI {100 * fi:.1f} %, faults missed "
            f"{100 * fnr:.2f} %, false alarms {100 * fpr:.2f} %; a head's profile gives about 90-97 % and below "
            f"{100 * POOR_FD_RATE:g} %): check its values and units"
            + (f" (implausible: {'; '.join(odd)})" if odd else "")
            + ", its sensor (gain_v_per_m3s, adc_range_v, adc_bits, noise) and its spreads" + few)


#: A class with fewer recorded rows than this has none held out for validation (a quarter, rounded down).
FEW_REAL_ROWS = 4
#: The recorded validation rows' FI accuracy this far below the simulated ones' (at least
#: :data:`MIN_REAL_VALIDATION` rows) is warned about: their labels, or the profile, disagree with the simulation.
REAL_ACCURACY_GAP = 0.15
MIN_REAL_VALIDATION = 20


def _recorded_rows(info, scores) -> None:
    """What train says of ``--data``'s rows: how many were used, held out, repeated, left out, and their own
    validation score (a warning on stderr when far below the pooled one, a note for classes too small to check)."""
    import sys

    per = ", ".join(f"{c} {k}" for c, k in sorted(info["real_rows_per_class"].items()))
    n, n_val = info["n_real_rows"], info["n_real_rows_validation"]
    print(f"recorded rows: {n} used ({n - n_val} trained on, {n_val} held out for validation; {per}); "
          f"{info['n_real_rows_screened_out']} screened out (non-finite, out of range, flat, clipped), "
          f"{info['n_real_rows_without_class']} without a class")
    if info["n_real_rows_repeated"]:
        print(f"note: {info['n_real_rows_repeated']} recorded rows repeat another of their class exactly (kept, each "
              "on the same side of the validation split as its copies)")
    few = sorted(f"{c} ({k})" for c, k in info["real_rows_per_class"].items() if k < FEW_REAL_ROWS)
    if few:
        print(f"note: recorded classes of fewer than {FEW_REAL_ROWS} rows have none held out, so nothing checks their "
              f"labels, and each row is replicated to the simulated count: {', '.join(few)}")
    acc = info.get("validation_real_fi_accuracy")
    if acc is None:
        return
    n_named, unknown = info["n_real_rows_validation_classified"], info["validation_real_unknown_share"]
    print(f"recorded validation rows ({n_val}): FI accuracy {100 * acc:.1f} % of the {n_named} given a class at the "
          f"FD threshold, {100 * unknown:.1f} % called unknown (as inkdiag label labels them)")
    ref = scores["validation_fi_accuracy_at_threshold"]  # all validation rows, at the same threshold
    if n_named >= MIN_REAL_VALIDATION and acc <= ref - REAL_ACCURACY_GAP:
        print(f"inkdiag train: warning: the recorded validation rows given a class are labelled right "
              f"{100 * acc:.1f} % of the time, against {100 * ref:.1f} % of all validation rows at the same "
              "threshold: their labels, or the profile, disagree with the simulated classes (docs/classes.md); "
              "check the labels, and the calibration, before using this model", file=sys.stderr)


def content_sha256(path) -> str:
    """sha256 of a file's bytes (as ``sha256sum`` gives it), or of a directory's (a rosbag2 bag's) files: a tag
    that it is a directory, then each file's path relative to it, size and bytes, in sorted order, symbolic links
    followed (each directory once); a hex string."""
    import hashlib
    import os
    from pathlib import Path

    root, h = Path(path), hashlib.sha256()
    if root.is_dir():
        h.update(b"inkdiag directory\0")  # not the hash of any one file's bytes
        files, seen = [], set()
        for here, dirs, names in os.walk(root, followlinks=True):
            if (real := os.path.realpath(here)) in seen:  # a link back up: its files are listed once
                dirs[:] = []
                continue
            seen.add(real)
            dirs.sort(key=lambda d: (os.path.islink(os.path.join(here, d)), d))  # real ones first: one order only
            files += [Path(here, n) for n in names if Path(here, n).is_file()]
        files.sort(key=lambda f: f.relative_to(root).as_posix())
    else:
        files = [root]
    for f in files:
        if root.is_dir():
            h.update(f"{f.relative_to(root).as_posix()}\0{f.stat().st_size}\0".encode())
        with open(f, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
    return h.hexdigest()
