"""The offline verbs stream a bag (issue 15, part 2): ``inkdiag label`` yields a chunk's rows before
the next chunk is read, its memory does not grow with the bag's length (tracemalloc peak, in a
subprocess), a bad frame is reported on stderr with its message index and reason and costs no
other frame; ``inkdiag estimate`` on a bag gives the rows the same recording as an .npz gives;
``calibrate``'s bounded sample of a bag; ``train --data`` refuses a bag without ``--labels`` before reading
it, and trains on one with them."""

import csv
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from _bags import NS, write_bag
from inkdiag_core import FaultClass, HeadProfile


@pytest.fixture(scope="module")
def sim():
    return HeadProfile.default().simulate({c: 6 for c in FaultClass}, seed=5)


def _cli(*args):
    """``inkdiag ARGS`` in this process (the offline verbs start no ROS): the console script's code without its
    2-3 s of imports per call; (exit status, stdout, stderr) as a ``subprocess.CompletedProcess``."""
    import contextlib
    import io

    from inkdiag_ros.cli import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            rc = main([*map(str, args)])
        except SystemExit as exc:  # argparse's usage errors
            rc = exc.code if isinstance(exc.code, int) else 1
    return subprocess.CompletedProcess(args, rc, out.getvalue(), err.getvalue())


def test_label_stream_yields_the_first_rows_before_the_bag_is_read(tmp_path, sim, fdi_model):
    from inkdiag_core import FrameLabeller, load_detector
    from inkdiag_ros.bags import BagFrames, iter_bag_chunks
    from inkdiag_ros.verbs.label import label_stream

    x = sim.traces[:16].astype(np.float32)
    bag = write_bag(tmp_path / "bag", [(16 * k, x) for k in range(30)])
    det = load_detector(fdi_model)
    labeller = FrameLabeller(det, sample_rate_hz=det.sample_rate_hz_, n_samples=x.shape[1])
    stats = BagFrames()
    rows = label_stream(labeller, iter_bag_chunks(bag, stats=stats, max_rows=32))
    first = next(rows)
    assert stats.n_messages <= 3  # two frames a chunk (and the one that closed it), not 30
    assert first[:3] == (0, 0, 0)
    rest = list(rows)
    assert stats.n_messages == 30 and len(rest) == 30 * 16 - 1
    assert [r[0] for r in rest] == list(range(1, 480)) and [r[2] for r in rest[15::16]] == list(range(1, 30))


_PEAK = textwrap.dedent("""
    import sys, tracemalloc, resource
    import sklearn.ensemble, rosbags.rosbag2, rclpy.serialization, msg_defs, inkdiag_core  # imports out of the peak
    from inkdiag_ros import cli
    from inkdiag_ros.verbs import label
    label.BATCH_ROWS = 1024  # chunks of 1024 rows (16 frames of 64) against bags of 1,280 and 12,800 rows
    tracemalloc.start()
    rc = cli.main(["label", sys.argv[1], "--model", sys.argv[2], "--out", sys.argv[3]])
    print(rc, tracemalloc.get_traced_memory()[1], resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)
""")


def test_label_memory_does_not_grow_with_the_bag(tmp_path, sim, fdi_model):
    x = sim.traces[:64].astype(np.float32)  # 128 kB a frame
    peaks = {}
    for n_frames in (20, 200):
        bag = write_bag(tmp_path / f"b{n_frames}", [(0, x)] * n_frames)
        out = tmp_path / f"l{n_frames}.csv"
        r = subprocess.run([sys.executable, "-c", _PEAK, str(bag), str(fdi_model), str(out)],
                           capture_output=True, text=True, timeout=120)
        assert r.returncode == 0, r.stderr[-2000:]
        rc, peak, rss_kb = map(int, r.stdout.splitlines()[-1].split())  # after label's own summary line
        assert rc == 0
        with open(out, newline="") as f:
            assert sum(1 for _ in f) == 64 * n_frames + 1
        peaks[n_frames] = peak
        print(f"{n_frames} frames: tracemalloc peak {peak / 1e6:.1f} MB, max RSS {rss_kb / 1e3:.0f} MB")
    grown = peaks[200] - peaks[20]
    # the larger bag holds 180 x 128 kB = 23.6 MB more traces; streamed, the peak is about one chunk either
    # way (measured: +3.6 MB, the reader's and the chunks' sizes; reading alone: 9.0 MB at 200 and 600 frames);
    # the whole bag in memory grew by twice the difference
    assert grown < 0.25 * 180 * x.nbytes, (peaks, grown)


