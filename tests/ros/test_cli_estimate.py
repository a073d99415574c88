"""``inkdiag estimate`` end to end, as a user runs it, on files.

Most tests call the command in this process (:func:`run_inproc`: ``inkdiag_ros.cli.main`` with stdout and
stderr captured, argparse's SystemExit taken as the status), which checks the same status, output and files
without a second or two of imports per call. These stay a subprocess (:func:`run_cli`), where the process
itself is the point:

- ``test_estimate_writes_the_columns_and_reports_bad_rows``: the command as a user runs it, ``python -m
  inkdiag_ros.cli`` (its ``__main__``, the real exit status);
- ``test_a_full_disk_names_the_output``: a write error is one line and status 2 from the real process
  (nothing more at interpreter exit, such as an unflushed file's "Exception ignored");
- ``test_a_reader_that_stops_early_is_one_line_and_status_1``: a closed pipe and buffered stdout flushed at
  exit, which only a real process has.
"""

import contextlib
import csv
import io
import os
import stat
import subprocess
import sys
import tempfile
import warnings
from typing import NamedTuple

import numpy as np
import pytest

from inkdiag_core import HeadProfile, Recording, fm_to_viscosity, save_recording
from inkdiag_core.estimation import calibrate_vp_cal

COLUMNS = ["row", "nozzle", "fm", "fm_std", "d_mu", "viscosity", "frame_id", "stamp", "fm_trend", "fm_rate",
           "eta_deeply_dried_s", "method", "reason"]


def run_cli(*args, timeout=300):
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1")
    return subprocess.run([sys.executable, "-m", "inkdiag_ros.cli", "estimate", *map(str, args)],
                          capture_output=True, text=True, timeout=timeout, env=env)


class Ran(NamedTuple):
    """What the tests read of ``subprocess.run``'s result."""

    returncode: int
    stdout: str
    stderr: str


#: A fresh interpreter's warning filters (no -W, no PYTHONWARNINGS): as the subprocess of run_cli has them,
#: not pytest's (filterwarnings in pytest.ini, "always" for deprecations).
_PYTHON_FILTERS = (("default", DeprecationWarning, "__main__"), ("ignore", DeprecationWarning, ""),
                   ("ignore", PendingDeprecationWarning, ""), ("ignore", ImportWarning, ""),
                   ("ignore", ResourceWarning, ""))


def _warning_to_stderr(message, category, filename, lineno, file=None, line=None):
    sys.stderr.write(warnings.formatwarning(message, category, filename, lineno, line))  # the redirected one


@contextlib.contextmanager
def _nothing_below_sys_streams():
    """Fail if anything writes to file descriptors 1 or 2 directly (C code, a stream bound before the redirect):
    run_inproc would not see it, where run_cli's subprocess would."""
    saved = [os.dup(1), os.dup(2)]
    with tempfile.TemporaryFile() as raw:
        try:
            for fd in (1, 2):
                os.dup2(raw.fileno(), fd)
            yield
        finally:
            for fd, keep in zip((1, 2), saved):
                os.dup2(keep, fd)
                os.close(keep)
        raw.seek(0)
        escaped = raw.read().decode(errors="replace")
    assert not escaped, f"output that escaped run_inproc's redirect of sys.stdout/sys.stderr: {escaped!r}"


def run_inproc(*args):
    """:func:`run_cli` in this process: ``inkdiag estimate ARGS`` through ``inkdiag_ros.cli.main``, its
    sys.stdout and sys.stderr captured, a SystemExit (argparse's usage errors) taken as the exit status, Python's
    own warning filters and warnings printed on the captured stderr, as the subprocess would. (Compared with
    run_cli's results call by call when this was written: the same status, stdout and stderr.)"""
    from inkdiag_ros.cli import main

    out, err = io.StringIO(), io.StringIO()
    with _nothing_below_sys_streams(), warnings.catch_warnings():
        warnings.resetwarnings()
        for action, category, module in reversed(_PYTHON_FILTERS):  # each inserted at the front
            warnings.filterwarnings(action, category=category, module=module)
        warnings.showwarning = _warning_to_stderr
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                status = main(["estimate", *map(str, args)])
            except SystemExit as exc:  # as the interpreter takes it
                status = exc.code
                if isinstance(status, str):
                    print(status, file=sys.stderr)
                    status = 1
            sys.stdout.flush()
            sys.stderr.flush()
    return Ran(0 if status is None else int(status), _as_read_from_a_pipe(out), _as_read_from_a_pipe(err))


def _as_read_from_a_pipe(stream: io.StringIO) -> str:
    """As subprocess.run(text=True) reads a pipe: universal newlines."""
    return stream.getvalue().replace("\r\n", "\n").replace("\r", "\n")


def read_csv(path):
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    return rows[0], [dict(zip(rows[0], r)) for r in rows[1:]]


