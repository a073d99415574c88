"""The default-model cache: train once, verify after, retrain a stale or tampered default."""

import json

import pytest

from inkdiag_core import ModelFileError, load_detector
from inkdiag_core.fdi import train_default_model
from inkdiag_core.model_cache import main as model_cache_main
from inkdiag_ros.model_cache import default_config, ensure_default_model


def _config(path):
    return json.loads(open(str(path) + ".manifest.json").read())["config"]


def test_stale_default_is_retrained_a_users_model_is_not(tmp_path):
    logs = []
    default = tmp_path / "fdi_default.joblib"
    train_default_model(default, n_per_class=30)  # a default trained with other settings
    assert ensure_default_model(default, progress=False, log=logs.append) == default
    assert "n_per_class=30, now 400" in logs[-1] and "retraining" in logs[-1]
    cfg = _config(default)
    assert {k: cfg[k] for k in default_config()} == default_config()
    detector = load_detector(default)  # one file, both branches, thresholds inside
    assert detector.baseline_pipeline_ is not None and cfg["baseline"] is True
    assert detector.model_id == f"fdi-rf-kpi_y+baseline-{json.loads(open(str(default) + '.manifest.json').read())['sha256'][:12]}"
    mtime = default.stat().st_mtime_ns
    ensure_default_model(default, progress=False, log=logs.append)  # up to date: kept
    assert default.stat().st_mtime_ns == mtime and len(logs) == 1

    mine = tmp_path / "mine.joblib"
    train_default_model(mine, n_per_class=30, features="rich")
    ensure_default_model(mine, progress=False, log=logs.append)
    assert _config(mine)["n_per_class"] == 30 and len(logs) == 1
    mm = json.loads(open(str(mine) + ".manifest.json").read())  # a user's model that does not verify
    del mm["config"]["estimator"]
    open(str(mine) + ".manifest.json", "w").write(json.dumps(mm))
    before = mine.read_bytes()
    with pytest.raises(ModelFileError, match="not a FaultDetector file.*not retrained"):
        ensure_default_model(mine, progress=False, log=logs.append)
    assert mine.read_bytes() == before and len(logs) == 1  # never trained over
    assert model_cache_main([str(mine)]) == 2

    with open(default, "ab") as f:  # tampered: refused by its manifest, retrained
        f.write(b"\0")
    ensure_default_model(default, progress=False, log=logs.append)
    assert "unusable" in logs[-1] and "tampered" in logs[-1]
    assert ensure_default_model(default, progress=False, log=logs.append) == default  # verifies again

    mpath = str(default) + ".manifest.json"  # its manifest edited to say other than the model: as tampered
    m = json.loads(open(mpath).read())
    m["config"]["fd_threshold"] = 0.99
    open(mpath, "w").write(json.dumps(m))
    ensure_default_model(default, progress=False, log=logs.append)
    assert "unusable" in logs[-1] and "config.fd_threshold is 0.99" in logs[-1] and "retraining" in logs[-1]
    load_detector(default)  # retrained: loads as the fdi node loads it


def test_a_default_from_before_max_features_is_retrained(tmp_path, monkeypatch):
    import inkdiag_core.model_cache as cache

    default = tmp_path / "fdi_default.joblib"
    train_default_model(default, n_per_class=30, baseline=True)  # as the default (its manifest below is)
    manifest = json.loads(open(str(default) + ".manifest.json").read())
    manifest["config"] = {**manifest["config"], **{k: v for k, v in default_config().items() if k != "max_features"}}
    del manifest["config"]["max_features"]  # written before the setting: its forests used sqrt(7) KPIs per split
    open(str(default) + ".manifest.json", "w").write(json.dumps(manifest))
    calls, logs = [], []
    monkeypatch.setattr(cache, "train_default_model", lambda path, **kw: calls.append((path, kw)))
    ensure_default_model(default, progress=False, log=logs.append)
    assert len(calls) == 1 and logs == ["inkdiag: cached model trained with other settings than the default "
                                        "(max_features='sqrt', now None); retraining"]


@pytest.mark.parametrize("old", [1, 2])
def test_a_default_whose_open_set_layer_is_of_an_older_scores_version_is_retrained(tmp_path, monkeypatch, old):
    """A default from before the row-by-row scores (OPENSET_SCORES_VERSION 1), or whose class models are the
    robust cores of their rows (2), is retrained once."""
    import inkdiag_core.model_cache as cache
    from inkdiag_core import save_detector
    from inkdiag_core.openset import OPENSET_SCORES_VERSION

    default = tmp_path / "fdi_default.joblib"
    train_default_model(default, n_per_class=30, baseline=True)
    det = load_detector(default)
    for layer in (det.openset_, det.baseline_openset_):
        if old == 1:
            del layer.scores_version_  # as a layer pickled before the attribute
        else:
            layer.scores_version_ = old
    manifest = json.loads(open(str(default) + ".manifest.json").read())
    save_detector(det, default, config={k: v for k, v in default_config().items()
                                        if k not in det.get_params() and k not in ("baseline",)})
    m = json.loads(open(str(default) + ".manifest.json").read())
    m["config"] = {**manifest["config"], **default_config(), "fd_threshold": m["config"]["fd_threshold"]}
    calls, logs = [], []
    monkeypatch.setattr(cache, "train_default_model", lambda path, **kw: calls.append((path, kw)))
    stale = [k for k in default_config() if m["config"].get(k) != default_config()[k]]
    assert not stale
    open(str(default) + ".manifest.json", "w").write(json.dumps(m))
    ensure_default_model(default, progress=False, log=logs.append)
    assert len(calls) == 1 and f"open-set scores version={old}, now {OPENSET_SCORES_VERSION}" in logs[-1], logs


def test_a_users_model_with_an_older_open_set_layer_is_kept_or_refused_never_trained_over(tmp_path, monkeypatch):
    """Only the default file is retrained for its layer's versions: a user's model of scores version 2 labels as
    it was calibrated and is kept; one of older open-set features cannot label and is refused (ModelFileError)."""
    import inkdiag_core.model_cache as cache
    from inkdiag_core import save_detector

    mine = tmp_path / "mine.joblib"
    train_default_model(mine, n_per_class=30, baseline=True)
    calls, logs = [], []
    monkeypatch.setattr(cache, "train_default_model", lambda path, **kw: calls.append(path))
    det = load_detector(mine)
    for layer in (det.openset_, det.baseline_openset_):
        layer.scores_version_ = 2
    save_detector(det, mine)
    assert ensure_default_model(mine, progress=False, log=logs.append) == mine and not calls and not logs
    for layer in (det.openset_, det.baseline_openset_):
        layer.features_version_ = 1
    save_detector(det, mine)
    before = mine.read_bytes()
    with pytest.raises(ModelFileError, match="open-set layer was fitted on the features of an older inkdiag"):
        ensure_default_model(mine, progress=False, log=logs.append)
    assert not calls and not logs and mine.read_bytes() == before
