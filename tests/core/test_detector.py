"""FaultDetector: the whole FDI model (both branches, thresholds, identity) as one estimator."""

import json
import pickle
import warnings

import numpy as np
import pytest
from sklearn.base import clone
from sklearn.model_selection import train_test_split
from sklearn.pipeline import Pipeline
from sklearn.utils.estimator_checks import parametrize_with_checks

from inkdiag_core import (
    FaultClass,
    FaultDetector,
    ModelFileError,
    baseline_training_kpis,
    baseline_training_rows,
    label_frames,
    load_detector,
    load_model,
    make_fdi_pipeline,
    save_detector,
    save_model,
    simulate,
    with_baseline,
)
from inkdiag_core.fdi import classify, fd_labels, fnr_threshold, train_default_model

SEED = 3
N_PER_CLASS = 24

# Every generic check applies (the KPIs of scikit-learn's blob rows are features like any
# other): no expected failures.
@parametrize_with_checks([FaultDetector(n_estimators=5, min_samples_leaf=1)])
def test_fault_detector_follows_the_sklearn_contract(estimator, check):
    check(estimator)


@pytest.fixture(scope="module")
def sim():
    return simulate({c: N_PER_CLASS for c in FaultClass}, seed=SEED)


@pytest.fixture(scope="module")
def new():
    return simulate({c: 6 for c in FaultClass}, seed=SEED + 100)


def _old_route(X, y, seed, features="kpi_y"):
    """train_default_model before FaultDetector: split, pipeline, threshold (as it was written; the
    forest's splits choose from every feature, as the detector's do since max_features)."""
    Xtr, Xval, ytr, yval = train_test_split(X, y, test_size=0.25, random_state=seed, stratify=y)
    pipe = make_fdi_pipeline("rf", features, random_state=seed, n_estimators=50, min_samples_leaf=3,
                             max_features=None).fit(Xtr, ytr)
    labels0, _, p_faulty = classify(pipe, Xval, fd_threshold=0.5)
    is_fault = fd_labels(yval) == 1
    threshold = fnr_threshold(p_faulty[is_fault], 0.005)
    labels, _, _ = classify(pipe, Xval, fd_threshold=threshold)
    flagged = ~np.isin(labels, ("ok_signal", "healthy_nozzle"))
    scores = {"validation_fi_accuracy": float(np.mean(labels0 == yval)),
              "validation_fi_accuracy_at_threshold": float(np.mean(labels == yval)),
              "validation_fd_fnr": float(np.mean(~flagged[is_fault])),
              "validation_fd_fpr": float(np.mean(flagged[~is_fault])), "n_validation": int(len(yval))}
    return pipe, threshold, scores


@pytest.fixture(scope="module")
def fitted(sim):
    det = FaultDetector(random_state=SEED, sample_rate_hz=sim.sample_rate_hz)
    return det.fit(sim.traces, sim.label_values(), baseline_kpis=baseline_training_kpis(sim, SEED))


def test_both_branches_are_bit_identical_to_the_previous_training_route(sim, new, fitted):
    y = sim.label_values()
    pipe, threshold, scores = _old_route(sim.traces, y, SEED)
    assert fitted.fd_threshold_ == threshold and fitted.scores_ == scores
    labels, conf, p_faulty = classify(pipe, new.traces, fd_threshold=threshold)
    out = fitted.label(new.traces)
    np.testing.assert_array_equal(out.classes, labels)
    np.testing.assert_array_equal(out.confidence, conf)
    np.testing.assert_array_equal(out.p_faulty, p_faulty)
    assert not out.baseline.any()
    np.testing.assert_array_equal(fitted.predict(new.traces), labels)
    np.testing.assert_array_equal(fitted.predict_proba(new.traces), pipe.predict_proba(new.traces))
    assert list(fitted.classes_) == list(pipe.classes_)

    bpipe, bthreshold, bscores = _old_route(baseline_training_rows(sim, SEED), y, SEED, "kpi_y+baseline")
    assert fitted.baseline_fd_threshold_ == bthreshold and fitted.baseline_scores_ == bscores
    base = baseline_training_kpis(new, SEED + 100)
    blabels, bconf, bp = classify(bpipe, with_baseline(new.traces, base), fd_threshold=bthreshold)
    out = fitted.label(new.traces, baseline_kpis=base)
    assert out.baseline.all()
    np.testing.assert_array_equal(out.classes, blabels)
    np.testing.assert_array_equal(out.confidence, bconf)
    np.testing.assert_array_equal(out.p_faulty, bp)