@pytest.fixture(scope="module")
def head(tmp_path_factory):
    """A 20 MHz x 1024 head of other geometry, ink and drive, its profile file with its vp_cal constants
    (a small fit, so the command does not fit them again), and a recording of it: 2 frames x 8 nozzles,
    healthy and dried, with a non-finite row, a flat row and a clipped row."""
    d = tmp_path_factory.mktemp("estimate")
    p = HeadProfile.default().replace(
        name="foreign20", sample_rate_hz=20e6, n_samples=1024,
        channel={"rho": 1100.0, "mu": 6e-3, "r_n": 11e-6, "L_n": 45e-6, "V_ch": 8e-12, "c": 1300.0, "L_r": 250e-6},
        drive={"amplitude_v": 25.0, "rise_s": 1e-6, "dwell_s": 2e-6, "fall_s": 1e-6})
    p = p.replace(calibration={"vp_cal": calibrate_vp_cal(p, seeds=(11, 12), n_per_class=20)})
    p.save(d / "head.yaml")
    r = p.simulate({"healthy_nozzle": 4, "slightly_dried": 4, "intermediately_dried": 4, "deeply_dried": 4}, seed=9)
    t = r.traces.copy()
    t[1, 5] = np.inf
    t[2] = 0.3
    t[3, 100:120] = t[3].max()
    labels = [getattr(c, "value", c) for c in r.labels]
    save_recording(d / "rec.npz", Recording.from_arrays(
        t, p.sample_rate_hz, nozzle=np.tile(np.arange(8), 2), frame_id=np.repeat([5, 6], 8),
        stamp=np.repeat([1.0, 1.5], 8), label=labels))
    return d, p, r


def test_estimate_writes_the_columns_and_reports_bad_rows(head):
    d, p, r = head
    out = d / "fm.csv"
    res = run_cli(d / "rec.npz", "--profile", d / "head.yaml", "--out", out)
    assert res.returncode == 0, res.stderr
    assert "13 of 16 rows estimated" in res.stdout
    assert "finite stamp" not in res.stderr  # every row stamped
    header, rows = read_csv(out)
    assert header == COLUMNS and b"\r" not in out.read_bytes()  # "\n" line ends, as inkdiag label writes
    assert [int(x["row"]) for x in rows] == list(range(16))
    assert [x["reason"] for x in rows[:4]] == ["", "non_finite", "flat", "clipped"]
    for x in rows[1:4]:
        assert x["fm"] == x["fm_std"] == x["d_mu"] == x["viscosity"] == ""
    good = [x for x in rows if not x["reason"]]
    for x in good:
        assert all(np.isfinite(float(x[k])) for k in ("fm", "fm_std", "d_mu", "viscosity", "fm_trend"))
        assert x["method"] == "vp_cal"
    # the second frame's nozzles have a rate (two updates), the first frame's not
    assert all(x["fm_rate"] == "" for x in good if x["frame_id"] == "5")
    assert all(x["fm_rate"] != "" for x in good if x["frame_id"] == "6" and rows[int(x["nozzle"])]["reason"] == "")
    dried = [x for x in good if int(x["row"]) >= 4]
    fm_true = r.fm[[int(x["row"]) for x in dried]]
    d_mu_true = fm_to_viscosity(p.channel_params(), fm_true)[0]
    d_mu = np.array([float(x["d_mu"]) for x in dried])
    assert np.median(np.abs(d_mu - d_mu_true) / d_mu_true) <= 0.10
    np.testing.assert_allclose([float(x["viscosity"]) - float(x["d_mu"]) for x in dried], p.channel["mu"],
                               rtol=1e-9)


def test_traces_in_other_units_that_do_not_ring_above_the_noise_are_said(head, tmp_path):
    """Traces a thousand times too small were estimated as any other, with no word (helper-103)."""
    d, p, r = head
    z = dict(np.load(d / "rec.npz"))
    np.savez(tmp_path / "kv.npz", **dict(z, traces=(z["traces"] * 1e-3).astype(np.float32)))
    res = run_inproc(tmp_path / "kv.npz", "--profile", d / "head.yaml", "--out", tmp_path / "fm.csv")
    assert res.returncode == 0, res.stderr
    assert "0 of 16 rows estimated" in res.stdout and "below_noise 13" in res.stdout, res.stdout  # the summary line
    assert ("inkdiag estimate: warning: 13 of 16 rows do not ring above the profile's sensor noise" in res.stderr
            and "traces in other units (kilovolts?), or nozzles that did not fire or hold no ink?" in res.stderr), res.stderr
    res = run_inproc(d / "rec.npz", "--profile", d / "head.yaml", "--out", tmp_path / "fm.csv")
    assert res.returncode == 0 and "below_noise" not in res.stdout + res.stderr and "warning" not in res.stderr


def test_estimate_selects_rows(head):
    d, p, r = head
    out = d / "sel.csv"
    res = run_inproc(d / "rec.npz", "--profile", d / "head.yaml", "--out", out, "--rows", "0:2,9", "--method", "vp")
    assert res.returncode == 0, res.stderr
    _, rows = read_csv(out)
    assert [int(x["row"]) for x in rows] == [0, 1, 9] and {x["method"] for x in rows} == {"vp"}
    assert b"\r" not in out.read_bytes()
    res = run_inproc(d / "rec.npz", "--profile", d / "head.yaml", "--out", out, "--rows", "dried")
    assert res.returncode == 0, res.stderr
    assert [int(x["row"]) for x in read_csv(out)[1]] == list(range(4, 16))
    # a label column from `inkdiag label` (it writes 'invalid' and 'unknown'), CSV to standard output
    z = dict(np.load(d / "rec.npz"))
    z["label"] = z["label"].astype(object)
    z["label"][[0, 5]] = ["invalid", "unknown"]
    np.savez(d / "relabelled.npz", **dict(z, label=z["label"].astype(str)))
    res = run_inproc(d / "relabelled.npz", "--profile", d / "head.yaml", "--out", "-", "--rows", "dried")
    assert res.returncode == 0, res.stderr
    lines = res.stdout.splitlines()
    assert lines[0] == ",".join(COLUMNS) and [int(x.split(",")[0]) for x in lines[1:]] == [4, *range(6, 16)]
    assert "11 of 11 rows estimated" in res.stderr and " -> " not in res.stderr
    # a selection of no row: the CSV is its header, and a warning says so (helper-125: silent)
    for rows in ("0:0", "fully_blocked"):
        res = run_inproc(d / "rec.npz", "--profile", d / "head.yaml", "--out", out, "--rows", rows)
        assert res.returncode == 0 and len(read_csv(out)[1]) == 0, res.stderr
        assert f"inkdiag estimate: warning: --rows {rows} selects no row of " in res.stderr, res.stderr


