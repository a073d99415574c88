"""Model files are verified before unpickling."""

import json

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


def test_missing_file_or_manifest_is_refused(saved, tmp_path):
    path, _, _ = saved
    with pytest.raises(ModelFileError, match="does not exist"):
        load_model(tmp_path / "nope.joblib")
    path.with_name(path.name + ".manifest.json").unlink()
    with pytest.raises(ModelFileError, match="no manifest"):
        load_model(path)


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