def test_label_reports_each_bad_frame_on_stderr_and_labels_the_others(tmp_path, sim, fdi_model):
    x = sim.traces[:8].astype(np.float32)
    bag = write_bag(tmp_path / "bag", [(8 * k, x) for k in range(5)], bad_frame=2)
    out = tmp_path / "l.csv"
    r = _cli("label", bag, "--model", fdi_model, "--out", out)
    assert r.returncode == 0, r.stderr
    assert f"{bag}: message 2 skipped: " in r.stderr and "data_offset" in r.stderr
    assert f"4 of 5 messages on {NS}/traces decoded" in r.stderr
    with open(out, newline="") as f:
        rows = list(csv.DictReader(f))
    assert sorted({int(r["frame_id"]) for r in rows}) == [0, 1, 3, 4] and len(rows) == 32
    assert list(rows[0])[:6] == ["row", "nozzle", "frame_id", "class", "confidence", "reason"]


def test_a_bad_first_frame_costs_only_itself(tmp_path, sim, fdi_model):
    """A bag whose first frame has another length than the head's: label, estimate and baseline skip it and
    read the others (the head's sampling, not the first frame's, decides; helper-69's QA)."""
    x = sim.traces[:8].astype(np.float32)
    bag = write_bag(tmp_path / "bag", [(0, x[:, :500])] + [(8 * k, x) for k in range(1, 5)])
    out = tmp_path / "l.csv"
    r = _cli("label", bag, "--model", fdi_model, "--out", out)
    assert r.returncode == 0, r.stderr
    assert "sampled at 10000000 Hz x 500, not at the model's head 'default', 10000000 Hz x 512" in r.stderr
    with open(out, newline="") as f:
        assert sorted({int(r["frame_id"]) for r in csv.DictReader(f)}) == [1, 2, 3, 4]
    default = HeadProfile.default()
    prof = tmp_path / "head.yaml"
    default.save(prof)
    r = _cli("estimate", bag, "--profile", prof, "--out", tmp_path / "fm.csv")
    assert r.returncode == 0, r.stderr
    assert "sampled at 10000000 Hz x 500, not at profile 'default', 10000000 Hz x 512" in r.stderr
    r = _cli("train", "--profile", prof, "--data", bag, "--labels", out, "--n-per-class", 60, "--out",
             tmp_path / "m.joblib", "--quiet")  # label's CSV numbers the rows of the frames it read: train reads those
    assert r.returncode == 0 and f"32 of the 32 rows of {bag} named" in r.stdout, r.stderr
    same = write_bag(tmp_path / "same", [(0, x[:, :500])] + [(0, x)] * 4)  # the same nozzles in every frame
    r = _cli("baseline", same, "--profile", prof, "--frames", 4, "--out", tmp_path / "b.npz")
    assert r.returncode == 0 and "message 0 (frame 0) skipped" in r.stderr, r.stderr
    bad = write_bag(tmp_path / "bad", [(0, x[:, :500])] * 2)  # no frame of the head's sampling: one line, exit 2
    r = _cli("label", bad, "--model", fdi_model, "--out", tmp_path / "l2.csv")  # (was a line per frame, then a
    assert r.returncode == 2 and r.stderr.strip().splitlines() == [  # summary repeating them: helper-84's QA)
        f"inkdiag label: error: {bad}: all its 2 trace frames on {NS}/traces are sampled at 10000000 Hz x 500, not "
        "at the model's head 'default', 10000000 Hz x 512: a recording of another head?"], r.stderr