def test_estimate_bad_input_is_one_line_and_status_2(head, tmp_path):
    d, p, r = head
    out = tmp_path / "fm.csv"
    # a recording of another sampling than the profile's
    save_recording(tmp_path / "10mhz.npz", Recording.from_arrays(
        HeadProfile.default().simulate({"deeply_dried": 2}, seed=1).traces, 10e6))
    # a nominal profile
    nominal = p.replace(channel={"r_r": None, "L_r": None, "B_act": None, "b": None},
                        sensor={"gain_v_per_m3s": None}, calibration={"vp_cal": None})
    nominal.save(tmp_path / "nominal.yaml")
    cases = [
        ((tmp_path / "10mhz.npz", "--profile", d / "head.yaml"),
         "is sampled at 10000000 Hz x 512 samples; profile 'foreign20' is 20000000 Hz x "),
        ((d / "rec.npz", "--profile", tmp_path / "nominal.yaml"), "run inkdiag calibrate first"),
        ((tmp_path / "missing.npz", "--profile", d / "head.yaml"), "no such recording"),
        ((d / "rec.npz", "--profile", tmp_path / "missing.yaml"), "no such head profile"),
        ((d / "rec.npz", "--profile", d / "head.yaml", "--rows", "40"), "no such row"),
        ((d / "rec.npz", "--profile", d / "head.yaml", "--rows", "5:2"), "START 5 is after STOP 2"),
        # a value starting with '-': its own error, not argparse's "expected one argument" (helper-125)
        ((d / "rec.npz", "--profile", d / "head.yaml", "--rows", "-3:-1"), "--rows -3:-1: outside 0:16"),
        ((d / "rec.npz", "--profile", d / "head.yaml", "--rows", "-:5"), "expected indices and ranges"),  # helper-129
        ((d / "rec.npz", "--profile", d / "head.yaml", "--rows", "\u0663"), "expected indices and ranges"),  # Arabic 3
        ((d / "rec.npz", "--profile", d / "head.yaml", "--rows", "\u0661:\u0663"), "expected indices and ranges"),
        ((d / "rec.npz", "--profile", d / "head.yaml", "--max-abs-v", "nan"), "--max-abs-v must be a finite number > 0 V"),
        ((d / "rec.npz", "--profile", d / "head.yaml", "--max-abs-v", "inf"), "--max-abs-v must be a finite number > 0 V"),
    ]
    for args, message in cases:
        res = run_inproc(*args, "--out", out)
        assert res.returncode == 2, (args, res.stderr)
        assert res.stderr.startswith("inkdiag estimate: error: ") and message in res.stderr, res.stderr
        assert len(res.stderr.strip().splitlines()) == 1 and not out.exists()


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs /dev/full (a device that is always full)")
def test_a_full_disk_names_the_output(head):
    d, p, r = head
    res = run_cli(d / "rec.npz", "--profile", d / "head.yaml", "--rows", "0:2", "--out", "/dev/full")
    assert res.returncode == 2 and len(res.stderr.strip().splitlines()) == 1, res.stderr
    assert res.stderr.strip() == "inkdiag estimate: error: --out /dev/full: No space left on device", res.stderr


def test_a_reader_that_stops_early_is_one_line_and_status_1(head):
    """`inkdiag estimate ... --out - | head`: the CSV's reader is gone before it is written; one line, status 1,
    no traceback (buffered stdout too: the summary flushed at exit must not fail either)."""
    d, p, r = head
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1")
    env.pop("PYTHONUNBUFFERED", None)
    for out in ("-", str(d / "piped.csv")):
        proc = subprocess.Popen([sys.executable, "-m", "inkdiag_ros.cli", "estimate", str(d / "rec.npz"), "--profile",
                                 str(d / "head.yaml"), "--out", out], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                text=True, env=env)
        proc.stdout.close()  # the reader is gone before the command writes anything
        err = proc.stderr.read()
        assert proc.wait(timeout=300) == 1, err
        assert err.strip().splitlines()[-1] == "inkdiag estimate: error: its output's reader is gone (Broken pipe)", err
        assert "Traceback" not in err and "Exception ignored" not in err, err