def test_label_routes_each_row_by_its_baseline(new, fitted):
    base = baseline_training_kpis(new, SEED + 100)
    base[::3] = np.nan  # these nozzles have no recorded baseline
    out = fitted.label(new.traces, baseline_kpis=base)
    np.testing.assert_array_equal(out.baseline, np.isfinite(base).all(axis=1))
    plain = fitted.label(new.traces[::3])
    with_base = fitted.label(new.traces[out.baseline], baseline_kpis=base[out.baseline])
    np.testing.assert_array_equal(out.classes[::3], plain.classes)
    np.testing.assert_array_equal(out.p_faulty[out.baseline], with_base.p_faulty)
    np.testing.assert_array_equal(out.confidence[out.baseline], with_base.confidence)
    with pytest.raises(ValueError, match=r"baseline_kpis must be \(72, 7\)"):
        fitted.label(new.traces, baseline_kpis=base[:5])
    # A detector without the baseline branch labels every row with its plain branch.
    plain_only = clone(fitted).fit(new.traces, new.label_values())
    assert plain_only.baseline_pipeline_ is None
    assert not plain_only.label(new.traces, baseline_kpis=base).baseline.any()


def test_fit_refuses_bad_settings_and_baselines(sim):
    X, y = sim.traces[:48], sim.label_values()[:48]
    with pytest.raises(ValueError, match="give baselines to fit/label as baseline_kpis"):
        FaultDetector(features="kpi_y+baseline").fit(X, y)
    with pytest.raises(ValueError, match=r"fnr_target must be a real number in \[0, 1\)"):
        FaultDetector(fnr_target=1.0).fit(X, y)
    with pytest.raises(ValueError, match="baseline_kpis must be finite"):
        FaultDetector().fit(X, y, baseline_kpis=np.full((48, 7), np.nan))


def test_save_load_roundtrip_gives_the_same_detector_and_its_id(tmp_path, new, fitted):
    path = tmp_path / "det.joblib"
    assert fitted.model_id.endswith("-unsaved")
    mpath = save_detector(fitted, path, config={"n_per_class": N_PER_CLASS})
    manifest = json.loads(mpath.read_text())
    assert fitted.model_id == f"fdi-rf-kpi_y+baseline-{manifest['sha256'][:12]}"
    cfg = manifest["config"]
    assert {k: cfg[k] for k in fitted.get_params()} == fitted.get_params()
    assert cfg["estimator"] == "FaultDetector" and cfg["baseline"] is True and cfg["n_per_class"] == N_PER_CLASS
    assert cfg["fd_threshold"] == fitted.fd_threshold_ and cfg["baseline_fd_threshold"] == fitted.baseline_fd_threshold_
    assert (cfg["sample_rate_hz"], cfg["n_samples"]) == (fitted.sample_rate_hz, new.traces.shape[1])
    assert cfg["classes"] == [str(c) for c in fitted.classes_]
    assert manifest["scores"]["baseline_validation_fi_accuracy"] == fitted.baseline_scores_["validation_fi_accuracy"]

    loaded = load_detector(path)
    assert isinstance(loaded, FaultDetector) and loaded.model_id == fitted.model_id
    base = baseline_training_kpis(new, SEED + 100)
    base[1::2] = np.nan
    for a, b in zip(loaded.label(new.traces, baseline_kpis=base), fitted.label(new.traces, baseline_kpis=base)):
        np.testing.assert_array_equal(a, b)
    assert "file_sha256_" not in pickle.loads(pickle.dumps(loaded)).__dict__  # not inside a file
    assert clone(loaded).fit(new.traces, new.label_values()).model_id.endswith("-unsaved")

    # A detector file is still a model for the previous loaders: its plain branch's pipeline, which
    # label_frames screens per row, with its threshold in the manifest.
    model, m = load_model(path)
    assert isinstance(model, Pipeline)
    labels, _, _ = classify(model, new.traces, fd_threshold=m["config"]["fd_threshold"])
    np.testing.assert_array_equal(labels, fitted.predict(new.traces))
    X = new.traces.copy()
    X[4] *= 1e30
    frame = label_frames(model, [X], fd_threshold=m["config"]["fd_threshold"])[0]
    assert frame.reasons[4] == "non_finite_features" and frame.valid.sum() == len(X) - 1
    assert isinstance(load_model(path, as_pipeline=False)[0], FaultDetector)


