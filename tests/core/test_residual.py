"""Residual filters and FDI pipelines (thesis 3.3-3.4)."""

import numpy as np
import pytest
from sklearn.utils.estimator_checks import parametrize_with_checks

from inkdiag_core import InkChannelModel
from inkdiag_core.fdi import BandEnergies, RawTraceFeatures, SecondModeKpis, fd_labels, make_fdi_pipeline
from inkdiag_core.kpis import extract_kpis
from inkdiag_core.residual import MODIFIED_BANDS_HZ, ResidualFilter, design_residual_filter

FS = 10e6


def healthy_traces(n, seed=0, n_samples=512):
    """Free responses of the healthy model from random initial states (independent path)."""
    rng = np.random.default_rng(seed)
    m = InkChannelModel()
    out = np.empty((n, n_samples))
    for i in range(n):
        x0 = np.array([rng.normal(0, 1e-12), rng.normal(1e-6, 2e-7), rng.normal(1e-6, 2e-7)])
        out[i] = m.free_response(x0, n_samples, FS)
    return out / np.abs(out).max()


def damped(f_hz, zeta, n, seed, n_samples=512):
    rng = np.random.default_rng(seed)
    t = np.arange(n_samples) / FS
    w0 = 2 * np.pi * f_hz / np.sqrt(1 - zeta**2)
    amp = rng.uniform(0.5, 1.5, (n, 1))
    phase = rng.uniform(-0.3, 0.3, (n, 1))  # the drive fixes the phase up to small spreads
    y = amp * np.exp(-zeta * w0 * t) * np.cos(2 * np.pi * f_hz * t + phase)
    return y + 0.005 * rng.standard_normal(y.shape)


@pytest.mark.parametrize("kind", ["original", "modified"])
def test_filters_are_stable_with_positive_margins(kind):
    d = design_residual_filter(kind)
    assert d.is_stable and np.all(np.abs(d.poles) < 1)
    assert np.all(d.poles_hz.real < 0)  # left half plane
    m = d.margins()
    assert m["phase_margin_deg"] > 30 and m["gain_margin_db"] > 0


def test_modified_filter_keeps_its_three_bands_and_rejects_dc():
    orig, mod = design_residual_filter("original"), design_residual_filter("modified")
    f = np.array(MODIFIED_BANDS_HZ)
    assert np.all(np.abs(mod.frequency_response(f)) > np.abs(orig.frequency_response(f)))
    assert abs(mod.frequency_response([1.0])[0]) < 0.01  # PI action: offsets do not pass
    with pytest.raises(ValueError, match="kind"):
        design_residual_filter("bogus")
    with pytest.raises(ValueError, match="twice the highest band"):
        design_residual_filter("modified", sample_rate_hz=2e6)


def test_healthy_residual_is_small_and_faulty_is_not():
    y_h = healthy_traces(20, seed=1)
    rf = ResidualFilter("original").fit(y_h)
    r_h = rf.transform(y_h)
    y_f = damped(2124e3, 0.05, 20, seed=2)
    r_f = rf.transform(y_f)
    e = lambda a: np.sum(a[:, 100:] ** 2, axis=1)  # after the observer transient
    assert np.median(e(r_h) / e(y_h)) < 0.05
    assert np.median(e(r_f) / e(y_f)) > 0.5


def test_residual_loses_the_empty_channel_frequency_and_modified_keeps_it():
    """Thesis Table 11: the residual's dominant peak moves to the healthy band."""
    y = damped(2124e3, 0.03, 30, seed=3) + 0.5 * healthy_traces(30, seed=4)
    r = ResidualFilter("modified").fit(healthy_traces(10)).transform(y)
    assert np.median(extract_kpis(r, FS)[:, 1]) == pytest.approx(2124e3, rel=0.02)


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