def test_out_dash_is_for_the_csv_verbs_only(head, tmp_path, monkeypatch):
    from inkdiag_ros.cli import main

    d, p, r = head
    monkeypatch.chdir(tmp_path)
    assert main(["baseline", str(d / "rec.npz"), "--profile", str(d / "head.yaml"), "--out", "-"]) == 2
    assert main(["train", "--profile", str(d / "head.yaml"), "--out", "-"]) == 2
    assert not (tmp_path / "-").exists()


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="needs /proc (a directory that takes no new file)")
def test_an_out_whose_directory_takes_no_file_is_refused_before_the_work(head, capsys):
    """Run as root (access() says yes) or on a read-only mount, train and calibrate found it out after their
    work, and said the raw OSError of a temporary file's name (helper-81's QA)."""
    from inkdiag_ros.cli import main

    d, p, r = head
    for argv in (["estimate", str(d / "rec.npz"), "--profile", str(d / "head.yaml"), "--out", "/proc/fm.csv"],
                 ["train", "--profile", str(d / "head.yaml"), "--out", "/proc/new/dir/m.joblib"]):  # train mkdirs
        capsys.readouterr()
        assert main(argv) == 2
        err = capsys.readouterr().err.strip().splitlines()
        probed = f"inkdiag {argv[0]}: error: --out {argv[-1]}: its directory /proc takes no new file ("
        denied = f"inkdiag {argv[0]}: error: /proc: not writable, for --out"  # not root: access() says so first
        assert len(err) == 1 and (err[0].startswith(probed) or (os.geteuid() != 0 and err[0] == denied)), err
    for fd_dir in ("/dev/fd", "/proc/self/fd"):  # a pipe, as a shell's >(gzip > x.gz) gives: not probed, written
        r, w = os.pipe()
        try:
            assert main(["estimate", str(d / "rec.npz"), "--profile", str(d / "head.yaml"), "--rows", "0",
                         "--out", f"{fd_dir}/{w}"]) == 0, capsys.readouterr().err
            os.close(w)
            with os.fdopen(r, "rb") as f:
                assert f.read().decode().splitlines()[0].startswith("row,nozzle,fm,")
        finally:
            for fd in (r, w):
                try:
                    os.close(fd)
                except OSError:
                    pass


def test_train_and_baseline_refuse_an_out_that_is_a_fifo_rather_than_rename_over_it(head, tmp_path, capsys):
    """train and baseline write beside --out and rename into place: over a FIFO or a device (/dev/null as root)
    that replaced the node for every user of it (helper-84's QA: /dev/full became a regular file)."""
    from inkdiag_core.persistence import save_model
    from inkdiag_ros.cli import main

    d, p, r = head
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    for argv in (["train", "--profile", str(d / "head.yaml"), "--n-per-class", "8", "--quiet", "--out", str(fifo)],
                 ["baseline", str(d / "rec.npz"), "--profile", str(d / "head.yaml"), "--out", str(fifo)]):
        capsys.readouterr()
        assert main(argv) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert err == [f"inkdiag {argv[0]}: error: --out {fifo} is not a regular file (a device, pipe or socket): "
                       "a file written there is renamed into place, which would replace it; give a file's name"], err
        assert stat.S_ISFIFO(os.lstat(fifo).st_mode)
    assert not (tmp_path / "fifo.manifest.json").exists()
    with pytest.raises(OSError, match="is not a regular file"):  # the core refuses it too
        save_model({"a": 1}, fifo)
    (tmp_path / "to_fifo").symlink_to(fifo)  # a link to one (as /dev/stdout is): refused too (helper-86's review)
    with pytest.raises(OSError, match="to_fifo is not a regular file"):
        save_model({"a": 1}, tmp_path / "to_fifo")
    (tmp_path / "dangling").symlink_to(tmp_path / "nothing")  # a link to nothing, or to a file: replaced, as before
    save_model({"a": 1}, tmp_path / "dangling")
    assert (tmp_path / "dangling").is_file() and not (tmp_path / "dangling").is_symlink()
    (tmp_path / "m.joblib.manifest.json").mkdir()  # a directory where the manifest goes: refused before the model
    with pytest.raises(OSError, match="is a directory"):
        save_model({"a": 1}, tmp_path / "m.joblib")
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode) and not (tmp_path / "m.joblib").exists()


def test_an_oserror_is_said_as_outs_only_when_it_is_about_the_output(tmp_path, monkeypatch):
    from inkdiag_ros.cli import _is_out_or_beside

    monkeypatch.chdir(tmp_path)
    (tmp_path / "head.yaml").write_text("x")
    assert _is_out_or_beside(str(tmp_path / "m.joblib.q11g331j.tmp"), "m.joblib")  # relative --out, absolute temp
    assert _is_out_or_beside("m.joblib", str(tmp_path / "m.joblib"))
    assert _is_out_or_beside(str(tmp_path / "new"), "new/dir/m.joblib")  # a directory train was to make
    assert not _is_out_or_beside(str(tmp_path / "head.yaml"), "head")  # an input named like it
    assert not _is_out_or_beside(str(tmp_path), "m.joblib") and not _is_out_or_beside(None, "m.joblib")


def test_estimate_says_how_many_rows_were_relative_to_their_nozzles_baseline(head, tmp_path):
    """--baselines of nozzles 0..3 on a recording of nozzles 0..7: the summary counts the rows taken relative
    to their nozzle's healthy f_m and the rows without one, and says where the ids come from."""
    from inkdiag_core import BaselineRecorder

    d, p, r = head
    rec = BaselineRecorder(n_frames=1, fm_frames=1, profile=p)
    rec.add(0, p.simulate({"healthy_nozzle": 4}, seed=21).traces)
    rec.baselines().save(tmp_path / "b.npz")
    res = run_inproc(d / "rec.npz", "--profile", d / "head.yaml", "--baselines", tmp_path / "b.npz",
                  "--out", tmp_path / "fm.csv")
    assert res.returncode == 0, res.stderr
    assert "13 of 16 rows estimated" in res.stdout
    # rows 0..3 and 8..11 are nozzles 0..3; rows 1, 2, 3 are not estimated (non-finite, flat, clipped)
    assert "; 5 relative to their nozzle's healthy f_m, 8 without one (no baseline for that nozzle id" in res.stdout


