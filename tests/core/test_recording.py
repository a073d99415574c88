"""Recordings (.npz) for the offline verbs: round trip, defaults, and clear errors."""

import os
import re
import zipfile

import numpy as np
import pytest

from inkdiag_core import Recording, RecordingError, load_recording, save_recording


def _save(path, **arrays):
    np.savez(path, **arrays)
    return path


def test_round_trip_and_defaults(tmp_path):
    t = np.random.default_rng(0).normal(size=(5, 64)).astype(np.float32)
    rec = load_recording(_save(tmp_path / "a.npz", traces=t, sample_rate_hz=10e6))
    np.testing.assert_array_equal(rec.traces, t)
    assert rec.sample_rate_hz == 10e6 and rec.n_rows == 5 and rec.n_samples == 64
    np.testing.assert_array_equal(rec.nozzle, np.arange(5))
    np.testing.assert_array_equal(rec.frame_id, np.zeros(5))
    assert np.isnan(rec.stamp).all() and rec.label is None
    full = Recording.from_arrays(t, 20e6, nozzle=[4, 3, 2, 1, 0], frame_id=[1, 1, 1, 2, 2],
                                 stamp=[0.1] * 5, label=["healthy_nozzle"] * 4 + ["deeply_dried"])
    back = load_recording(save_recording(tmp_path / "b.npz", full))
    for k in ("traces", "nozzle", "frame_id", "stamp"):
        np.testing.assert_array_equal(getattr(back, k), getattr(full, k))
    assert list(back.label) == list(full.label) and back.sample_rate_hz == 20e6


def test_non_finite_rows_load_as_they_are(tmp_path):
    t = np.zeros((3, 32), np.float32)
    t[1, 4] = np.nan
    rec = load_recording(_save(tmp_path / "a.npz", traces=t, sample_rate_hz=1e6))
    assert np.isnan(rec.traces[1, 4]) and rec.n_rows == 3


@pytest.mark.parametrize("arrays, match", [
    ({"sample_rate_hz": 1e6}, "no 'traces'"),
    ({"traces": np.zeros((2, 8))}, "no 'sample_rate_hz'"),
    ({"traces": np.zeros(8), "sample_rate_hz": 1e6}, "2-D array"),
    ({"traces": np.zeros((2, 8)), "sample_rate_hz": -1.0}, "positive number of Hz"),
    ({"traces": np.zeros((2, 8)), "sample_rate_hz": [1e6, 2e6]}, "must be a scalar"),
    ({"traces": np.zeros((2, 8)), "sample_rate_hz": 1e6, "nozzle": [1, 2, 3]}, r"nozzle must have one entry"),
    ({"traces": np.zeros((2, 8)), "sample_rate_hz": 1e6, "frame_id": [0.5, 1]}, "frame_id must be integers"),
    ({"traces": np.zeros((2, 8)), "sample_rate_hz": 1e6, "label": ["healthy_nozzle", "wet"]}, "'wet' is not a class"),
    ({"traces": np.array([["a", "b"]]), "sample_rate_hz": 1e6}, "must be floating-point volts"),
    ({"traces": np.zeros((2, 8), np.int16), "sample_rate_hz": 1e6}, "convert ADC counts or millivolts to volts"),
    ({"traces": np.zeros((2, 8)), "sample_rate_hz": 1e6, "label": ["wet", "dry"]}, "'dry', 'wet' are not classes"),
])
def test_bad_recordings_name_the_key(tmp_path, arrays, match):
    with pytest.raises(RecordingError, match=match):
        load_recording(_save(tmp_path / "bad.npz", **arrays))


def test_unreadable_files(tmp_path):
    with pytest.raises(RecordingError, match="no such recording"):
        load_recording(tmp_path / "none.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip at all")
    with pytest.raises(RecordingError, match=r"not an .npz archive \(a zip of numpy arrays\): it starts with b'not a"):
        load_recording(tmp_path / "junk.npz")
    (tmp_path / "empty.npz").write_bytes(b"")
    with pytest.raises(RecordingError, match="an empty file"):
        load_recording(tmp_path / "empty.npz")
    (tmp_path / "cut.npz").write_bytes(b"PK\x03\x04" + b"\x00" * 20)  # a zip cut short
    with pytest.raises(RecordingError, match="cannot read the recording"):
        load_recording(tmp_path / "cut.npz")
    os.mkfifo(tmp_path / "pipe.npz")  # np.load cannot seek in it, and opening it would wait for a writer
    with pytest.raises(RecordingError, match="not a regular file"):
        load_recording(tmp_path / "pipe.npz")
    np.save(tmp_path / "one.npy", np.zeros(3))
    with pytest.raises(RecordingError, match="not an .npz"):
        load_recording(tmp_path / "one.npy")
    with pytest.raises(RecordingError, match="directory"):
        load_recording(tmp_path)
    with zipfile.ZipFile(tmp_path / "text.npz", "w") as z:  # a member that is not .npy data: its raw bytes
        z.writestr("traces.npy", b"1 2 3\n")
        z.writestr("sample_rate_hz.npy", b"1e7")
    with pytest.raises(RecordingError, match=r"'traces' is not a numpy array in the archive \(not .npy data\)"):
        load_recording(tmp_path / "text.npz")