def test_tampered_or_foreign_files_are_refused(tmp_path, fitted, sim):
    path = tmp_path / "det.joblib"
    save_detector(fitted, path)
    with open(path, "ab") as f:
        f.write(b"\0")
    with pytest.raises(ModelFileError, match="tampered"):
        load_detector(path)
    other = tmp_path / "pipe.joblib"
    save_model(make_fdi_pipeline(n_estimators=2).fit(sim.traces, sim.label_values()), other,
               config={"kind": "rf", "features": "kpi_y"})
    with pytest.raises(ModelFileError, match="not a FaultDetector file"):
        load_detector(other)
    with pytest.raises(ValueError, match="may not replace"):
        save_detector(fitted, tmp_path / "x.joblib", config={"fd_threshold": 0.1})


@pytest.mark.parametrize("edit, where", [
    (lambda m: m["config"].__setitem__("fd_threshold", 0.99), r"config\.fd_threshold is 0\.99"),
    (lambda m: m["config"]["classes"].reverse(), r"config\.classes\[0\]"),
    (lambda m: m["config"]["classes"].pop(), r"config\.classes is a list of 11, the model's a list of 12: manifest"),
    (lambda m: m["config"].__setitem__("profile_name", "h" * 70),
     r"config\.profile_name is \"h{59} \.\.\. \(12 characters more\), the model's"),
    (lambda m: m["config"].__setitem__("profile_name", "other_head"), r"config\.profile_name"),
    (lambda m: m["scores"].__setitem__(sorted(m["scores"])[0], 1.5), r"scores\."),
    (lambda m: m["scores"].__setitem__("fi_accuracy_claimed", 1.0), r"scores \['fi_accuracy_claimed'\]"),
])
def test_a_manifest_edited_to_say_other_than_its_model_is_refused(tmp_path, fitted, edit, where):
    """The file's sha256 covers the model, not its manifest: the manifest's own entries (the threshold,
    classes, head, scores a user reads there) must still be the model's, else the file is refused."""
    path = tmp_path / "det.joblib"
    save_detector(fitted, path, config={"note": "kept"})
    mpath = tmp_path / "det.joblib.manifest.json"
    m = json.loads(mpath.read_text())
    m["config"]["note"] = "an entry of the caller's may change"
    mpath.write_text(json.dumps(m))
    assert load_detector(path).fd_threshold_ == fitted.fd_threshold_
    edit(m)
    mpath.write_text(json.dumps(m))
    with pytest.raises(ModelFileError, match=where):
        load_detector(path)


def test_train_default_model_saves_a_detector_as_the_previous_route_trained_it(tmp_path, sim):
    path = tmp_path / "fdi.joblib"
    train_default_model(path, n_per_class=N_PER_CLASS, seed=SEED, baseline=True)
    det = load_detector(path)
    pipe, threshold, scores = _old_route(sim.traces, sim.label_values(), SEED)
    assert det.fd_threshold_ == threshold and det.scores_ == scores
    np.testing.assert_array_equal(det.predict(sim.traces), classify(pipe, sim.traces, fd_threshold=threshold)[0])
    assert det.baseline_pipeline_ is not None
    cfg = json.loads((tmp_path / "fdi.joblib.manifest.json").read_text())["config"]
    assert (cfg["n_per_class"], cfg["seed"], cfg["random_state"]) == (N_PER_CLASS, SEED, SEED)