def test_rows_without_a_finite_stamp_are_said_to_have_no_trend(head, tmp_path):
    """A recording whose stamps are partly NaN: those rows are estimated without a trend, and the run says so."""
    d, p, r = head
    rec = np.load(d / "rec.npz", allow_pickle=True)
    stamp = np.repeat([1.0, 1.5], 8)
    stamp[[8, 9]] = np.nan
    save_recording(tmp_path / "rec.npz", Recording.from_arrays(rec["traces"], p.sample_rate_hz, nozzle=rec["nozzle"],
                                                               frame_id=rec["frame_id"], stamp=stamp))
    res = run_inproc(tmp_path / "rec.npz", "--profile", d / "head.yaml", "--out", tmp_path / "fm.csv")
    assert res.returncode == 0, res.stderr
    assert "note: 2 of the 13 estimated rows have no finite stamp: fm_trend, fm_rate and eta_deeply_dried_s are " \
           "empty for them" in res.stderr, res.stderr
    _, rows = read_csv(tmp_path / "fm.csv")
    assert rows[8]["fm"] != "" and rows[8]["fm_trend"] == "" and rows[10]["fm_trend"] != ""


def test_a_nozzle_given_twice_at_one_stamp_is_estimated_twice_but_measured_once(head, tmp_path):
    """A nozzle column gone wrong (all rows nozzle 0) or a row given twice (--rows 12,12): every row is
    estimated, the run warns, and a nozzle's trend takes one measurement per stamp (as fe's tracker): its
    repeats have no trend, and no rate comes out where no time passed."""
    d, p, r = head
    rec = np.load(d / "rec.npz", allow_pickle=True)
    save_recording(tmp_path / "dup.npz", Recording.from_arrays(
        rec["traces"], p.sample_rate_hz, nozzle=np.zeros(16, int), frame_id=rec["frame_id"], stamp=rec["stamp"]))
    res = run_inproc(tmp_path / "dup.npz", "--profile", d / "head.yaml", "--out", tmp_path / "fm.csv")
    assert res.returncode == 0, res.stderr
    assert "warning: 14 row(s) repeat the nozzle, frame_id and stamp of an earlier row; each is estimated" \
        in res.stderr
    _, rows = read_csv(tmp_path / "fm.csv")
    trended = [x for x in rows if x["fm_trend"] != ""]
    assert all(x["fm"] != "" for x in rows if not x["reason"])
    assert [x["frame_id"] for x in trended] == ["5", "6"]  # the first estimated row of each frame
    assert trended[0]["fm_rate"] == "" and trended[1]["fm_rate"] != ""  # a rate over the 0.5 s between frames
    res = run_inproc(d / "rec.npz", "--profile", d / "head.yaml", "--rows", "12,12,12", "--out", tmp_path / "fm3.csv")
    assert res.returncode == 0 and "warning: 2 row(s) repeat" in res.stderr and "2 row(s) estimated but not " \
        "folded into their nozzle's trend" in res.stderr, res.stderr
    _, rows = read_csv(tmp_path / "fm3.csv")
    fm = [float(x["fm"]) for x in rows]  # one trace three times (the batch's sums may differ in the last bits)
    # frames told apart by their stamps alone (no frame_id column): no repeat, every row trended
    save_recording(tmp_path / "st.npz", Recording.from_arrays(rec["traces"], p.sample_rate_hz, nozzle=rec["nozzle"],
                                                              stamp=rec["stamp"]))
    res2 = run_inproc(tmp_path / "st.npz", "--profile", d / "head.yaml", "--out", tmp_path / "st.csv")
    assert res2.returncode == 0 and "repeat" not in res2.stderr and "not folded" not in res2.stderr, res2.stderr
    assert fm == pytest.approx([fm[0]] * 3, rel=1e-12) and [x["fm_trend"] != "" for x in rows] == [True, False, False]
    assert all(x["fm_rate"] == "" for x in rows)


def test_a_recording_in_millivolts_is_told_about_units(head, tmp_path):
    """As inkdiag label does: every row out_of_range is a recording in other units, said on stderr."""
    d, p, r = head
    save_recording(tmp_path / "mv.npz", Recording.from_arrays(r.traces[:8] * 1e3, p.sample_rate_hz))
    res = run_inproc(tmp_path / "mv.npz", "--profile", d / "head.yaml", "--out", tmp_path / "fm.csv")
    assert res.returncode == 0, res.stderr
    assert "warning: 8 of 8 rows have a sample beyond" in res.stderr and "in volts (not millivolts" in res.stderr
    res = run_inproc(d / "rec.npz", "--profile", d / "head.yaml", "--out", tmp_path / "ok.csv")
    assert res.returncode == 0 and "in volts" not in res.stderr


def test_a_recording_of_mostly_nan_rows_is_warned_about(head, tmp_path):
    d, p, r = head
    x = np.array(r.traces, dtype=np.float32)  # 16 rows
    x[:10, 3] = np.inf
    save_recording(tmp_path / "inf.npz", Recording.from_arrays(x, p.sample_rate_hz))
    res = run_inproc(tmp_path / "inf.npz", "--profile", d / "head.yaml", "--out", tmp_path / "fm.csv")
    assert res.returncode == 0, res.stderr
    assert "warning: 10 of 16 rows are invalid (10 non_finite); most are NaN or infinite" in res.stderr
    x = np.array(r.traces, dtype=np.float32)  # as many rows of two reasons: neither is 'most'
    x[:4, 3], x[4:8] = np.nan, 0.25
    save_recording(tmp_path / "tie.npz", Recording.from_arrays(x, p.sample_rate_hz))
    res = run_inproc(tmp_path / "tie.npz", "--profile", d / "head.yaml", "--out", tmp_path / "fm.csv")
    assert "warning: 8 of 16 rows are invalid (4 flat, 4 non_finite): is this the recording" in res.stderr, res.stderr
    # fewer than 8 invalid rows are a few channels, not a head (helper-110: 1 flat row of 2 picked was warned about)
    res = run_inproc(tmp_path / "tie.npz", "--profile", d / "head.yaml", "--out", tmp_path / "fm.csv", "--rows", "3,8")
    assert res.returncode == 0 and "rows are invalid" not in res.stderr, res.stderr
    res = run_inproc(d / "rec.npz", "--profile", d / "head.yaml", "--out", tmp_path / "ok.csv")
    assert res.returncode == 0 and "rows are invalid" not in res.stderr


