"""``inkdiag baseline``: a head's per-nozzle healthy baselines from a recording (.npz or bag), the
same file record_baseline writes (BaselineRecorder), by each row's nozzle id; rows not labelled
healthy_nozzle left out; one-line errors, exit status 2."""

import os

import numpy as np
import pytest
from _bags import write_bag

from inkdiag_core import (BaselineRecorder, FaultClass, HeadProfile, NozzleBaselines, Recording, save_recording,
                          simulate_nozzles)
from inkdiag_ros.cli import main

N_NOZZLES, N_FRAMES = 6, 3


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    d = tmp_path_factory.mktemp("baseline")
    head = HeadProfile.default()
    head.save(d / "head.yaml")
    head.replace(channel={"r_r": None, "L_r": None, "B_act": None, "b": None}).save(d / "nominal.yaml")
    frames = [simulate_nozzles([FaultClass.HEALTHY_NOZZLE] * N_NOZZLES, seed=3, frame_seed=f).traces
              for f in range(N_FRAMES)]
    return d, head, frames


def test_baselines_of_a_recording_are_record_baselines_of_its_frames(work, tmp_path, capsys):
    d, head, frames = work
    x = np.concatenate(frames)
    ids = 100 + np.tile(np.arange(N_NOZZLES), N_FRAMES)
    labels = np.full(x.shape[0], "healthy_nozzle", dtype=object)
    labels[2] = "deeply_dried"  # nozzle 102's first frame: not used
    x[7, 9] = np.nan  # nozzle 101's second frame: invalid, not used
    save_recording(tmp_path / "c.npz", Recording.from_arrays(x, head.sample_rate_hz, nozzle=ids, label=labels))
    capsys.readouterr()
    assert main(["baseline", str(tmp_path / "c.npz"), "--profile", str(d / "head.yaml"), "--out",
                 str(tmp_path / "b.npz"), "--frames", "2", "--fm-frames", "1"]) == 0
    out = capsys.readouterr().out
    assert "inkdiag baseline: baselines of 6 nozzles (head 'default') from 12 of 18 rows (1 not labelled " \
           "healthy_nozzle)" in out, out
    got = NozzleBaselines.load(tmp_path / "b.npz")
    mask = os.umask(0o022)
    os.umask(mask)
    assert (tmp_path / "b.npz").stat().st_mode & 0o777 == 0o666 & ~mask  # readable as the CSVs beside it
    want = BaselineRecorder(n_frames=2, fm_frames=1, profile=head)
    for k, f in enumerate(frames):  # the same frames, one message each, as the node takes them
        f = f.copy()
        keep = np.ones(N_NOZZLES, bool)
        if k == 0:
            keep[2] = False
        if k == 1:
            f[1, 9] = np.nan
        want.add(100, f, keep=keep)
    want = want.baselines()
    np.testing.assert_array_equal(got.nozzle_ids, 100 + np.arange(N_NOZZLES))
    np.testing.assert_array_equal(got.kpis, want.kpis)
    np.testing.assert_allclose(got.fm, want.fm, rtol=1e-6)  # f_m fits in batches of other sizes
    np.testing.assert_array_equal(got.reference, want.reference)
    assert got.head_sha256 == head.sha256 and got.n_frames == 2


def test_a_bag_gives_the_same_baselines_as_its_npz(work, tmp_path):
    d, head, frames = work
    bag = write_bag(tmp_path / "bag", [(40, f) for f in frames])
    x = np.concatenate(frames)
    save_recording(tmp_path / "c.npz", Recording.from_arrays(x, head.sample_rate_hz,
                                                             nozzle=40 + np.tile(np.arange(N_NOZZLES), N_FRAMES)))
    for src, out in ((bag, "from_bag.npz"), (tmp_path / "c.npz", "from_npz.npz")):
        assert main(["baseline", str(src), "--profile", str(d / "head.yaml"), "--out", str(tmp_path / out),
                     "--frames", "3", "--fm-frames", "0"]) == 0
    a, b = NozzleBaselines.load(tmp_path / "from_bag.npz"), NozzleBaselines.load(tmp_path / "from_npz.npz")
    np.testing.assert_array_equal(a.nozzle_ids, 40 + np.arange(N_NOZZLES))
    np.testing.assert_array_equal(a.kpis, b.kpis)
    assert a.fm is None