def test_labels_stored_as_bytes_are_text(tmp_path):
    """An 'S' array (as h5py or MATLAB write) holds the class names as bytes."""
    rec = load_recording(_save(tmp_path / "b.npz", traces=np.zeros((2, 8)), sample_rate_hz=1e6,
                               label=np.array(["healthy_nozzle", "deeply_dried"]).astype("S")))
    assert list(rec.label) == ["healthy_nozzle", "deeply_dried"]


def test_labels_are_read_without_case_as_a_labels_csv_is(tmp_path):
    rec = load_recording(_save(tmp_path / "c.npz", traces=np.zeros((3, 8)), sample_rate_hz=1e6,
                               label=np.array(["Healthy_Nozzle", "DEEPLY_DRIED", "Unknown"])))
    assert list(rec.label) == ["healthy_nozzle", "deeply_dried", "unknown"]
    # and without padding: a MATLAB char matrix pads its rows with spaces (bytes, as scipy.io or h5py give them)
    rec = load_recording(_save(tmp_path / "p.npz", traces=np.zeros((3, 8)), sample_rate_hz=1e6,
                               label=np.array([b"ok_signal   ", b" deeply_dried", b"unknown\t"])))
    assert list(rec.label) == ["ok_signal", "deeply_dried", "unknown"]


def test_labels_from_inkdiag_label_load_and_training_leaves_their_rows_out(tmp_path):
    """A label column copied from `inkdiag label` holds `invalid` and `unknown`: they load (estimate
    --rows dried and baseline take such a recording), and training data leaves those rows out."""
    from inkdiag_core import HeadProfile, simulate
    from inkdiag_core.training import _real_rows

    profile = HeadProfile.default()
    sim = simulate({"healthy_nozzle": 6, "deeply_dried": 6}, seed=2)
    label = sim.label_values().astype(object)
    label[[0, 7]] = ["invalid", "unknown"]
    rec = load_recording(_save(tmp_path / "l.npz", traces=sim.traces.astype(np.float32), sample_rate_hz=10e6,
                               label=label.astype(str)))
    assert list(rec.label[[0, 7]]) == ["invalid", "unknown"]
    fit_x, fit_y, val_x, val_y, counts = _real_rows(rec, profile, 0, 0.25, 8)
    assert (counts["n_real_rows"], counts["n_real_rows_invalid"]) == (10, 2)
    assert (counts["n_real_rows_screened_out"], counts["n_real_rows_without_class"]) == (0, 2)
    assert counts["real_rows_per_class"] == {"deeply_dried": 5, "healthy_nozzle": 5}
    assert set(fit_y) | set(val_y) == {"healthy_nozzle", "deeply_dried"}


def _csv(path, text):
    path.write_text(text)
    return path