def _labels_csv(path, rec_npz, classes, *, nozzle_offset=0):
    """A labels CSV as ``inkdiag label`` writes it (row, nozzle, frame_id, class, ...) for ``rec_npz``, with
    ``classes`` per row; ``nozzle_offset``: its nozzle column off by that much (the labels of another recording)."""
    z = np.load(rec_npz)
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["row", "nozzle", "frame_id", "class", "confidence", "reason", "baseline"])
        for i, c in enumerate(classes):
            w.writerow([i, int(z["nozzle"][i]) + nozzle_offset, int(z["frame_id"][i]), c, "0.9", "", 0])
    return path


def test_estimate_takes_the_rows_a_labels_csv_calls_dried(head, tmp_path):
    d, p, r = head
    # the model's labels, not the recording's: rows 5 and 9 called healthy, row 0 (healthy) called deeply dried,
    # row 1 invalid
    classes = ["deeply_dried", "invalid", "healthy_nozzle", "healthy_nozzle"] + ["slightly_dried"] * 12
    classes[5] = classes[9] = "healthy_nozzle"
    labels = _labels_csv(tmp_path / "labels.csv", d / "rec.npz", classes)
    res = run_inproc(d / "rec.npz", "--profile", d / "head.yaml", "--labels", labels, "--out", tmp_path / "a.csv")
    assert res.returncode == 0, res.stderr
    picked = [0, 4, 6, 7, 8, *range(10, 16)]
    _, rows = read_csv(tmp_path / "a.csv")
    assert [int(x["row"]) for x in rows] == picked
    res = run_inproc(d / "rec.npz", "--profile", d / "head.yaml", "--rows", ",".join(map(str, picked)),
                  "--out", tmp_path / "b.csv")
    assert res.returncode == 0, res.stderr
    assert read_csv(tmp_path / "b.csv")[1] == rows  # the same rows, the same numbers
    res = run_inproc(d / "rec.npz", "--profile", d / "head.yaml", "--labels", labels, "--rows", "deeply_dried",
                  "--out", "-")
    assert res.returncode == 0, res.stderr
    assert [int(x.split(",")[0]) for x in res.stdout.splitlines()[1:]] == [0]
    assert "warning" not in res.stderr
    # label's CSV of another recording that agrees on the rows it names: estimated, with train's warning
    part = _labels_csv(tmp_path / "part.csv", d / "rec.npz", classes[:10])
    res = run_inproc(d / "rec.npz", "--profile", d / "head.yaml", "--labels", part, "--out", tmp_path / "c.csv")
    assert res.returncode == 0, res.stderr
    assert ("inkdiag estimate: warning: " + str(part) + " looks like `inkdiag label`'s CSV, which names every row of "
            "the recording it labelled, but it names 10 of the 16 rows of") in res.stderr, res.stderr


def test_estimate_refuses_labels_of_another_recording_or_with_row_indices(head, tmp_path):
    d, p, r = head
    out = tmp_path / "fm.csv"
    other = _labels_csv(tmp_path / "other.csv", d / "rec.npz", ["deeply_dried"] * 16, nozzle_offset=1)
    good = _labels_csv(tmp_path / "good.csv", d / "rec.npz", ["deeply_dried"] * 16)
    cases = [
        (("--labels", other), "other.csv:2: row 0 is nozzle 0 in "),
        (("--labels", good, "--rows", "0:4"), "--rows 0:4 with --labels: --labels picks rows by their class"),
        (("--labels", tmp_path / "missing.csv"), "no such labels file"),
    ]
    for args, message in cases:
        res = run_inproc(d / "rec.npz", "--profile", d / "head.yaml", *args, "--out", out)
        assert res.returncode == 2, (args, res.stderr)
        assert res.stderr.startswith("inkdiag estimate: error: ") and message in res.stderr, res.stderr
        assert len(res.stderr.strip().splitlines()) == 1 and not out.exists()