def test_nozzles_short_of_frames_are_left_out_and_said(work, tmp_path, capsys):
    d, head, frames = work
    x = np.concatenate([frames[0], frames[1][:2]])  # nozzles 0, 1 twice, the others once
    x[5] = np.nan  # nozzle 5's one row unusable: a nozzle of the recording all the same
    x[3] *= 1e3  # nozzle 3's one row beyond the sensor's range (5x the ADC's): not used
    save_recording(tmp_path / "c.npz", Recording.from_arrays(
        x, head.sample_rate_hz, nozzle=np.r_[np.arange(N_NOZZLES), 0, 1]))
    capsys.readouterr()
    assert main(["baseline", str(tmp_path / "c.npz"), "--profile", str(d / "head.yaml"), "--out",
                 str(tmp_path / "b.npz"), "--frames", "2", "--fm-frames", "0"]) == 0
    out = capsys.readouterr().out
    assert "from 6 of 8 rows" in out and "4 nozzles with fewer than 2 usable rows left out" in out, out
    np.testing.assert_array_equal(NozzleBaselines.load(tmp_path / "b.npz").nozzle_ids, [0, 1])


def test_frames_given_twice_are_warned_about(work, tmp_path, capsys):
    """helper-107: a bag of 5 frames each written twice made baselines 'of 8 frames' from 5, without a word (label
    and estimate warned). A recording without frame_id or stamp (rows told apart by nozzle id alone) is not."""
    d, head, frames = work
    x = np.concatenate(frames + frames[:1])  # frame 0 given twice, as frame 0
    fid = np.r_[np.repeat(np.arange(N_FRAMES), N_NOZZLES), np.zeros(N_NOZZLES, int)]
    save_recording(tmp_path / "dup.npz", Recording.from_arrays(x, head.sample_rate_hz,
                                                               nozzle=np.tile(np.arange(N_NOZZLES), N_FRAMES + 1),
                                                               frame_id=fid))
    args = ["--profile", str(d / "head.yaml"), "--out", str(tmp_path / "b.npz"), "--frames", "4", "--fm-frames", "0"]
    capsys.readouterr()
    assert main(["baseline", str(tmp_path / "dup.npz"), *args]) == 0
    err = capsys.readouterr().err
    assert f"inkdiag baseline: warning: {N_NOZZLES} row(s) repeat the nozzle, frame_id and stamp of an earlier " \
           "row; each is counted as one of its nozzle's --frames" in err, err
    save_recording(tmp_path / "plain.npz", Recording.from_arrays(x, head.sample_rate_hz,
                                                                 nozzle=np.tile(np.arange(N_NOZZLES), N_FRAMES + 1)))
    assert main(["baseline", str(tmp_path / "plain.npz"), *args]) == 0
    assert "repeat" not in capsys.readouterr().err
    # a repeated row the label column leaves out counts toward no baseline: not said (helper-110)
    labels = np.full(x.shape[0], "healthy_nozzle", dtype=object)
    labels[-N_NOZZLES:] = "deeply_dried"
    save_recording(tmp_path / "lab.npz", Recording.from_arrays(x, head.sample_rate_hz, label=labels, frame_id=fid,
                                                               nozzle=np.tile(np.arange(N_NOZZLES), N_FRAMES + 1)))
    assert main(["baseline", str(tmp_path / "lab.npz"), *args[:-4], "--frames", "3", "--fm-frames", "0"]) == 0
    assert "repeat" not in capsys.readouterr().err


def test_a_nozzle_faulty_at_commissioning_is_left_out_and_said(work, tmp_path, capsys):
    d, head, _ = work
    classes = [FaultClass.HEALTHY_NOZZLE] * 12
    classes[4] = FaultClass.INTERMEDIATELY_DRIED
    x = np.concatenate([simulate_nozzles(classes, seed=5, frame_seed=f).traces for f in range(2)])
    save_recording(tmp_path / "c.npz", Recording.from_arrays(x, head.sample_rate_hz, nozzle=np.tile(np.arange(12), 2)))
    capsys.readouterr()
    assert main(["baseline", str(tmp_path / "c.npz"), "--profile", str(d / "head.yaml"), "--out",
                 str(tmp_path / "b.npz"), "--frames", "2", "--fm-frames", "0"]) == 0
    out, err = capsys.readouterr()
    assert "baselines of 11 nozzles" in out and "; 1 ringing unlike the others left out;" in out, out
    assert "nozzles with fewer than" not in out, out
    assert err.startswith("inkdiag baseline: warning: 1 nozzle(s) ring unlike the head's others") and " 4 (" in err, err
    np.testing.assert_array_equal(NozzleBaselines.load(tmp_path / "b.npz").nozzle_ids, np.delete(np.arange(12), 4))
    # a recording of nozzles that did not fire: said as such
    noise = np.random.default_rng(0).normal(0.0, 0.01, x.shape).astype(np.float32)
    save_recording(tmp_path / "n.npz", Recording.from_arrays(noise, head.sample_rate_hz, nozzle=np.tile(np.arange(12), 2)))
    assert main(["baseline", str(tmp_path / "n.npz"), "--profile", str(d / "head.yaml"), "--out",
                 str(tmp_path / "n_b.npz"), "--frames", "2", "--fm-frames", "0"]) == 2
    assert capsys.readouterr().err.strip().endswith(
        "(of 24 rows, 0 usable, 24 not ringing above their noise): are they healthy nozzles fired with the head's "
        "drive, in volts?")


