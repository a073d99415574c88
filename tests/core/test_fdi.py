"""FDI pipelines (thesis 3.4)."""

import numpy as np
import pytest
from sklearn.utils.estimator_checks import parametrize_with_checks

from _helpers import FS, damped
from inkdiag_core.fdi import BandEnergies, RawTraceFeatures, SecondModeKpis, fd_labels, make_fdi_pipeline
from inkdiag_core.kpis import extract_kpis
from inkdiag_core.residual import ResidualFilter


@parametrize_with_checks([SecondModeKpis(), BandEnergies(), RawTraceFeatures(), ResidualFilter("original"), ResidualFilter("modified")])
def test_feature_transformers_follow_the_sklearn_contract(estimator, check):
    check(estimator)


def test_fd_labels_count_both_healthy_classes_as_healthy():
    assert fd_labels(["ok_signal", "healthy_nozzle", "deeply_dried"]).tolist() == [0, 0, 1]


@pytest.mark.parametrize("kind", ["rf", "knn"])
@pytest.mark.parametrize("features", ["kpi_y", "kpi_r", "kpi_r_modified", "kpi_y+r_modified", "rich"])
def test_pipelines_learn_frequency_classes(kind, features):
    freqs = {"a": 190e3, "b": 237e3, "c": 357e3, "d": 2124e3}
    zetas = (0.12, 0.07, 0.04, 0.02)  # classes differ in frequency and damping, as faults do
    X = np.vstack([damped(f, z, 40, seed=i) for i, (f, z) in enumerate(zip(freqs.values(), zetas))])
    y = np.repeat(list(freqs), 40)
    rng = np.random.default_rng(0)
    idx = rng.permutation(len(y))
    train, test = idx[:100], idx[100:]
    pipe = make_fdi_pipeline(kind, features).fit(X[train], y[train])
    assert (pipe.predict(X[test]) == y[test]).mean() > 0.8
    assert set(pipe.classes_) == set(freqs)


def test_pipeline_arguments_are_checked():
    with pytest.raises(ValueError, match="kind"):
        make_fdi_pipeline("svm")
    with pytest.raises(ValueError, match="features"):
        make_fdi_pipeline("rf", "everything")


def test_default_model_trains_saves_and_classifies(tmp_path):
    from inkdiag_core import load_model, simulate
    from inkdiag_core.fdi import classify, train_default_model

    steps = []
    manifest = train_default_model(tmp_path / "fdi.joblib", n_per_class=40, seed=1,
                                   progress=lambda s, t, m: steps.append(s))
    assert steps == [1, 2, 3, 4] and manifest.is_file()
    pipe, info = load_model(tmp_path / "fdi.joblib")
    assert 0 < info["config"]["fd_threshold"] <= 0.5
    assert info["scores"]["validation_fi_accuracy"] > 0.7  # 12 classes: chance is 0.08
    sim = simulate({"deeply_dried": 20, "healthy_nozzle": 20, "empty_channel_1": 20}, seed=9)
    labels, conf, p_faulty = classify(pipe, sim.traces, fd_threshold=info["config"]["fd_threshold"])
    assert np.mean(labels == sim.label_values()) > 0.8
    assert np.all((conf > 0) & (conf <= 1)) and np.all((p_faulty >= 0) & (p_faulty <= 1))
    # a lower threshold never turns a faulty verdict healthy
    labels_low, _, _ = classify(pipe, sim.traces, fd_threshold=0.05)
    healthy = np.isin(labels, ["ok_signal", "healthy_nozzle"])
    assert np.all(~np.isin(labels_low[~healthy], ["ok_signal", "healthy_nozzle"]))
    with pytest.raises(ValueError, match="fd_threshold"):
        classify(pipe, sim.traces, fd_threshold=0)


def test_fnr_threshold_misses_at_most_the_target():
    from inkdiag_core.fdi import fnr_threshold

    p = np.linspace(0.01, 1.0, 1000)
    t = fnr_threshold(p, 0.005)
    assert np.mean(p < t) <= 0.005 and t <= 0.5