def test_a_bag_of_another_heads_sampling_is_refused_without_reading_it_all(tmp_path, sim):
    """The first MAX_OFF_SAMPLING frames all of another sampling: refused there (another head's bag, not bad frames);
    a rate that is the head's rounded to float32 (as a trace header carries it) is the head's."""
    from inkdiag_core.head_profile import same_sample_rate
    from inkdiag_core.recording import RecordingError
    from inkdiag_ros.bags import MAX_OFF_SAMPLING, BagFrames, iter_bag_chunks

    x = sim.traces[:2].astype(np.float32)
    bag = write_bag(tmp_path / "bag", [(0, x[:, :500])] * MAX_OFF_SAMPLING + [(0, x)] * 3)
    stats = BagFrames()
    with pytest.raises(RecordingError, match=f"its first {MAX_OFF_SAMPLING} trace frames on .* are sampled at "
                                             r"10000000 Hz x 500, not at the head 10000000 Hz x 512: a recording"):
        list(iter_bag_chunks(bag, stats=stats, sampling=(10e6, 512, "the head")))
    assert stats.n_messages == MAX_OFF_SAMPLING and stats.n_skipped == 0  # not read to the end; one error says it
    ok = write_bag(tmp_path / "ok", [(0, x[:, :500])] * (MAX_OFF_SAMPLING - 1) + [(0, x)] * 3)
    stats = BagFrames()
    chunks = list(iter_bag_chunks(ok, stats=stats, sampling=(10e6, 512, "the head")))
    assert sum(c.n_rows for _, c in chunks) == 6
    assert stats.n_skipped == MAX_OFF_SAMPLING - 1 and stats.skipped[0][0] == 0  # reported once a frame is kept
    rate = 4166666.67  # not a float32: its header carries 4166666.75
    assert same_sample_rate(float(np.float32(rate)), rate) and not same_sample_rate(4166667.5, rate)
    assert same_sample_rate(10e6 * (1 + 1e-10), 10e6) and not same_sample_rate(10e6 * (1 + 1e-6), 10e6)


def test_frames_of_another_sampling_held_back_are_reported_when_the_bag_breaks_off(monkeypatch):
    """Frames of another sampling before the first kept one are held back (one error says it if none is kept); a
    bag that breaks off meanwhile reports them as skipped, with its own error (helper-86's review: they were lost)."""
    import types

    import inkdiag_ros.bags as bags
    from inkdiag_core.recording import RecordingError

    def frames(bag_dir, topic=None, stats=None):
        stats.topic = "/t"
        for i, n in enumerate((500, 500, 256)):
            stats.n_messages += 1
            yield types.SimpleNamespace(sample_rate_hz=10e6, n_samples=n, frame_id=i, nozzle_ids=np.arange(2),
                                        traces=np.zeros((2, n), np.float32), n_nozzles=2, stamp=0.0)
        if broken:
            raise RecordingError("bag: truncated or corrupt bag: 3 messages readable, then: boom")

    monkeypatch.setattr(bags, "iter_bag_frames", frames)
    for broken in (True, False):
        seen = []
        stats = bags.BagFrames(report=lambda *a: seen.append(a))
        with pytest.raises(RecordingError) as exc:
            list(bags.iter_bag_chunks("bag", stats=stats, sampling=(10e6, 512, "the head")))
        if broken:
            assert str(exc.value).endswith("then: boom") and [a[0] for a in seen] == [0, 1, 2]
            assert stats.n_skipped == 3
        else:
            assert str(exc.value) == ("bag: all its 3 trace frames on /t are of 2 other samplings (the first sampled "
                                      "at 10000000 Hz x 500, not at the head 10000000 Hz x 512): a recording of "
                                      "another head?") and seen == []