@pytest.mark.parametrize(("argv", "match"), [
    (["--profile", "{d}/nominal.yaml"], "inkdiag calibrate"),
    (["--profile", "{d}/missing.yaml"], "no such head profile"),
    (["--profile", "{d}/head.yaml", "--frames", "2", "--fm-frames", "3"], "--fm-frames must be in 0..--frames"),
    (["--profile", "{d}/head.yaml", "--frames", "0"], "--frames must be in 1..1000"),
    (["--profile", "{d}/head.yaml", "--frames", "1000000000000"], "--frames must be in 1..1000"),
    (["--profile", "{d}/head.yaml", "--frames", "1", "--max-abs-v", "0"], "--max-abs-v must be a finite number > 0"),
    (["--profile", "{d}/head.yaml", "--frames", "1", "--max-abs-v", "inf"], "--max-abs-v must be a finite number > 0"),
    (["--profile", "{d}/head.yaml", "--frames", "2", "--fm-frames", "0", "--min-frames", "3"], "--min-frames must be in 1..--frames"),
    (["--profile", "{d}/head.yaml", "--fm-frames", "0"], "no nozzle has 8 usable healthy rows (of 6 rows, 6 usable): "
     "no nozzle id comes twice (a recording without a 'nozzle' column numbers its rows 0..n-1)"),
    (["--profile", "{d}/head20.yaml"], "Hz"),
])
def test_bad_input_is_one_line_and_exit_status_2(work, tmp_path, argv, match, capsys):
    d, head, frames = work
    if not (d / "once.npz").exists():
        save_recording(d / "once.npz", Recording.from_arrays(frames[0], head.sample_rate_hz))  # one frame a nozzle
        head.replace(name="h20", sample_rate_hz=20e6, n_samples=1024).save(d / "head20.yaml")
    capsys.readouterr()
    args = ["baseline", str(d / "once.npz"), *[a.format(d=d) for a in argv], "--out", str(tmp_path / "b.npz")]
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("inkdiag baseline: error: ") and match in err[0], err
    assert not (tmp_path / "b.npz").exists()


def test_fewer_frames_than_the_default_fm_frames(work, tmp_path):
    """--frames 1 alone (a one-frame recording): the f_m reading takes that frame, as record_baseline clamps."""
    d, head, frames = work
    save_recording(tmp_path / "c.npz", Recording.from_arrays(frames[0], head.sample_rate_hz))
    assert main(["baseline", str(tmp_path / "c.npz"), "--profile", str(d / "head.yaml"), "--out",
                 str(tmp_path / "b.npz"), "--frames", "1"]) == 0
    got = NozzleBaselines.load(tmp_path / "b.npz")
    assert len(got) == N_NOZZLES and np.isfinite(got.fm).all()


def test_help(capsys):
    with pytest.raises(SystemExit) as stop:
        main(["baseline", "--help"])
    out = capsys.readouterr().out
    assert stop.value.code == 0 and "--profile" in out and "--fm-frames" in out and "record_baseline" in out


def test_a_head_ringing_at_another_amplitude_than_its_profiles_is_warned_about(work, tmp_path, capsys):
    """The model reads the amplitude: a controller whose analog gain is not the profile's had its faults called
    unknown, and docs/controller.md said the gain need not be calibrated (helper-88). Its baselines say so."""
    d, head, _ = work
    n = 48
    frames = [simulate_nozzles([FaultClass.HEALTHY_NOZZLE] * n, seed=5, frame_seed=f).traces for f in range(3)]
    said = {}
    for gain in (1.0, 0.85):
        save_recording(tmp_path / "c.npz", Recording.from_arrays(
            gain * np.concatenate(frames), head.sample_rate_hz, nozzle=np.tile(np.arange(n), 3)))
        capsys.readouterr()
        assert main(["baseline", str(tmp_path / "c.npz"), "--profile", str(d / "head.yaml"), "--out",
                     str(tmp_path / f"b{gain}.npz"), "--frames", "3"]) == 0
        said[gain] = capsys.readouterr().err
    assert said[1.0] == ""
    assert said[0.85].startswith("inkdiag baseline: warning: the baselines' 48 healthy nozzles ring at 0.8") and \
        "x the amplitude of the healthy nozzles of head 'default': a sensor gain other than the profile's?" in said[0.85]
    assert NozzleBaselines.load(tmp_path / "b0.85.npz").gain_mismatch(head) in said[0.85]  # written all the same
