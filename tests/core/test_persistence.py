"""Model files are verified before unpickling."""

import json
import os
import re

import numpy as np
import pytest
from sklearn.linear_model import LogisticRegression

from inkdiag_core.persistence import ModelFileError, load_model, read_manifest, save_model


@pytest.fixture
def saved(tmp_path):
    rng = np.random.default_rng(0)
    X, y = rng.standard_normal((40, 3)), np.repeat([0, 1], 20)
    model = LogisticRegression().fit(X, y)
    path = tmp_path / "m.joblib"
    save_model(model, path, config={"kind": "logreg"}, scores={"acc": 1.0})
    return path, model, X


def test_round_trip_keeps_predictions_and_manifest(saved):
    path, model, X = saved
    loaded, manifest = load_model(path)
    np.testing.assert_array_equal(loaded.predict(X), model.predict(X))
    assert manifest["config"] == {"kind": "logreg"} and manifest["scores"] == {"acc": 1.0}
    assert len(manifest["sha256"]) == 64


def test_tampered_file_is_refused(saved):
    path, _, _ = saved
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(ModelFileError, match="sha256 .* tampered"):
        load_model(path)


def test_truncated_file_is_refused(saved):
    path, _, _ = saved
    path.write_bytes(path.read_bytes()[:-10])
    with pytest.raises(ModelFileError, match="truncated or tampered"):
        load_model(path)