def test_labels_from_csv_by_row_by_nozzle_and_by_nozzle_and_frame(tmp_path):
    from inkdiag_core import labels_from_csv

    t = np.random.default_rng(0).normal(size=(6, 64)).astype(np.float32)
    rec = Recording.from_arrays(t, 10e6, nozzle=[7, 8, 9, 7, 8, 9], frame_id=[0, 0, 0, 1, 1, 1])
    got, n = labels_from_csv(rec, _csv(tmp_path / "r.csv", "row, nozzle ,class,confidence\n"
                                       "4,8,fully_blocked,0.9\n0,,healthy_nozzle,\n"))
    assert n == 2 and list(got.label) == ["healthy_nozzle", "unknown", "unknown", "unknown", "fully_blocked", "unknown"]
    assert rec.label is None and got.traces is rec.traces  # a copy with labels; the recording is untouched
    got, n = labels_from_csv(rec, _csv(tmp_path / "n.csv", "nozzle,class\n9,deeply_dried\n"))
    assert n == 2 and list(got.label) == ["unknown", "unknown", "deeply_dried"] * 2
    got, n = labels_from_csv(rec, _csv(tmp_path / "nf.csv", "frame_id,nozzle,class\n1,9,deeply_dried\n"))
    assert n == 1 and list(got.label) == ["unknown"] * 5 + ["deeply_dried"]
    # a spreadsheet's CSV: byte-order mark, Windows line ends, capitalised headers, blank and comma-only lines
    (tmp_path / "x.csv").write_bytes("\ufeffRow,Nozzle,Class\r\n1,8,small_air_bubble\r\n\r\n,,\r\n5,9,ok_signal\r\n"
                                     .encode("utf-8"))
    got, n = labels_from_csv(rec, tmp_path / "x.csv")
    assert n == 2 and list(got.label) == ["unknown", "small_air_bubble"] + ["unknown"] * 3 + ["ok_signal"]
    got, n = labels_from_csv(rec, _csv(tmp_path / "c.csv", "row,class\n2,Fully_Blocked\n"))  # capitalised
    assert n == 1 and got.label[2] == "fully_blocked"


@pytest.mark.parametrize("text, message", [
    ("row;class\n0;ok_signal\n", "needs a header with a 'class' column and a 'row' or 'nozzle' column"),
    ("", "needs a header"),
    ("row,class\n", "l.csv: a header and no labelled line: it names no row"),  # was "no row is usable" (helper-84)
    ("nozzle,class\n\n , \n", "l.csv: a header and no labelled line"),
    ("row,class\n0,clogged\n", "l.csv:2: class 'clogged' is not a class"),
    ("row,class\n0,ok_signal\n6,ok_signal\n", "l.csv:3: row 6 is not a row of recording (0..5)"),
    ("row,class\n-1,ok_signal\n", "l.csv:2: row -1 is not a row"),
    ("row,class\n1.5,ok_signal\n", "l.csv:2: row '1.5' is not an integer"),
    ("row,frame_id,class\n3,0,ok_signal\n", "l.csv:2: row 3 is frame_id 1 in recording, the CSV says 0"),
    ("row,class\n2,ok_signal\n2,ok_signal\n", "l.csv:3: row 2 is named twice (first on line 2)"),
    ("nozzle,class\n7,ok_signal\n7,ok_signal\n", "l.csv:3: nozzle 7 is named twice (first on line 2)"),
    ("nozzle,frame_id,class\n7,1,ok_signal\n8,1,ok_signal\n7,1,ok_signal\n",
     "l.csv:4: nozzle 7 in frame 1 is named twice (first on line 2)"),
    ("row,class,Class\n0,ok_signal,ok_signal\n", "the header names 'class' twice"),
    ("row,class\n0_3,ok_signal\n", "l.csv:2: row '0_3' is not an integer"),
    ("row,nozzle,class\n3,-1,ok_signal\n", "l.csv:2: row 3 is nozzle 7 in recording, the CSV says -1"),
    ("nozzle,class\n,ok_signal\n", "l.csv:2: nozzle '' is not an integer"),
    ("nozzle,class\n5,ok_signal\n", "l.csv:2: recording has no row of nozzle 5"),
    ("nozzle,frame_id,class\n7,2,ok_signal\n", "l.csv:2: recording has no row of nozzle 7 in frame 2"),
    ("row,class\n0,ok_signal,extra\n", "l.csv:2: 3 fields, the header has 2: ['extra'] beyond its columns"),
    ('row,class\n"0,ok_signal\n1,ok_signal\n', "l.csv:2: cannot read the labels CSV: unexpected end of data"),
    # the quote's record begins after a blank line and a good one (helper-145: no line was named)
    ('row,class\n0,ok_signal\n\n1,"ok_signal\n2,ok_signal\n', "l.csv:4: cannot read the labels CSV: unexpected end"),
    # beyond an int64: was OverflowError, a traceback (helper-106)
    ("row,class\n99999999999999999999999999,ok_signal\n", "l.csv:2: row 99999999999999999999999999 is too large"),
    ("nozzle,frame_id,class\n7,-99999999999999999999,ok_signal\n", "l.csv:2: frame_id -99999999999999999999 is too"),
])
def test_labels_from_csv_refuses_what_it_cannot_use_naming_the_line(tmp_path, text, message):
    from inkdiag_core import labels_from_csv

    t = np.random.default_rng(0).normal(size=(6, 64)).astype(np.float32)
    rec = Recording.from_arrays(t, 10e6, nozzle=[7, 8, 9, 7, 8, 9], frame_id=[0, 0, 0, 1, 1, 1])
    with pytest.raises(RecordingError, match=re.escape(message)):
        labels_from_csv(rec, _csv(tmp_path / "l.csv", text))


