"""``inkdiag train`` and ``inkdiag label`` end to end on a head that is not the default one
(20 MHz x 1024, another nozzle and ink): a model trained on its profile labels a simulated
recording of it; CSV columns exact; invalid rows with reasons while the rest of their frame is
labelled; per-nozzle baselines by the recording's nozzle ids; one-line errors, exit status 2."""

import csv
import json
import os
import re
import subprocess
import sys
from types import SimpleNamespace

import numpy as np
import pytest

from inkdiag_core import BaselineRecorder, FaultClass, HeadProfile, Recording, save_recording
from inkdiag_ros.cli import main

COLUMNS = ["row", "nozzle", "frame_id", "class", "confidence", "reason"]
CLASSES = {c.value for c in FaultClass} | {"invalid"}


def _head():
    return HeadProfile.default().replace(name="foreign20", sample_rate_hz=20e6, n_samples=1024,
                                         channel={"rho": 1100.0, "mu": 6e-3, "r_n": 11e-6, "L_n": 45e-6},
                                         drive={"amplitude_v": 25.0, "dwell_s": 2.0e-6})


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    d = tmp_path_factory.mktemp("cli")
    head = _head()
    head.save(d / "head.yaml")
    head.replace(channel={"r_r": None, "L_r": None, "B_act": None, "b": None}).save(d / "nominal.yaml")
    sim = head.simulate({c: 10 for c in FaultClass}, seed=77)
    x = sim.traces.copy()
    x[3, 5] = np.nan  # non_finite
    x[45, 9] = 1e30  # out_of_range
    n = len(x)
    save_recording(d / "rec.npz", Recording.from_arrays(x, 20e6, nozzle=np.arange(n) % 40,
                                                        frame_id=np.arange(n) // 40, label=sim.label_values()))
    d10 = HeadProfile.default().simulate({FaultClass.HEALTHY_NOZZLE: 4}, seed=0)
    save_recording(d / "rec10.npz", Recording.from_arrays(d10.traces, 10e6))
    return d, head, sim


@pytest.fixture(scope="module")
def trained(work):
    d, _, _ = work
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    out = subprocess.run([sys.executable, "-m", "inkdiag_ros.cli", "train", "--profile", str(d / "head.yaml"),
                          "--out", str(d / "head.joblib"), "--n-per-class", "40", "--seed", "1"],
                         capture_output=True, text=True, timeout=300, env=env)
    assert out.returncode == 0, out.stderr[-2000:]
    return d / "head.joblib", out


def _read(path):
    with open(path, newline="") as f:
        r = csv.reader(f)
        header = next(r)
        return header, [dict(zip(header, row)) for row in r]


def test_train_then_label_a_foreign_head_end_to_end(work, trained):
    d, head, sim = work
    model, out = trained
    mask = os.umask(0o022)  # what the files got is what a new file gets under the umask (not mkstemp's 0600)
    os.umask(mask)
    assert model.stat().st_mode & 0o777 == 0o666 & ~mask
    assert "validation" in out.stdout and "FI accuracy" in out.stdout
    assert "the validation rows are simulated on this profile" in out.stdout  # simulated rows only: said
    m = json.loads((d / "head.joblib.manifest.json").read_text())
    assert m["config"]["profile_sha256"] == head.sha256 and m["config"]["n_per_class"] == 40
    assert 0 < m["scores"]["validation_fi_accuracy"] <= 1
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    lab = subprocess.run([sys.executable, "-m", "inkdiag_ros.cli", "label", str(d / "rec.npz"), "--model",
                          str(model), "--out", str(d / "labels.csv")], capture_output=True, text=True,
                         timeout=300, env=env)
    assert lab.returncode == 0, lab.stderr[-2000:]
    header, rows = _read(d / "labels.csv")
    assert header[:6] == COLUMNS
    assert [int(r["row"]) for r in rows] == list(range(len(sim)))
    assert [int(r["frame_id"]) for r in rows] == (np.arange(len(sim)) // 40).tolist()
    assert [int(r["nozzle"]) for r in rows] == (np.arange(len(sim)) % 40).tolist()
    got = np.array([r["class"] for r in rows])
    assert set(got) <= CLASSES
    # the NaN row and the 1e30 row are invalid with their reason; their frames' other rows are labelled
    assert (rows[3]["class"], rows[3]["reason"], rows[3]["confidence"]) == ("invalid", "non_finite", "")
    assert (rows[45]["class"], rows[45]["reason"]) == ("invalid", "out_of_range")
    assert (got == "invalid").sum() == 2
    ok = got != "invalid"
    assert all(r["reason"] == "" and 0 < float(r["confidence"]) <= 1 for r in np.array(rows)[ok])
    acc = np.mean(got[ok] == sim.label_values()[ok])
    assert acc > 0.8, acc


def test_label_uses_each_rows_nozzle_baseline(work, tmp_path, capsys):
    d, head, _ = work
    model = tmp_path / "models" / "b.joblib"  # train creates its model's directory (docs/cli.md)
    assert main(["train", "--profile", str(d / "head.yaml"), "--out", str(model), "--baseline",
                 "--n-per-class", "24", "--quiet"]) == 0
    rec = BaselineRecorder(n_frames=2, profile=head)  # baselines of this head (its sha256 in the file)
    for k in range(2):
        rec.add(100, head.simulate({FaultClass.HEALTHY_NOZZLE: 5}, seed=50 + k).traces)
    rec.baselines().save(tmp_path / "base.npz")  # nozzles 100..104
    x = head.simulate({FaultClass.HEALTHY_NOZZLE: 6}, seed=60).traces
    save_recording(tmp_path / "r.npz", Recording.from_arrays(x, 20e6, nozzle=[104, 7, 100, 8, 102, 9]))
    assert main(["label", str(tmp_path / "r.npz"), "--model", str(model), "--baselines",
                 str(tmp_path / "base.npz"), "--out", str(tmp_path / "l.csv")]) == 0
    _, rows = _read(tmp_path / "l.csv")
    assert [r["baseline"] for r in rows] == ["1", "0", "1", "0", "1", "0"]
    # rows of nozzles without a baseline are said (a nozzle column that does not match is not silent)
    assert "3 against their nozzle's baseline, 3 without one" in capsys.readouterr().out


@pytest.mark.parametrize(("argv", "match"), [
    (["train", "--profile", "{d}/nominal.yaml", "--out", "{d}/x.joblib"], "inkdiag calibrate"),
    (["train", "--profile", "{d}/missing.yaml", "--out", "{d}/x.joblib"], "no such head profile"),
    (["train", "--profile", "{d}/head.yaml", "--out", "{d}/x.joblib", "--data", "{d}/rec10.npz"],
     "is sampled at 10000000 Hz"),
    (["train", "--profile", "{d}/head.yaml", "--out", "{d}/x.joblib", "--posterior-draws", "0"],
     "--posterior-draws must be >= 1"),
    (["train", "--profile", "{d}/head.yaml", "--out", "{d}/head.joblib.manifest.json"],  # was: written, exit 0
     "names a model's manifest, which train writes beside the model: give the model file's name (head.joblib)"),
    (["train", "--profile", "{d}/head.yaml", "--out", "{d}/x.joblib", "--unknown-rate", "1.5"],
     "--unknown-rate must be in [0, 1)"),
    (["train", "--profile", "{d}/head.yaml", "--out", "{d}/x.joblib", "--seed", "-3"], "--seed must be in"),
    (["calibrate", "{d}/rec.npz", "--nominal", "{d}/nominal.yaml", "--out", "{d}/c.yaml", "--seed", "-3"],
     "--seed must be in"),
    (["label", "{d}/rec10.npz", "--model", "{d}/head.joblib", "--out", "{d}/l.csv"], "head 'foreign20'"),
    (["label", "{d}/missing.npz", "--model", "{d}/head.joblib", "--out", "{d}/l.csv"], "no such recording"),
    (["label", "{d}/rec.npz", "--model", "{d}/missing.joblib", "--out", "{d}/l.csv"], "does not exist"),
    (["label", "{d}/rec.npz", "--model", "{d}/tampered.joblib", "--out", "{d}/l.csv"], "tampered"),
    (["label", "{d}/rec.npz", "--model", "{d}/head.joblib", "--baselines", "{d}/base10.npz", "--out",
      "{d}/l.csv"], "baseline"),
    (["label", "{d}/notzip.npz", "--model", "{d}/head.joblib", "--out", "{d}/l.csv"],
     "not an .npz archive (a zip of numpy arrays): it starts with b'row,no'"),
    (["label", "{d}/rec.npz", "--model", "{d}/head.joblib", "--out", "{d}/nodir/l.csv"],
     "nodir: no such directory for --out"),
    # an --out that is one of the inputs: refused before it is written over
    (["label", "{d}/rec.npz", "--model", "{d}/head.joblib", "--out", "{d}/rec.npz"], "also the RECORDING input"),
    (["label", "{d}/rec.npz", "--model", "{d}/head.joblib", "--out", "{d}/../{n}/head.joblib"],
     "also the --model input"),
    (["train", "--profile", "{d}/head.yaml", "--out", "{d}/head.yaml"], "also the --profile input"),
    (["label", "{d}/rec.npz", "--model", "{d}/head.joblib", "--out", "{d}/head.joblib.manifest.json"],
     "also the --model input's manifest"),
    (["label", "{d}/rec.npz", "--model", "{d}/head.joblib", "--out", "{d}"], "is a directory; give the output file"),
    (["label", "{d}/int.npz", "--model", "{d}/head.joblib", "--out", "{d}/l.csv"],
     "got dtype int16: convert ADC counts or millivolts to volts first"),
    (["train", "--profile", "{d}/head.yaml", "--out", "{d}/x.joblib", "--seed", str(2**32)], "--seed must be in"),
    (["train", "--profile", "{d}/head.yaml", "--out", "{d}/x.joblib", "--n-per-class", str(10**13)],
     "--n-per-class must be at most 87381 for 1024-sample traces (the training set's traces within 4 GiB)"),
    # one input given for another
    (["label", "{d}/rec.npz", "--model", "{d}/head.yaml", "--out", "{d}/l.csv"],
     "is a head profile (YAML), not a model"),
    (["label", "{d}/rec.npz", "--model", "{d}/head.joblib.manifest.json", "--out", "{d}/l.csv"],
     "head.joblib.manifest.json is a model's manifest, not the model: give the head.joblib it describes"),
    (["label", "{d}/rec.npz", "--model", "{d}/head.joblib", "--out", ""], "--out is empty: give the output file"),
    (["calibrate", "{d}/rec.npz", "--nominal", "{d}/nominal.yaml", "--out", "{d}/c.yaml", "--report-dir",
      "{d}/rec.npz"], "rec.npz: is a file, not a directory"),
    (["estimate", "{d}/rec.npz", "--profile", "{d}/head.joblib", "--out", "{d}/f.csv"],
     "not a head profile: a binary file, not YAML text"),
    (["label", "{d}/transposed.npz", "--model", "{d}/head.joblib", "--out", "{d}/l.csv"],
     "are the traces transposed?"),
    (["calibrate", "{d}/rec.npz", "--nominal", "{d}/nominal_mpas.yaml", "--out", "{d}/c.yaml"],
     "implausible: channel.mu 6 Pa s (an inkjet head's: 0.0001 to 0.5 Pa s), a value in other units?"),
    (["train", "--profile", "{d}/bad_posterior.yaml", "--out", "{d}/x.joblib"],
     "bad_posterior.yaml: profile 'foreign20': calibration.posterior.parameters must be"),
])
def test_bad_input_is_one_line_and_exit_status_2(work, trained, argv, match, capsys):
    d, _, _ = work
    if not (d / "tampered.joblib").exists():
        data = trained[0].read_bytes()
        (d / "tampered.joblib").write_bytes(data[:-1] + bytes([data[-1] ^ 1]))
        (d / "tampered.joblib.manifest.json").write_text((d / "head.joblib.manifest.json").read_text())
        rec = BaselineRecorder(n_frames=1)
        rec.add(0, HeadProfile.default().simulate({FaultClass.HEALTHY_NOZZLE: 3}, seed=0).traces)
        rec.baselines().save(d / "base10.npz")
        (d / "notzip.npz").write_text("row,nozzle,class\n")  # a CSV given an .npz name
        z = dict(np.load(d / "rec.npz"))
        mv = np.clip(np.nan_to_num(z["traces"] * 1e3), -32768, 32767)  # its hostile rows (NaN, 1e30) cast too
        np.savez(d / "int.npz", **dict(z, traces=mv.astype(np.int16)))  # millivolts as integers
        np.savez(d / "transposed.npz", **dict(z, traces=z["traces"].T.copy()))
        nominal = HeadProfile.load(d / "nominal.yaml")
        nominal.replace(channel={"mu": 1e3 * nominal.channel["mu"]}).save(d / "nominal_mpas.yaml")  # mPa s
        head = HeadProfile.load(d / "head.yaml")  # a calibration section edited by hand: its posterior unreadable
        head.replace(calibration={**head.calibration, "posterior": {"parameters": None, "cov_log": [[1.0]]}}).save(
            d / "bad_posterior.yaml")
    capsys.readouterr()
    inputs = {p: p.read_bytes() for p in (d / "rec.npz", d / "head.yaml", trained[0],
                                          d / "head.joblib.manifest.json")}
    assert main([a.format(d=d, n=d.name) for a in argv]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"inkdiag {argv[0]}: error: ") and match in err[0], err
    assert all(p.read_bytes() == data for p, data in inputs.items())  # bad input loses nothing


@pytest.mark.parametrize(("argv", "match"), [
    ([], "inkdiag: error: the following arguments are required: VERB (see inkdiag --help)"),
    (["train", "--profile", "p.yaml", "--out", "m.joblib", "--n-per-class", "abc"],
     "inkdiag train: error: argument --n-per-class: invalid int value: 'abc' (see inkdiag train --help)"),
    (["estimate", "r.npz", "--profile", "p.yaml", "--out", "f.csv", "--model", "m.joblib"],  # another verb's option
     "inkdiag estimate: error: unrecognized arguments: --model m.joblib (see inkdiag estimate --help)"),
])
def test_usage_errors_are_one_line_and_exit_status_2(argv, match, capsys):
    with pytest.raises(SystemExit) as stop:
        main(argv)
    assert stop.value.code == 2
    assert capsys.readouterr().err.strip().splitlines() == [match]


def test_an_out_named_like_an_option_value_is_not_an_input(work, trained, tmp_path, monkeypatch):
    """Only the arguments that name files read are compared with --out (not --rows, --kind, the verb...)."""
    d, _, _ = work
    monkeypatch.chdir(tmp_path)
    assert main(["label", str(d / "rec.npz"), "--model", str(trained[0]), "--out", "label"]) == 0
    assert (tmp_path / "label").stat().st_size > 0


def test_a_rate_computed_as_one_over_dt_is_the_models(work, trained, tmp_path):
    """10 MHz written by another tool as 1/dt (1e7 + 1e-8) is the model's rate, as the profile checks say."""
    d, head, sim = work
    rec = Recording.from_arrays(sim.traces[:20], head.sample_rate_hz * (1 + 1e-15))
    assert rec.sample_rate_hz != head.sample_rate_hz
    save_recording(tmp_path / "dt.npz", rec)
    out = subprocess.run([sys.executable, "-m", "inkdiag_ros.cli", "label", str(tmp_path / "dt.npz"), "--model",
                          str(trained[0]), "--out", str(tmp_path / "l.csv")], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr


def test_a_recording_in_millivolts_is_labelled_invalid_with_a_hint_about_units(work, trained, tmp_path, capsys):
    d, head, sim = work
    save_recording(tmp_path / "mv.npz", Recording.from_arrays(sim.traces[:20] * 1e3, head.sample_rate_hz))
    assert main(["label", str(tmp_path / "mv.npz"), "--model", str(trained[0]), "--out", str(tmp_path / "l.csv")]) == 0
    cap = capsys.readouterr()  # the summary line on stdout (the CSV went to a file), the hint on stderr
    assert cap.out.startswith("inkdiag label: labelled 0 of 20 rows") and "20 invalid" in cap.out
    assert "are the traces in volts (not millivolts or ADC counts)?" in cap.err
    # the user's own bound too small: the warning names it, not only the traces (helper-125)
    save_recording(tmp_path / "v.npz", Recording.from_arrays(sim.traces[:20], head.sample_rate_hz))
    assert main(["label", str(tmp_path / "v.npz"), "--model", str(trained[0]), "--out", str(tmp_path / "l.csv"),
                 "--max-abs-v", "1e-9"]) == 0
    assert ("20 of 20 rows have a sample beyond --max-abs-v 1e-09 V: is that what the sensor can produce, and are "
            "the traces in volts?") in capsys.readouterr().err
    _, rows = _read(tmp_path / "l.csv")
    assert {r["reason"] for r in rows} == {"out_of_range"}
    for bound in ("inf", "0"):  # as baseline and estimate refuse them (helper-137: label took inf, screening nothing out)
        assert main(["label", str(tmp_path / "v.npz"), "--model", str(trained[0]), "--out", str(tmp_path / "i.csv"),
                     "--max-abs-v", bound]) == 2
        assert f"--max-abs-v must be a finite number > 0 V, got {float(bound)!r}" in capsys.readouterr().err
    # a recording with one such row is not told about units
    assert main(["label", str(d / "rec.npz"), "--model", str(trained[0]), "--out", str(tmp_path / "r.csv")]) == 0
    assert "in volts" not in capsys.readouterr().err


def test_a_recording_of_mostly_invalid_rows_is_warned_about_with_its_reasons(work, trained, tmp_path, capsys):
    d, head, sim = work
    x = sim.traces[:20].copy()
    x[:14, 7] = np.nan  # 14 non_finite, 2 flat, 4 classified
    x[14:16] = 0.0
    save_recording(tmp_path / "nan.npz", Recording.from_arrays(x, head.sample_rate_hz))
    assert main(["label", str(tmp_path / "nan.npz"), "--model", str(trained[0]), "--out", str(tmp_path / "l.csv")]) == 0
    err = capsys.readouterr().err
    assert "warning: 16 of 20 rows are invalid (14 non_finite, 2 flat); most are NaN or infinite samples" in err
    assert "in volts" not in err
    # a recording with two invalid rows of 120 is not warned about
    assert main(["label", str(d / "rec.npz"), "--model", str(trained[0]), "--out", str(tmp_path / "r.csv")]) == 0
    assert "rows are invalid" not in capsys.readouterr().err


def test_another_heads_recording_of_the_same_sampling_is_labelled_with_a_warning(work, trained, tmp_path, capsys):
    # a head with 1.6 times the actuator compliance (181 kHz against 213): its healthy traces look like one fault
    d, head, sim = work
    other = head.replace(name="other", channel={"B_act": head.channel["B_act"] * 1.6})
    x = other.simulate({FaultClass.HEALTHY_NOZZLE: 30}, seed=5).traces
    save_recording(tmp_path / "other.npz", Recording.from_arrays(x, head.sample_rate_hz))
    assert main(["label", str(tmp_path / "other.npz"), "--model", str(trained[0]), "--out", str(tmp_path / "o.csv")]) == 0
    err = capsys.readouterr().err
    assert re.search(r"(\d+) of 30 labelled rows \(\d+ %\) are small_air_bubble: a working head has few faulty "
                     r"nozzles\. If this recording is of a working head, is the model for this head\? It was trained "
                     r"for head 'foreign20', healthy mode 213\.0 kHz", err), err
    # every class in equal numbers (a test recording), or too few rows: no warning
    assert main(["label", str(d / "rec.npz"), "--model", str(trained[0]), "--out", str(tmp_path / "r.csv")]) == 0
    assert "a working head" not in capsys.readouterr().err
    save_recording(tmp_path / "few.npz", Recording.from_arrays(x[:19], head.sample_rate_hz))
    assert main(["label", str(tmp_path / "few.npz"), "--model", str(trained[0]), "--out", str(tmp_path / "f.csv")]) == 0
    assert "a working head" not in capsys.readouterr().err
    # the head's own healthy traces: no warning
    own = head.simulate({FaultClass.HEALTHY_NOZZLE: 30}, seed=5).traces
    save_recording(tmp_path / "own.npz", Recording.from_arrays(own, head.sample_rate_hz))
    assert main(["label", str(tmp_path / "own.npz"), "--model", str(trained[0]), "--out", str(tmp_path / "h.csv")]) == 0
    assert "a working head" not in capsys.readouterr().err
    # invalid rows are not a class: 20 of them among 30 rows are said as invalid (their own warning), not as a class
    own[:20, 3] = np.nan
    save_recording(tmp_path / "bad.npz", Recording.from_arrays(own, head.sample_rate_hz))
    assert main(["label", str(tmp_path / "bad.npz"), "--model", str(trained[0]), "--out", str(tmp_path / "b.csv")]) == 0
    cap = capsys.readouterr()
    assert "20 invalid" in cap.out and "labelled rows" not in cap.err and "20 of 30 rows are invalid" in cap.err
    save_recording(tmp_path / "few.npz", Recording.from_arrays(own[:5], head.sample_rate_hz))  # all of a few
    assert main(["label", str(tmp_path / "few.npz"), "--model", str(trained[0]), "--out", str(tmp_path / "f.csv")]) == 0
    assert "5 of 5 rows are invalid (5 non_finite)" in capsys.readouterr().err


def test_label_csv_says_unknown_for_a_trace_unlike_every_class(work, tmp_path, capsys):
    # issue 16: `inkdiag train --unknown-rate` and `class` = unknown in `inkdiag label`'s CSV
    from inkdiag_core import extract_kpis

    d, head, _ = work
    for rate, name in (("0.01", "u.joblib"), ("0", "c.joblib")):
        assert main(["train", "--profile", str(d / "head.yaml"), "--out", str(tmp_path / name), "--n-per-class",
                     "320", "--unknown-rate", rate, "--quiet"]) == 0
        said = capsys.readouterr().out
        assert ("open-set layer: a trace of a known class is 'unknown' with probability <= 0.01 (with 90 % "
                "confidence); calibration rows per class 240-240\n") in said if rate != "0" else "open-set" not in said
    # too few calibration rows for that confidence: the layer never calls a known class's row unknown, and says so
    assert main(["train", "--profile", str(d / "head.yaml"), "--out", str(tmp_path / "small.joblib"),
                 "--n-per-class", "140", "--quiet"]) == 0
    said = capsys.readouterr().out
    assert "12 classes have fewer than 230 (" in said and "with them the layer never calls a trace unknown" in said
    x = head.simulate({FaultClass.HEALTHY_NOZZLE: 20}, seed=61).traces.astype(np.float64)
    k = extract_kpis(x, 20e6)
    t = np.arange(x.shape[1]) / 20e6
    f = np.linspace(600e3, 1200e3, 20)[:, None]  # a lightly damped foreign-body mode, 30 % of the amplitude
    x += 0.3 * k[:, [3]] * np.exp(-0.01 * 2 * np.pi * f * t) * np.cos(2 * np.pi * f * t)
    save_recording(tmp_path / "fb.npz", Recording.from_arrays(x.astype(np.float32), 20e6))
    got = {}
    for name in ("u.joblib", "c.joblib"):
        assert main(["label", str(tmp_path / "fb.npz"), "--model", str(tmp_path / name), "--out",
                     str(tmp_path / "l.csv")]) == 0
        got[name] = _read(tmp_path / "l.csv")[1]
    unknown = [r for r in got["u.joblib"] if r["class"] == "unknown"]
    assert len(unknown) >= 18
    assert all(0.99 <= float(r["confidence"]) < 1 and r["reason"] == "" for r in unknown)
    assert not any(r["class"] == "unknown" for r in got["c.joblib"])  # --unknown-rate 0: no layer


def test_rows_repeating_a_nozzle_and_frame_are_labelled_with_a_warning(work, trained, tmp_path, capsys):
    """A nozzle column gone wrong (every row nozzle 0, one frame): each row is labelled as before, and the
    run says that a frame holds one trace per nozzle. A recording without repeats is not told."""
    d, head, sim = work
    save_recording(tmp_path / "dup.npz", Recording.from_arrays(sim.traces[:30], head.sample_rate_hz,
                                                               nozzle=np.zeros(30, int)))
    assert main(["label", str(tmp_path / "dup.npz"), "--model", str(trained[0]), "--out", str(tmp_path / "l.csv")]) == 0
    assert ("warning: 29 row(s) repeat the nozzle, frame_id and stamp of an earlier row; each is labelled, but a "
            "frame holds one trace per nozzle") in capsys.readouterr().err
    _, dup = _read(tmp_path / "l.csv")
    save_recording(tmp_path / "ok.npz", Recording.from_arrays(sim.traces[:30], head.sample_rate_hz))
    assert main(["label", str(tmp_path / "ok.npz"), "--model", str(trained[0]), "--out", str(tmp_path / "k.csv")]) == 0
    assert "repeat" not in capsys.readouterr().err
    _, ok = _read(tmp_path / "k.csv")
    assert [(r["class"], r["confidence"]) for r in dup] == [(r["class"], r["confidence"]) for r in ok]
    # frames told apart by their stamps alone (no frame_id column): no repeat
    save_recording(tmp_path / "st.npz", Recording.from_arrays(sim.traces[:30], head.sample_rate_hz,
                                                              nozzle=np.arange(30) % 10, stamp=np.arange(30) // 10))
    assert main(["label", str(tmp_path / "st.npz"), "--model", str(trained[0]), "--out", str(tmp_path / "s.csv")]) == 0
    assert "repeat" not in capsys.readouterr().err


def test_train_checks_the_recorded_rows_labels_against_the_model(work, tmp_path, capsys):
    """helper-120: a recording whose labels were shuffled trained a model with no word (validation pools a few
    recorded rows with many simulated ones). train now scores the recorded validation rows alone, and warns when
    they come out far below the rest; a class of 1-3 rows (none held out) is noted. The right labels: no warning."""
    d, head, _ = work
    sim = head.simulate({c: 12 for c in FaultClass}, seed=78)
    lab = np.asarray(sim.label_values(), dtype=object)
    shuffled = np.random.default_rng(0).permutation(lab)
    for name, labels in (("right", lab), ("shuffled", shuffled)):
        save_recording(tmp_path / f"{name}.npz", Recording.from_arrays(sim.traces, head.sample_rate_hz, label=labels))
    args = ["--profile", str(d / "head.yaml"), "--n-per-class", "40", "--unknown-rate", "0", "--quiet"]
    assert main(["train", *args, "--out", str(tmp_path / "r.joblib"), "--data", str(tmp_path / "right.npz")]) == 0
    out = capsys.readouterr()
    assert "recorded validation rows (36): FI accuracy" in out.out and "called unknown" in out.out
    assert [w for w in out.err.splitlines() if "warning" in w and "no channel.f_act" not in w] == [], out.err
    assert main(["train", *args, "--out", str(tmp_path / "s.joblib"), "--data", str(tmp_path / "shuffled.npz")]) == 0
    out = capsys.readouterr()
    assert "warning: the recorded validation rows given a class are labelled right" in out.err, out.err
    info = json.loads((tmp_path / "s.joblib.manifest.json").read_text())["config"]
    assert info["validation_real_fi_accuracy"] < 0.5 and info["n_real_rows_validation"] == 36
    few = lab.copy()
    few[:2] = "slightly_dried"  # 14 rows of it; deeply dried left with 2 rows:
    few[np.flatnonzero(lab == "deeply_dried")[2:]] = "intermediately_dried"
    save_recording(tmp_path / "few.npz", Recording.from_arrays(sim.traces, head.sample_rate_hz, label=few))
    assert main(["train", *args, "--out", str(tmp_path / "f.joblib"), "--data", str(tmp_path / "few.npz")]) == 0
    assert "none held out, so nothing checks their labels" in capsys.readouterr().out


def test_train_warns_of_a_model_that_tells_its_own_simulated_classes_apart_poorly():
    """helper-125: profiles with a value in other units (a nozzle radius of 1.5 mm) trained to FI 41-70 % with 8-86 %
    false alarms, exit 0, without a word. The validation scores of the heads of reports/heads.md (FI 90-97 %, about
    0 % missed and false alarms) pass; poor ones are warned about, naming an implausible value where there is one."""
    from inkdiag_ros.verbs.train import _poor_validation

    def scores(fi, fnr=0.0, fpr=0.0, n=15000):
        return {"validation_fi_accuracy": fi, "validation_fd_fnr": fnr, "validation_fd_fpr": fpr, "n_validation": n}

    head = HeadProfile.default()
    assert _poor_validation(scores(0.927), head) is None and _poor_validation(scores(0.86, 0.005, 0.01), head) is None
    odd = head.replace(channel={"r_n": 1.5e-3})
    why = _poor_validation(scores(0.511, 0.005, 0.8562), odd)
    assert why.startswith("the model tells the profile's own simulated classes apart poorly (FI 51.1 %, faults "
                          "missed 0.50 %, false alarms 85.62 %") and "implausible: channel.r_n 0.0015 m" in why
    assert "implausible" not in _poor_validation(scores(0.95, 0.0, 0.05), head)  # the FD rates alone are poor too
    assert _poor_validation(scores(0.95, 0.03, 0.0), head) is not None
    # a tiny training set (--n-per-class 8: 24 validation rows) may be the cause: said (helper-128)
    assert _poor_validation(scores(0.792, n=24), head).endswith("; or too few traces: 24 validation rows, raise "
                                                                  "--n-per-class")
    assert "too few" not in _poor_validation(scores(0.792), head)


def test_train_warns_of_a_hand_written_profile_without_the_actuators_resonance(trained):
    """helper-134: a complete profile written by hand without channel.f_act trained its empty-channel classes on the
    default head's actuator at its B_act, with no spread: a head whose actuator rang at 0.75-0.8 of that had every
    empty-channel trace labelled unknown, and train said nothing. A profile calibrate made (it noted the assumed
    actuator and widened its spread), one giving f_act, and the default head itself are not warned about."""
    from inkdiag_core.calibration import assumed_actuator_warning

    _, out = trained
    assert re.search(r"inkdiag train: warning: profile 'foreign20' gives no channel.f_act: its empty channels are "
                     r"simulated with an actuator like the default head's at this B_act \(2175 kHz\), with no spread\. "
                     r".*give channel.f_act \(Hz\) and channel.zeta_act", out.stderr), out.stderr[-2000:]
    head = _head()
    assert "spread 8.5 %" in assumed_actuator_warning(head.replace(spreads_overrides={"actuator_resonance_rel": 0.085}))
    for fine in (HeadProfile.default(), head.replace(channel={"f_act": 1.6e6}), head.replace(calibration={"by": "x"}),
                 head.replace(channel={"r_r": None, "L_r": None, "B_act": None, "b": None})):  # nominal: not trained
        assert assumed_actuator_warning(fine) is None


def test_label_warns_when_the_rows_it_calls_fully_blocked_ring_away_from_the_models(work, trained, tmp_path, capsys,
                                                                                      monkeypatch):
    """helper-134: a head whose restrictor calibration left 18 % off (healthy traces leave it to a prior) labelled
    5 % of its partially blocked nozzles right, and nothing said so. Its fully blocked nozzles rang 4.9 % below the
    model's: label says so and names the second pass; the head's own fully blocked nozzles are not warned about."""
    from inkdiag_core.calibration import BLOCKED_MODE_WARNING, blocked_mode_offset

    d, head, _ = work
    model, _ = trained
    other = head.replace(channel={"L_r": 1.25 * head.channel["L_r"]})  # its blocked mode about 10 % lower
    for name, prof, warned in (("own", head, False), ("other", other, True)):
        sim = prof.simulate({FaultClass.FULLY_BLOCKED: 30, FaultClass.HEALTHY_NOZZLE: 30}, seed=5)
        x, blocked = sim.traces, np.asarray(sim.label_values()) == "fully_blocked"
        save_recording(tmp_path / f"{name}.npz", Recording.from_arrays(x, head.sample_rate_hz))
        assert main(["label", str(tmp_path / f"{name}.npz"), "--model", str(model), "--out",
                     str(tmp_path / f"{name}.csv")]) == 0
        err = capsys.readouterr().err
        _, rows = _read(tmp_path / f"{name}.csv")
        n = sum(r["class"] == "fully_blocked" for r in rows)
        got = blocked_mode_offset(head, x[blocked], head.sample_rate_hz)
        assert (abs(got["offset_rel"]) > BLOCKED_MODE_WARNING) == warned, got
        if warned:
            assert n >= 10 and re.search(
                rf"warning: the rows labelled fully_blocked \({n} usable of the first 400 at most\) ring at [0-9.]+ "
                rf"kHz, the model's fully blocked nozzles at [0-9.]+ kHz \(-[0-9.]+ %; a well calibrated head's within "
                rf"2 %\): .*--blocked {tmp_path}/other.npz --blocked-labels {tmp_path}/other.csv --out HEAD2.yaml", err), err
            warning = err
        else:
            assert "labelled fully_blocked (" not in err, err
    assert blocked_mode_offset(head, x[blocked][:9], head.sample_rate_hz) is None  # too few to tell
    # the rows kept across a bag's chunks (20 rows a chunk here) are those the CSV calls fully blocked: the same words
    from _bags import write_bag

    import inkdiag_ros.verbs.label as label_verb

    bag = write_bag(tmp_path / "bag", [(10 * k, x[10 * k:10 * k + 10]) for k in range(6)], fs=head.sample_rate_hz)
    monkeypatch.setattr(label_verb, "BATCH_ROWS", 20)
    assert main(["label", str(bag), "--model", str(model), "--out", str(tmp_path / "bag.csv")]) == 0
    said = capsys.readouterr().err
    assert said[said.index("warning: the rows"):].split(": inkdiag calibrate")[0] == \
        warning[warning.index("warning: the rows"):].split(": inkdiag calibrate")[0], (said, warning)
    # a profile a second pass made: the restrictor is not blamed; a model whose own blocked traces clip: no word
    second = head.replace(calibration={"n_blocked_traces": 50, "blocked_mode_hz": 1.0e5})
    assert "are these rows fully blocked nozzles of that head" in label_verb._blocked_mode_warning(
        second, list(x[blocked]), head.sample_rate_hz, SimpleNamespace(topic=None, recording="r", out="o"))
    loud = head.replace(sensor={"adc_range_v": 0.3})  # above the healthy rms (0.245 V), below the blocked peaks
    assert blocked_mode_offset(loud, x[blocked], head.sample_rate_hz) is None