def test_estimate_takes_a_labels_csv_of_a_bag(head, tmp_path):
    from _bags import write_bag

    d, p, r = head
    z = np.load(d / "rec.npz")
    bag = write_bag(tmp_path / "bag", [(0, z["traces"][:8]), (0, z["traces"][8:])], fs=p.sample_rate_hz)
    same = tmp_path / "same.npz"  # the bag's frames (ids 0, 1 at 100 s, 101 s) as an .npz
    save_recording(same, Recording.from_arrays(z["traces"], p.sample_rate_hz, nozzle=z["nozzle"],
                                               frame_id=np.repeat([0, 1], 8), stamp=np.repeat([100.0, 101.0], 8)))
    classes = ["healthy_nozzle"] * 4 + ["intermediately_dried"] * 12
    classes[12] = "unknown"
    labels = _labels_csv(tmp_path / "labels.csv", same, classes)
    res = run_inproc(bag, "--profile", d / "head.yaml", "--labels", labels, "--out", tmp_path / "bag.csv")
    assert res.returncode == 0, res.stderr
    _, rows = read_csv(tmp_path / "bag.csv")
    assert [int(x["row"]) for x in rows] == [*range(4, 12), *range(13, 16)]
    res = run_inproc(same, "--profile", d / "head.yaml", "--labels", labels, "--out", tmp_path / "npz.csv")
    assert res.returncode == 0, res.stderr
    assert read_csv(tmp_path / "npz.csv")[1] == rows  # the bag's rows estimated as the .npz's
    # a bag has no label column; labels of another recording; a CSV naming rows the bag lacks
    other = _labels_csv(tmp_path / "other.csv", same, classes, nozzle_offset=2)
    with open(tmp_path / "long.csv", "w") as f:
        f.write(open(labels).read() + "16,0,2,deeply_dried,0.9,,0\n17,0,2,deeply_dried,0.9,,0\n")
    for args, message in [(("--rows", "dried"), "a bag has no label column; give the rows' classes with --labels"),
                          (("--labels", other), "other.csv:2: row 0 is nozzle 0 in the bag, the CSV says 2"),
                          (("--labels", tmp_path / "long.csv"), "long.csv: row 16 (and 1 more) is past the end (the bag has 16 rows")]:
        res = run_inproc(bag, "--profile", d / "head.yaml", *args, "--out", tmp_path / "x.csv")
        assert res.returncode == 2, (args, res.stderr)
        last = res.stderr.strip().splitlines()[-1]  # after the bag's own report, where it was read
        assert last.startswith("inkdiag estimate: error: ") and message in last, res.stderr


def test_a_nozzle_the_labels_call_recovered_starts_a_new_trend_as_in_fe(tmp_path, monkeypatch, capsys):
    """fe ends a nozzle's trend when its range's drying lists leave it out 3 frames in a row (it recovered); estimate
    with class --rows does the same (the rows not of the class), in an .npz and in a bag; with row indices it does
    not. Left out 2 frames in a row, the trend goes on."""
    from inkdiag_core import simulate_nozzles
    from _bags import write_bag

    dried = {0: [2], 1: [2], 2: [], 3: [], 4: [2], 5: [], 6: [], 7: [], 8: [2]}  # purged (5-7), dries again
    frames = []
    for f, ids in dried.items():
        classes = np.array(["healthy_nozzle"] * 4, dtype=object)
        classes[ids] = "deeply_dried"
        frames.append((classes, simulate_nozzles(classes, seed=4, frame_seed=f).traces))
    x = np.concatenate([t for _, t in frames])
    label = np.concatenate([c for c, _ in frames]).astype(str)
    save_recording(tmp_path / "r.npz", Recording.from_arrays(
        x, 10e6, nozzle=np.tile(np.arange(4), 9), frame_id=np.repeat(np.arange(9), 4),
        stamp=np.repeat(100.0 + np.arange(9), 4), label=label))
    bag = write_bag(tmp_path / "bag", [(0, t) for _, t in frames])  # frame k at stamp 100 + k
    with open(tmp_path / "l.csv", "w") as f:
        f.write("row,class\n" + "".join(f"{i},{c}\n" for i, c in enumerate(label)))
    profile = tmp_path / "default.yaml"
    HeadProfile.default().save(profile)

    def nozzle_2(*args):
        res = run_inproc(*args, "--profile", profile, "--out", "-")
        assert res.returncode == 0, res.stderr
        rows = [dict(zip(COLUMNS, line.split(","))) for line in res.stdout.splitlines()[1:]]
        return [(int(r["row"]), r["fm"] == r["fm_trend"], r["fm_rate"] != "") for r in rows if r["nozzle"] == "2"]

    restarted = [(2, True, False), (6, False, True), (18, False, True), (34, True, False)]  # frame 8: a new trend
    assert nozzle_2(tmp_path / "r.npz", "--rows", "dried") == restarted
    assert nozzle_2(tmp_path / "r.npz", "--labels", tmp_path / "l.csv") == restarted
    assert nozzle_2(bag, "--labels", tmp_path / "l.csv") == restarted
    assert nozzle_2(tmp_path / "r.npz", "--rows", "2,6,18,34")[3] == (34, False, True)  # indices: one trend
    # a bag read one frame a chunk (helper-89): the frame without a dried row is a chunk with none selected
    from inkdiag_ros.cli import main
    from inkdiag_ros.verbs import estimate

    monkeypatch.setattr(estimate, "_BAG_CHUNK_ROWS", 4)
    capsys.readouterr()
    assert main(["estimate", str(bag), "--profile", str(profile), "--labels", str(tmp_path / "l.csv"), "--out",
                 str(tmp_path / "chunked.csv")]) == 0
    _, rows = read_csv(tmp_path / "chunked.csv")
    assert [(int(r["row"]), r["fm"] == r["fm_trend"], r["fm_rate"] != "") for r in rows if r["nozzle"] == "2"] \
        == restarted