def test_labels_from_csv_refuses_a_missing_file_a_directory_and_bytes_that_are_not_text(tmp_path):
    from inkdiag_core import labels_from_csv

    rec = Recording.from_arrays(np.zeros((2, 64), np.float32), 10e6)
    with pytest.raises(RecordingError, match="no such labels file"):
        labels_from_csv(rec, tmp_path / "missing.csv")
    with pytest.raises(RecordingError, match="is a directory, not a labels CSV"):
        labels_from_csv(rec, tmp_path)
    (tmp_path / "u.csv").write_bytes("row,class\n0,ok_signal\n".encode("utf-16"))  # a spreadsheet's export
    with pytest.raises(RecordingError, match="UTF-16 text .*: save the labels as a UTF-8 CSV"):
        labels_from_csv(rec, tmp_path / "u.csv")
    (tmp_path / "b.csv").write_bytes(b"\x80\x81\x00r")  # not UTF-8 text
    with pytest.raises(RecordingError, match="cannot read the labels CSV"):
        labels_from_csv(rec, tmp_path / "b.csv")


def test_a_label_csv_that_names_part_of_the_recording_is_warned_about(tmp_path):
    """inkdiag label's CSV names every row of its recording: one that names fewer is another recording's."""
    from inkdiag_core import read_labels_csv

    label = tmp_path / "label.csv"
    label.write_text("row,nozzle,frame_id,class,confidence,reason\n0,0,0,deeply_dried,0.9,\n1,1,0,healthy_nozzle,0.99,\n")
    hand = tmp_path / "hand.csv"
    hand.write_text("row,class\n0,deeply_dried\n1,healthy_nozzle\n")
    why = read_labels_csv(label).coverage_warning(2, 5, "rec.npz")
    assert why == (f"{label} looks like `inkdiag label`'s CSV, which names every row of the recording it labelled, "
                   "but it names 2 of the 5 rows of rec.npz (rows 0..1): the labels of another recording?")
    assert read_labels_csv(label).coverage_warning(2, 2, "rec.npz") is None  # every row
    assert read_labels_csv(hand).coverage_warning(2, 5, "rec.npz") is None  # a hand's CSV names what it checked


def test_labels_from_csv_takes_empty_cells_beyond_the_header(tmp_path):
    """A spreadsheet's export may end lines with empty cells; a non-empty one beyond the header is refused."""
    from inkdiag_core import labels_from_csv

    rec = Recording.from_arrays(np.random.default_rng(0).normal(size=(2, 64)).astype(np.float32), 10e6)
    labelled, n_named = labels_from_csv(rec, _csv(tmp_path / "l.csv", "row,class\n0,ok_signal,,\n1,deeply_dried, \n"))
    assert n_named == 2 and list(labelled.label) == ["ok_signal", "deeply_dried"]


def test_float64_samples_beyond_float32s_range_stay_finite_and_are_out_of_range():
    """A float64 recording with a finite sample of 1e300: converted to float32 it was inf, with numpy's overflow
    warning on stderr, and screening called the row non_finite (helper-84's QA). Now it is the largest float32 of
    its sign: screening says out_of_range; NaN and inf rows are still non_finite; the other rows are untouched."""
    import warnings

    from inkdiag_core import screen_traces

    x = np.sin(np.arange(64 * 5, dtype=np.float64) / 3.0).reshape(5, 64) * 0.3
    x[1, 7], x[2, 9], x[3, 0], x[4, 4] = 1e300, -1e300, np.nan, np.inf
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no RuntimeWarning leaks
        rec = Recording.from_arrays(x, 10e6)
    assert rec.traces.dtype == np.float32
    assert rec.traces[1, 7] == np.finfo(np.float32).max and rec.traces[2, 9] == -np.finfo(np.float32).max
    np.testing.assert_array_equal(rec.traces[0], x[0].astype(np.float32))
    valid, reasons = screen_traces(rec.traces, max_abs_v=10.0)
    assert reasons.tolist() == ["", "out_of_range", "out_of_range", "non_finite", "non_finite"]