def test_estimate_on_a_bag_streams_the_rows_the_npz_gives(tmp_path, capsys):
    from inkdiag_core import save_recording
    from inkdiag_ros import cli
    from inkdiag_ros.bags import load_recording

    prof = HeadProfile.default()
    prof.save(tmp_path / "head.yaml")
    r = prof.simulate({"healthy_nozzle": 6, "intermediately_dried": 6}, seed=3)
    x = r.traces.astype(np.float32)
    bag = write_bag(tmp_path / "bag", [(0, x[k::3]) for k in range(3)])
    save_recording(tmp_path / "same.npz", load_recording(bag))

    def estimate(src, rows, out):  # in-process, as the command runs
        status = cli.main(["estimate", str(src), "--profile", str(tmp_path / "head.yaml"), "--rows", rows,
                           "--out", str(tmp_path / out)])
        return status, capsys.readouterr().err

    outs = {}
    for name, src in (("bag", bag), ("npz", tmp_path / "same.npz")):
        status, err = estimate(src, "1:11", f"{name}.csv")
        assert status == 0, err
        with open(tmp_path / f"{name}.csv", newline="") as f:
            outs[name] = list(csv.reader(f))
    assert outs["bag"] == outs["npz"] and len(outs["bag"]) == 11
    status, err = estimate(bag, "5:40", "x.csv")
    assert status == 2 and "error: --rows 5:40: outside 0:12 (the bag has 12 rows" in err.splitlines()[-1]
    status, err = estimate(bag, "3,20,5:40", "x.csv")  # the first part past the end, as an .npz's error says it
    assert status == 2 and "error: --rows 20: no such row (the bag has 12 rows" in err.splitlines()[-1]
    status, err = estimate(bag, "-3:-1", "x.csv")  # no index from the end, as in an .npz
    assert status == 2 and "error: --rows -3:-1: outside 0:N, a row of the bag" in err.splitlines()[-1]
    for odd in ("-:5", "3:-"):  # a sign without digits: the spec's error, not int()'s (helper-129)
        status, err = estimate(bag, odd, "x.csv")
        assert status == 2 and "expected indices and ranges" in err.splitlines()[-1], err
    status, err = estimate(bag, "dried", "x.csv")
    assert status == 2 and "a bag has no label column" in err