@pytest.mark.parametrize("damage", ["zeroed half", "truncated", "not a pickle"])
def test_damaged_file_whose_manifest_matches_it_is_a_model_file_error(saved, damage):
    """A file damaged and its manifest's sha256 and size rewritten to match (helper-68's QA: a KeyError
    traceback, exit 1): a ModelFileError naming the file, as every other refused file."""
    path, _, _ = saved
    data = path.read_bytes()
    data = {"zeroed half": data[:len(data) // 2] + bytes(len(data) - len(data) // 2),
            "truncated": data[:len(data) * 2 // 3], "not a pickle": b"hello, not a model"}[damage]
    path.write_bytes(data)
    import hashlib

    mpath = path.with_name(path.name + ".manifest.json")
    manifest = json.loads(mpath.read_text())
    manifest.update(sha256=hashlib.sha256(data).hexdigest(), size_bytes=len(data))
    mpath.write_text(json.dumps(manifest))
    with pytest.raises(ModelFileError, match=f"model file {path} matches its manifest but does not load"):
        load_model(path)


def test_a_model_naming_a_class_this_code_lacks_is_a_model_file_error(tmp_path, monkeypatch):
    """A pickle whose module is gone (a model of another inkdiag version): said so, not 'damaged'."""
    import sys

    (tmp_path / "gone_mod.py").write_text("class Model:\n    pass\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    import gone_mod

    path = tmp_path / "m.joblib"
    save_model(gone_mod.Model(), path)
    monkeypatch.delitem(sys.modules, "gone_mod")
    (tmp_path / "gone_mod.py").unlink()
    with pytest.raises(ModelFileError, match="needs ModuleNotFoundError: .*gone_mod.*another version of inkdiag"):
        load_model(path)


@pytest.mark.parametrize("error", [MemoryError(), OSError("Invalid data stream")])
def test_what_unpickling_raises_on_damaged_bytes_is_a_model_file_error(saved, monkeypatch, error):
    """A damaged length field asks for more memory than there is; damaged first bytes pick a decompressor
    (bz2: OSError): said of the file, not a traceback (helper-71's byte flips)."""
    import joblib

    def fail(*_a, **_k):
        raise error

    monkeypatch.setattr(joblib, "load", fail)
    with pytest.raises(ModelFileError, match=f"model file {saved[0]} .*{type(error).__name__}"):
        load_model(saved[0])


def test_missing_file_or_manifest_is_refused(saved, tmp_path):
    path, _, _ = saved
    with pytest.raises(ModelFileError, match="does not exist"):
        load_model(tmp_path / "nope.joblib")
    with pytest.raises(ModelFileError, match=f"model file {tmp_path} is a directory, not a model file"):
        load_model(tmp_path)  # it exists: not "does not exist" (helper-82's QA: fdi -p model_path:=models)
    path.with_name(path.name + ".manifest.json").unlink()
    with pytest.raises(ModelFileError, match=re.escape(f"no manifest ({path}.manifest.json is missing)")):
        load_model(path)  # its directory named (helper-84's QA: the manifest's name alone)


def test_version_mismatch_is_refused(saved):
    path, _, _ = saved
    mpath = path.with_name(path.name + ".manifest.json")
    manifest = json.loads(mpath.read_text())
    manifest["versions"]["scikit-learn"] = "0.24.2"
    mpath.write_text(json.dumps(manifest))
    with pytest.raises(ModelFileError, match=r"scikit-learn 0.24.2 \(file\)"):
        load_model(path)
    assert read_manifest(path)["versions"]["scikit-learn"] == "0.24.2"


def test_garbage_manifest_is_refused(saved):
    path, _, _ = saved
    path.with_name(path.name + ".manifest.json").write_text("{not json")
    with pytest.raises(ModelFileError, match="not valid JSON"):
        load_model(path)
    path.with_name(path.name + ".manifest.json").write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(ModelFileError, match="not valid JSON: nested too deeply"):  # not a RecursionError
        load_model(path)
    assert issubclass(ModelFileError, ValueError)


@pytest.mark.parametrize("key", ["config", "versions", "scores"])
def test_manifest_whose_sections_are_not_objects_is_refused(saved, key):
    """A manifest edited so that a section is a list or a string: ModelFileError, not AttributeError."""
    path, _, _ = saved
    mpath = path.with_name(path.name + ".manifest.json")
    manifest = json.loads(mpath.read_text())
    manifest[key] = ["not", "an", "object"]
    mpath.write_text(json.dumps(manifest))
    with pytest.raises(ModelFileError, match=f"'{key}' must be an object"):
        load_model(path)


@pytest.mark.parametrize("mask", [0o022, 0o077, 0o002])
def test_a_saved_model_and_baselines_get_a_new_files_mode(tmp_path, mask):
    """Not mkstemp's owner-only 0600: what open() gives a new file under the umask, for a node of another
    user to read (the model file and a baselines file; their manifest and CSVs were always so)."""
    from inkdiag_core import BaselineRecorder, simulate_nozzles
    from inkdiag_core._fileio import _umask

    old = os.umask(mask)
    try:
        assert _umask() == mask  # /proc/self/status's Umask line, read without setting it
        save_model(LogisticRegression().fit([[0.0], [1.0]], [0, 1]), tmp_path / "m.joblib")
        rec = BaselineRecorder(n_frames=1, fm_frames=0)
        rec.add(0, simulate_nozzles(["healthy_nozzle"] * 2, seed=1).traces)
        rec.baselines().save(tmp_path / "b.npz")
    finally:
        os.umask(old)
    for p in (tmp_path / "m.joblib", tmp_path / "b.npz"):
        assert p.stat().st_mode & 0o777 == 0o666 & ~mask, (p, oct(p.stat().st_mode))


def test_a_filesystem_that_refuses_modes_still_gets_the_files(tmp_path, monkeypatch):
    """Some network and FUSE mounts refuse chmod: the file is written all the same (mkstemp's mode)."""
    def refuse(fd, mode):
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(os, "fchmod", refuse)
    save_model(LogisticRegression().fit([[0.0], [1.0]], [0, 1]), tmp_path / "m.joblib")
    assert load_model(tmp_path / "m.joblib") is not None
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.joblib", "m.joblib.manifest.json"]


@pytest.mark.parametrize("stage", ["model", "manifest"])
def test_a_save_stopped_half_way_leaves_no_file_behind(tmp_path, monkeypatch, stage):
    """A Ctrl-C while `graph --train-if-missing` (scripts/run's first run) saves the default model: neither the
    model, its manifest nor a temporary file stays (the next run trains it again, rather than refusing a model
    without its manifest)."""
    import joblib

    from inkdiag_core import persistence

    def stopped(*args, **kwargs):
        with open(args[1], "w") as f:  # half written
            f.write("{")
        raise KeyboardInterrupt

    if stage == "model":
        monkeypatch.setattr(joblib, "dump", lambda model, path, *a, **k: stopped(model, path))
    else:
        monkeypatch.setattr(persistence.json, "dump", lambda doc, f, **k: (f.write("{"), stopped(doc, f.name)))
    with pytest.raises(KeyboardInterrupt):
        save_model(LogisticRegression().fit([[0.0], [1.0]], [0, 1]), tmp_path / "models" / "m.joblib")
    assert list((tmp_path / "models").iterdir()) == []