def test_raw_trace_features_are_the_three_parts_side_by_side():
    X = damped(300e3, 0.05, 6, seed=5) + 0.3 * damped(1.2e6, 0.02, 6, seed=6)
    both = RawTraceFeatures().fit(X).transform(X)
    parts = np.hstack([extract_kpis(X, FS), SecondModeKpis().fit(X).transform(X), BandEnergies().fit(X).transform(X)])
    np.testing.assert_allclose(both, parts)
    assert len(RawTraceFeatures().fit(X).get_feature_names_out()) == both.shape[1]
    assert np.median(both[:, 7]) == pytest.approx(1.2e6, rel=0.02)  # the second mode is found


def test_forest_predict_proba_is_bit_identical_to_sklearn_and_checks_input():
    from sklearn.ensemble import RandomForestClassifier

    from inkdiag_core.fdi import fault_probability, forest_predict_proba

    rng = np.random.default_rng(0)
    X = rng.normal(size=(300, 7))
    y = np.array(["a", "b", "c"])[(X[:, 0] > 0).astype(int) + (X[:, 1] > 1)]
    rf = RandomForestClassifier(n_estimators=17, random_state=0).fit(X, y)
    Xt = rng.normal(size=(50, 7))
    np.testing.assert_array_equal(forest_predict_proba(rf, Xt), rf.predict_proba(Xt))
    with pytest.raises(ValueError, match=r"\(n, 7\)"):
        forest_predict_proba(rf, Xt[:, :5])
    with pytest.raises(ValueError, match="finite"):
        forest_predict_proba(rf, np.full((1, 7), np.nan))
    # through a whole FDI pipeline, as the nodes call it
    from inkdiag_core import FaultClass, simulate

    sim = simulate({FaultClass.HEALTHY_NOZZLE: 20, FaultClass.FULLY_BLOCKED: 20}, seed=1)
    pipe = make_fdi_pipeline("rf", "kpi_y", n_estimators=10).fit(sim.traces, sim.label_values())
    proba, _ = fault_probability(pipe, sim.traces[:9])
    np.testing.assert_array_equal(proba, pipe.predict_proba(sim.traces[:9]))


def test_forest_predict_proba_compiled_and_per_tree_paths_are_sklearns_and_a_refit_is_seen():
    """Both paths (the compiled walk up to _KERNEL_MAX_ROWS rows, one tree_.predict per tree beyond) give
    predict_proba bit for bit, with integer and string classes and deep trees; a refit forest (and one grown by
    warm_start, whose list of trees stays the same object) is flattened again."""
    from sklearn.ensemble import RandomForestClassifier

    from inkdiag_core import fdi

    rng = np.random.default_rng(3)
    X = rng.normal(size=(2000, 9)).astype(np.float32)
    y = (X[:, 0] * 3 + X[:, 1] ** 2 + rng.normal(size=2000)).round().astype(int) % 5
    rf = RandomForestClassifier(n_estimators=23, min_samples_leaf=1, random_state=0).fit(X, y)
    for n in (1, 7, fdi._KERNEL_MAX_ROWS, fdi._KERNEL_MAX_ROWS + 1, 1500):
        Xt = rng.normal(size=(n, 9))  # float64 in: the forest sees float32, as scikit-learn's
        np.testing.assert_array_equal(fdi.forest_predict_proba(rf, Xt), rf.predict_proba(Xt), err_msg=f"{n} rows")
    assert fdi.forest_predict_proba(rf, np.empty((0, 9))).shape == (0, 5)
    flat = fdi.flat_forest(rf)
    rf.fit(X[:500], np.array(["p", "q", "r"])[y[:500] % 3])  # the same object, new trees and classes
    assert fdi.flat_forest(rf) is not flat
    Xt = rng.normal(size=(40, 9))
    np.testing.assert_array_equal(fdi.forest_predict_proba(rf, Xt), rf.predict_proba(Xt))
    rf.set_params(warm_start=True, n_estimators=30).fit(X[:500], np.array(["p", "q", "r"])[y[:500] % 3])
    assert len(fdi.flat_forest(rf)[0]) == 30  # trees appended to the same list: flattened again
    np.testing.assert_array_equal(fdi.forest_predict_proba(rf, Xt), rf.predict_proba(Xt))