def test_estimate_on_a_bag_folds_a_frame_out_of_time_order_into_no_trend(tmp_path, capsys):
    """A bag is estimated in its own order: a frame stamped before one already trended (or at its stamp) is
    estimated, its trend columns empty, and stderr says so, as fe's tracker does; so do repeated rows."""
    from inkdiag_ros import cli

    prof = HeadProfile.default()
    prof.save(tmp_path / "head.yaml")
    x = prof.simulate({"intermediately_dried": 4}, seed=3).traces.astype(np.float32)
    bag = write_bag(tmp_path / "bag", [(0, x)] * 4, stamps=[100, 102, 101, 102])  # whole s (the header's field)
    assert cli.main(["estimate", str(bag), "--profile", str(tmp_path / "head.yaml"), "--out",
                     str(tmp_path / "fm.csv")]) == 0
    err = capsys.readouterr().err
    assert "note: 8 row(s) estimated but not folded into their nozzle's trend" in err and "out of time order" in err
    assert "repeat" not in err  # frame ids tell the frames apart
    with open(tmp_path / "fm.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [r["fm_trend"] != "" for r in rows] == [True] * 8 + [False] * 8 and all(r["fm"] for r in rows)


def test_bag_sample_is_bounded_uniform_and_screened():
    from inkdiag_core import Recording
    from inkdiag_ros.verbs.calibrate import bag_sample

    prof = HeadProfile.default()
    n_s = prof.n_samples
    rng = np.random.default_rng(0)
    chunks = []
    for k in range(40):  # 40 chunks of 100 rows; row value = its index; every 10th row flat (screened out)
        t = (np.arange(100 * k, 100 * k + 100)[:, None] * 1e-4 + 1e-5 * rng.standard_normal((100, n_s)))
        t[::10] = 0.0
        chunks.append((100 * k, Recording.from_arrays(t.astype(np.float32), prof.sample_rate_hz)))
    traces, n_read, n_screened = bag_sample(iter(chunks), prof, max_rows=500, seed=1)
    assert traces.shape == (500, n_s) and n_read == 4000 and n_screened == 400
    idx = np.round(traces.mean(axis=1) / 1e-4).astype(int)
    assert np.all(idx % 10 != 0) and np.all(np.diff(idx) > 0)  # usable rows only, in stream order, no repeats
    assert 0.35 < (idx < 2000).mean() < 0.65  # early and late rows alike (uniform)


def test_train_refuses_a_bag_as_data_before_reading_it(tmp_path):
    bag = write_bag(tmp_path / "bag", [])
    HeadProfile.default().save(tmp_path / "head.yaml")
    r = _cli("train", "--profile", tmp_path / "head.yaml", "--out", tmp_path / "m.joblib", "--data", bag, "--quiet")
    assert r.returncode == 2 and "has no per-row labels" in r.stderr, r.stderr


def test_train_on_a_bag_with_the_labels_csv_that_label_wrote_and_a_user_corrected(tmp_path, sim, fdi_model):
    import json

    HeadProfile.default().save(tmp_path / "head.yaml")
    x = sim.traces.astype(np.float32)  # 72 rows, 6 of each class, as 3 frames of 24
    bag = write_bag(tmp_path / "bag", [(24 * k, x[24 * k:24 * k + 24]) for k in range(3)])
    r = _cli("label", bag, "--model", fdi_model, "--out", tmp_path / "labels.csv")
    assert r.returncode == 0, r.stderr
    with open(tmp_path / "labels.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    truth = np.asarray(sim.label_values() if callable(sim.label_values) else sim.label_values)
    for row in rows:  # the user's check: the true class of every row but the first ten
        row["class"] = truth[int(row["row"])] if int(row["row"]) >= 10 else "unknown"
    with open(tmp_path / "checked.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    r = _cli("train", "--profile", tmp_path / "head.yaml", "--out", tmp_path / "m.joblib", "--data", bag,
             "--labels", tmp_path / "checked.csv", "--n-per-class", 40, "--unknown-rate", 0, "--quiet")
    assert r.returncode == 0, r.stderr
    assert f"72 of the 72 rows of {bag} named, 62 with a class" in r.stdout and "warning" not in r.stderr
    assert "recorded rows: 62 used (" in r.stdout and "held out for validation" in r.stdout
    assert "0 screened out" in r.stdout and "recorded validation rows (" in r.stdout
    assert "the validation rows are simulated" not in r.stdout  # recorded rows validate too
    info = json.loads((tmp_path / "m.joblib.manifest.json").read_text())["config"]
    assert info["n_real_rows"] == 62 and info["labels_file"] == str(tmp_path / "checked.csv")
    import hashlib

    from inkdiag_ros.verbs.train import content_sha256
    assert info["labels_sha256"] == hashlib.sha256((tmp_path / "checked.csv").read_bytes()).hexdigest()
    assert info["data_file"] == str(bag) and info["data_sha256"] == content_sha256(bag)
    import shutil  # a bag's content: a byte more in any of its files changes it

    copy = shutil.copytree(bag, tmp_path / "copy")
    assert content_sha256(copy) == info["data_sha256"]
    with open(copy / "metadata.yaml", "a") as f:
        f.write("\n")
    assert content_sha256(copy) != info["data_sha256"]
    # what training read: each bag row (in label's numbering) with its own true class
    from inkdiag_core import labels_from_csv
    from inkdiag_ros.bags import read_bag_recording

    got, _ = labels_from_csv(read_bag_recording(bag), tmp_path / "checked.csv")
    assert list(got.label[10:]) == list(truth[10:]) and set(got.label[:10]) == {"unknown"}
    np.testing.assert_array_equal(got.traces, x)
    # --baseline with --data: refused before the recording is read
    r = _cli("train", "--profile", tmp_path / "head.yaml", "--out", tmp_path / "m3.joblib", "--data", bag,
             "--labels", tmp_path / "checked.csv", "--baseline", "--quiet")
    assert r.returncode == 2 and "--baseline with --data" in r.stderr and "named" not in r.stdout
    # label's CSV cut short (the labels of another, shorter recording?): trained on, with a warning
    with open(tmp_path / "short.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows[:30])
    r = _cli("train", "--profile", tmp_path / "head.yaml", "--out", tmp_path / "s.joblib", "--data", bag,
             "--labels", tmp_path / "short.csv", "--n-per-class", 40, "--unknown-rate", 0, "--quiet")
    assert r.returncode == 0 and "names 30 of the 72 rows" in r.stderr and "another recording?" in r.stderr
    # label's header alone: it names no row, said as such (before the bag is read)
    (tmp_path / "header.csv").write_text(",".join(rows[0]) + "\n")
    r = _cli("train", "--profile", tmp_path / "head.yaml", "--out", tmp_path / "h.joblib", "--data", bag,
             "--labels", tmp_path / "header.csv", "--quiet")
    assert r.returncode == 2 and r.stderr.strip().splitlines() == [
        f"inkdiag train: error: {tmp_path / 'header.csv'}: a header and no labelled line: it names no row"], r.stderr
    # an --out whose manifest would be written over the labels: refused before any work
    (tmp_path / "m4.joblib.manifest.json").write_bytes((tmp_path / "short.csv").read_bytes())
    r = _cli("train", "--profile", tmp_path / "head.yaml", "--out", tmp_path / "m4.joblib", "--data", bag,
             "--labels", tmp_path / "m4.joblib.manifest.json", "--quiet")
    assert r.returncode == 2 and "which is also the --labels input" in r.stderr
    assert (tmp_path / "m4.joblib.manifest.json").read_bytes() == (tmp_path / "short.csv").read_bytes()
    # the labels of another recording (its nozzles differ) are refused, naming the line
    rows[3]["nozzle"] = "999"
    with open(tmp_path / "other.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    r = _cli("train", "--profile", tmp_path / "head.yaml", "--out", tmp_path / "m2.joblib", "--data", bag,
             "--labels", tmp_path / "other.csv", "--quiet")
    assert r.returncode == 2 and "other.csv:5: row 3 is nozzle 3" in r.stderr and "another recording" in r.stderr
    assert not (tmp_path / "m2.joblib").exists()


def test_calibrate_on_a_bag_fits_a_bounded_sample_of_its_healthy_rows(tmp_path, capsys, monkeypatch):
    import json

    from inkdiag_core.head_profile import NOMINAL_CHANNEL_KEYS
    from inkdiag_ros import cli
    from inkdiag_ros.verbs import calibrate

    true = HeadProfile.default()
    x = true.simulate({"healthy_nozzle": 60}, seed=4).traces.astype(np.float32)
    x[7] = 0.25  # flat: screened out
    bag = write_bag(tmp_path / "bag", [(10 * k, x[10 * k:10 * k + 10]) for k in range(6)])
    doc = true.to_dict()
    doc.pop("sensor")
    doc["channel"] = {k: doc["channel"][k] for k in NOMINAL_CHANNEL_KEYS}
    HeadProfile.from_dict(doc).save(tmp_path / "nominal.yaml")
    monkeypatch.setattr(calibrate, "MAX_BAG_ROWS", 40)
    status = cli.main(["calibrate", str(bag), "--nominal", str(tmp_path / "nominal.yaml"),
                       "--out", str(tmp_path / "head.yaml"), "--no-vp-cal"])
    out, err = capsys.readouterr()
    assert status == 0, err
    assert "(40 traces, 0 dropped; 1 of the bag's 60 rows screened out; a uniform sample of 40 of its 59 usable rows)" in out
    assert f"6 of 6 messages on {NS}/traces decoded" in err
    assert json.loads((tmp_path / "head.fit.json").read_text())["n_traces"] == 40
    assert abs(HeadProfile.load(tmp_path / "head.yaml").healthy_mode()[0] / true.healthy_mode()[0] - 1) < 0.01


def test_content_sha256_follows_linked_directories_once_and_tells_a_directory_from_a_file(tmp_path):
    """helper-110: a bag's linked directory was not hashed, and an empty directory hashed as an empty file."""
    import hashlib
    import os

    from inkdiag_ros.verbs.train import content_sha256

    (tmp_path / "bag").mkdir()
    (tmp_path / "out").mkdir()
    (tmp_path / "bag" / "metadata.yaml").write_text("m")
    (tmp_path / "out" / "x.mcap").write_bytes(b"abc")
    os.symlink(tmp_path / "out", tmp_path / "bag" / "link")
    os.symlink(tmp_path / "bag", tmp_path / "bag" / "loop")  # a link back up: listed once, no endless walk
    before = content_sha256(tmp_path / "bag")
    (tmp_path / "out" / "x.mcap").write_bytes(b"abd")
    assert content_sha256(tmp_path / "bag") != before
    (tmp_path / "empty").mkdir()
    (tmp_path / "nothing").write_bytes(b"")
    assert content_sha256(tmp_path / "nothing") == hashlib.sha256(b"").hexdigest()  # a file: as sha256sum says
    assert content_sha256(tmp_path / "empty") != content_sha256(tmp_path / "nothing")