def test_a_row_whose_features_overflow_costs_only_itself(new, fitted):
    X = new.traces.copy()
    X[[2, 9]] *= 1e30  # finite samples whose energy overflows float32 features
    base = baseline_training_kpis(new, SEED + 100)
    base[1::2] = np.nan  # row 9 plain, row 2 through the baseline branch
    out = fitted.label(X, baseline_kpis=base)
    assert list(np.flatnonzero(~out.valid)) == [2, 9]
    assert out.classes[2] is None and np.isnan(out.confidence[[2, 9]]).all() and np.isnan(out.p_faulty[[2, 9]]).all()
    keep = out.valid
    ref = fitted.label(new.traces[keep], baseline_kpis=base[keep])
    for a, b in zip(out, ref):
        np.testing.assert_array_equal(a[keep], b)
    with pytest.raises(ValueError, match="2 of 72 rows have non-finite features"):
        fitted.predict(X)


def test_label_skips_sklearn_checks_for_checked_arrays_with_the_same_result(new, fitted):
    """The hot path (issue 17): a finite float ndarray of the fitted width skips scikit-learn's input
    checks (about as costly as the KPIs of a few traces); every other input still gets them."""
    from inkdiag_core.kpis import extract_kpis, kpis_of_checked

    base = baseline_training_kpis(new, SEED + 100)
    base[::3] = np.nan
    X = np.asarray(new.traces, dtype=np.float64)
    fast = fitted.label(X, baseline_kpis=base)
    slow = fitted.label(X.tolist(), baseline_kpis=base)  # a list: validate_data's route
    for field in ("classes", "confidence", "p_faulty", "baseline", "valid", "unknown_score"):
        np.testing.assert_array_equal(getattr(fast, field), getattr(slow, field), err_msg=field)
    fortran = fitted.label(np.asfortranarray(X), baseline_kpis=base)  # any layout, the same features
    np.testing.assert_array_equal(fortran.confidence, fast.confidence)
    for Y in (X.astype(np.float32), np.asfortranarray(X[:5])):
        np.testing.assert_array_equal(kpis_of_checked(Y, 10e6), extract_kpis(Y, 10e6))
    bad = X.copy()
    bad[4, 10] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        fitted.label(bad)
    with pytest.raises(ValueError, match="features"):
        fitted.label(X[:, :-1])


def test_a_file_from_before_max_features_reads_as_sqrt_and_numpy_settings_save(tmp_path, sim, new, fitted):
    state = fitted.__getstate__()
    state.pop("max_features")  # pickled before the parameter: its forests chose from sqrt(n) features
    old = FaultDetector.__new__(FaultDetector)
    old.__setstate__(state)
    assert old.get_params()["max_features"] == "sqrt" and fitted.get_params()["max_features"] is None
    np.testing.assert_array_equal(old.label(new.traces).classes, fitted.label(new.traces).classes)
    det = FaultDetector(n_estimators=3, max_features=np.int64(3), min_samples_leaf=np.int64(3), unknown_rate=None,
                        sample_rate_hz=sim.sample_rate_hz).fit(sim.traces, sim.label_values())
    cfg = json.loads(save_detector(det, tmp_path / "np.joblib").read_text())["config"]
    assert (cfg["max_features"], cfg["min_samples_leaf"]) == (3, 3)
    assert {t.max_features_ for t in det.pipeline_[-1].estimators_} == {3}


def test_a_knn_rows_non_finite_baseline_feature_costs_only_itself(new):
    """A relative feature that overflows (a baseline KPI of exactly -1e-30: k / 0) in a knn detector's
    baseline branch: its scaler refuses non-finite rows, so the row is left out before it, not the call."""
    from inkdiag_core import FaultDetector

    sim = simulate({c: 24 for c in FaultClass}, seed=SEED + 5)
    det = FaultDetector(kind="knn", random_state=SEED).fit(sim.traces, sim.label_values(),
                                                          baseline_kpis=baseline_training_kpis(sim, SEED + 5))
    base = baseline_training_kpis(new, SEED + 100)
    base[4, 1] = -1e-30
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the overflow is expected: no floating-point warning either
        out = det.label(new.traces, baseline_kpis=base)
    assert list(np.flatnonzero(~out.valid)) == [4]
    keep = out.valid
    ref = det.label(new.traces[keep], baseline_kpis=base[keep])
    for a, b in zip(out, ref):
        np.testing.assert_array_equal(a[keep], b)