def test_a_frame_that_lists_the_nozzle_is_no_miss_though_not_estimated_as_in_fe(tmp_path):
    """helper-122: misses at frames 2 and 4 around frame 3, which labels nozzle 2 dried but whose trace no drying
    nozzle gives (misfit), ended its trend at frame 5: two frames in a row, not three. As fe, estimate counts
    frame 3 as news that the nozzle still dries."""
    from inkdiag_core import simulate_nozzles

    lists = [[2], [2], [], [2], [], [], [2]]
    t = np.arange(512) / 10e6
    xs, labels = [], []
    for f, ids in enumerate(lists):
        classes = np.array(["healthy_nozzle"] * 4, dtype=object)
        classes[ids] = "deeply_dried"
        x = simulate_nozzles(classes, seed=4, frame_seed=f).traces
        if f == 3:
            x[2] = 0.3 * np.sin(2 * np.pi * 300e3 * t)
        xs.append(x)
        labels.append(classes.astype(str))
    save_recording(tmp_path / "r.npz", Recording.from_arrays(
        np.concatenate(xs), 10e6, nozzle=np.tile(np.arange(4), len(lists)),
        frame_id=np.repeat(np.arange(len(lists)), 4), stamp=np.repeat(100.0 + np.arange(len(lists)), 4),
        label=np.concatenate(labels)))
    HeadProfile.default().save(tmp_path / "default.yaml")
    res = run_inproc(tmp_path / "r.npz", "--profile", tmp_path / "default.yaml", "--rows", "dried", "--out", "-")
    assert res.returncode == 0, res.stderr
    rows = [dict(zip(COLUMNS, line.split(","))) for line in res.stdout.splitlines()[1:]]
    last = [r for r in rows if r["nozzle"] == "2"][-1]
    assert last["row"] == "26" and last["fm_rate"] != "", rows  # frame 6 goes on with the trend of frames 0-1
    assert [r["reason"] for r in rows if r["row"] == "14"] == ["misfit"]


def test_rows_labelled_a_fault_other_than_drying_are_noted_and_class_names_are_read_without_case(head, tmp_path):
    """helper-109's QA: a recording of bubbles and partial blocks estimated without --rows gave them viscosities
    with no word; its label column says they are no drying nozzles, so a note says so. ``--rows Deeply_Dried``
    was refused (a labels CSV's class names are read without case)."""
    d, p, r = head
    labels = np.array([getattr(c, "value", c) for c in r.labels], dtype=object)
    labels[[4, 12]] = "small_air_bubble"
    labels[5] = "partially_blocked"
    save_recording(tmp_path / "mixed.npz", Recording.from_arrays(r.traces, p.sample_rate_hz, label=labels))
    res = run_inproc(tmp_path / "mixed.npz", "--profile", d / "head.yaml", "--out", tmp_path / "fm.csv")
    assert res.returncode == 0, res.stderr
    assert "note: 3 estimated rows are labelled a fault other than drying in the recording's label column " \
           "(partially_blocked 1, small_air_bubble 2): their f_m is no ink viscosity; --rows dried" in res.stderr
    res = run_inproc(tmp_path / "mixed.npz", "--profile", d / "head.yaml", "--out", tmp_path / "ix.csv",
                     "--rows", "0:8")  # rows picked by index are of any class too (helper-110)
    assert "note: 2 estimated rows are labelled a fault other than drying in the recording's label column " \
           "(partially_blocked 1, small_air_bubble 1)" in res.stderr, res.stderr
    res = run_inproc(tmp_path / "mixed.npz", "--profile", d / "head.yaml", "--out", tmp_path / "dd.csv",
                     "--rows", "Deeply_Dried")
    assert res.returncode == 0 and "other than drying" not in res.stderr, res.stderr
    assert [x["row"] for x in read_csv(tmp_path / "dd.csv")[1]] == [str(i) for i in np.flatnonzero(
        labels == "deeply_dried")]


def test_another_heads_profile_and_stamps_in_nanoseconds_are_warned_about(head, tmp_path):
    """helper-109's QA: a profile of another nozzle and ink with the same sampling read healthy nozzles at 0.4x
    the ink's viscosity, and stamps in nanoseconds gave a 300-year eta, both without a word."""
    d, p, r = head
    healthy = p.simulate({"healthy_nozzle": 12}, seed=4)
    save_recording(tmp_path / "h.npz", Recording.from_arrays(healthy.traces, p.sample_rate_hz))
    other = p.replace(name="other", channel={"mu": 2 * p.channel["mu"]})  # an ink twice as thick
    other = other.replace(calibration={"vp_cal": calibrate_vp_cal(other, seeds=(11, 12), n_per_class=20)})
    other.save(tmp_path / "other.yaml")
    res = run_inproc(tmp_path / "h.npz", "--profile", tmp_path / "other.yaml", "--out", tmp_path / "o.csv")
    assert res.returncode == 0, res.stderr
    assert "warning: 12 of 12 estimated rows come out thinner than the profile's ink" in res.stderr, res.stderr
    res = run_inproc(tmp_path / "h.npz", "--profile", d / "head.yaml", "--out", tmp_path / "h.csv")
    assert res.returncode == 0 and "thinner" not in res.stderr, res.stderr
    x = r.traces[8:16]  # one nozzle's dried frames, stamps in nanoseconds
    save_recording(tmp_path / "ns.npz", Recording.from_arrays(x, p.sample_rate_hz, nozzle=np.zeros(8, int),
                                                              frame_id=np.arange(8), stamp=1.7e18 + 1e8 * np.arange(8)))
    res = run_inproc(tmp_path / "ns.npz", "--profile", d / "head.yaml", "--out", tmp_path / "ns.csv")
    assert res.returncode == 0 and "warning: stamps up to 1.7e+18 s" in res.stderr, res.stderr
    assert "in nanoseconds or milliseconds?" in res.stderr
    res = run_inproc(d / "rec.npz", "--profile", d / "head.yaml", "--out", tmp_path / "ok.csv")
    assert res.returncode == 0 and "nanoseconds" not in res.stderr, res.stderr
