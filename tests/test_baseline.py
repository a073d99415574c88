"""Per-nozzle healthy baselines: twins, baseline KPIs, the baseline feature set."""

import numpy as np
import pytest
from sklearn.utils.estimator_checks import parametrize_with_checks

from inkdiag_core import (
    KPI_NAMES,
    BaselineKpis,
    FaultClass,
    baseline_kpis,
    healthy_twin_frames,
    make_fdi_pipeline,
    simulate,
    with_baseline,
)

FS = 10e6


# scikit-learn's generic checks feed 2-5 columns; a BaselineKpis row is a trace plus the 7
# baseline KPIs (>= 9 columns), so the checks that fit on such narrow data are expected to
# fail on the column count (validate_data's ValueError), and the contract is tested below
# on real rows instead.
_NARROW = ("check_fit_score_takes_y", "check_estimators_overwrite_params", "check_dont_overwrite_parameters",
           "check_estimators_fit_returns_self", "check_readonly_memmap_input",
           "check_n_features_in_after_fitting", "check_positive_only_tag_during_fit",
           "check_estimators_dtypes", "check_pipeline_consistency", "check_estimators_nan_inf",
           "check_estimators_pickle", "check_f_contiguous_array_estimator",
           "check_transformer_data_not_an_array", "check_transformer_general",
           "check_transformer_preserve_dtypes", "check_methods_sample_order_invariance",
           "check_methods_subset_invariance", "check_dict_unchanged", "check_fit_idempotent",
           "check_fit_check_is_fitted", "check_n_features_in", "check_fit2d_predict1d")


@parametrize_with_checks([BaselineKpis()], expected_failed_checks=lambda est: {
    c: "needs >= 9 columns (a trace plus 7 baseline KPIs)" for c in _NARROW})
def test_baseline_kpis_follows_the_sklearn_contract(estimator, check):
    check(estimator)


def test_baseline_kpis_contract_on_real_rows():
    import pickle

    from sklearn.base import clone

    sim = simulate({FaultClass.HEALTHY_NOZZLE: 5, FaultClass.FULLY_BLOCKED: 5}, seed=6)
    _, frames = healthy_twin_frames(10, seed=6, n_frames=2, noise_std_v=sim.noise_std_v)
    X = with_baseline(sim.traces, baseline_kpis(frames, FS))
    est = BaselineKpis(FS)
    assert est.fit(X) is est and est.n_features_in_ == X.shape[1]
    F = est.transform(X)
    np.testing.assert_array_equal(pickle.loads(pickle.dumps(est)).transform(X), F)
    np.testing.assert_array_equal(clone(est).fit(X[::-1]).transform(X[::-1]), F[::-1])  # per row
    np.testing.assert_array_equal(est.transform(X[3:7]), F[3:7])
    assert list(est.get_feature_names_out()) == list(KPI_NAMES) + [
        "frequency_ratio", "damping_ratio_difference", "damping_ratio_ratio", "amplitude_ratio",
        "energy_ratio", "phase_difference_rad"]
    with pytest.raises(ValueError, match="features"):
        est.transform(X[:, :-1])
    bad = X.copy()
    bad[2, 5] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        est.transform(bad)


def test_twins_are_the_same_nozzles_healthy_with_their_own_noise():
    counts = {FaultClass.DEEPLY_DRIED: 5, FaultClass.FULLY_BLOCKED: 3}
    sim = simulate(counts, seed=4)
    twins, frames = healthy_twin_frames(8, seed=4, n_frames=3, noise_std_v=sim.noise_std_v)
    for name in ("r_n", "L_n", "r_r", "B_act", "b"):
        np.testing.assert_array_equal(twins.params[name], sim.params[name])
    assert set(twins.label_values()) == {"healthy_nozzle"}
    assert np.all(twins.params["temperature_k"] == twins.params["temperature_k"][0])
    assert frames.shape == (8, 3, sim.traces.shape[1]) and frames.dtype == np.float32
    d = frames[:, 0] - frames[:, 1]
    assert 0.5 * sim.noise_std_v < np.std(d) / np.sqrt(2) < 2 * sim.noise_std_v
    with pytest.raises(ValueError, match="n_frames must be >= 1"):
        healthy_twin_frames(8, seed=4, n_frames=0, noise_std_v=0.01)


def test_baseline_features_are_relative_to_the_nozzle():
    sim = simulate({FaultClass.HEALTHY_NOZZLE: 6, FaultClass.DEEPLY_DRIED: 6}, seed=1)
    _, frames = healthy_twin_frames(12, seed=1, n_frames=4, noise_std_v=sim.noise_std_v)
    base = baseline_kpis(frames, FS)
    assert base.shape == (12, len(KPI_NAMES))
    F = BaselineKpis(FS).fit_transform(with_baseline(sim.traces, base))
    assert F.shape == (12, 13)
    ratio = F[:, 7]  # frequency relative to the nozzle's own healthy frequency
    assert np.all(np.abs(ratio[:6] - 1) < 0.03)  # healthy: itself (up to temperature and noise)
    assert np.all(ratio[6:] < 0.85)  # deeply dried: clearly lower than its own healthy mode
    with pytest.raises(ValueError, match=r"baseline \(n, 7\)"):
        with_baseline(sim.traces, base[:3])
    with pytest.raises(ValueError, match="n_frames >= 1"):
        baseline_kpis(frames[:, 0], FS)


def test_baseline_pipeline_separates_the_dried_classes():
    counts = {c: 40 for c in (FaultClass.HEALTHY_NOZZLE, FaultClass.SLIGHTLY_DRIED,
                              FaultClass.INTERMEDIATELY_DRIED, FaultClass.DEEPLY_DRIED)}
    sim = simulate(counts, seed=2)
    _, frames = healthy_twin_frames(len(sim), seed=2, n_frames=4, noise_std_v=sim.noise_std_v)
    X = with_baseline(sim.traces, baseline_kpis(frames, FS))
    y = sim.label_values()
    idx = np.random.default_rng(0).permutation(len(y))
    tr, te = idx[:100], idx[100:]
    pipe = make_fdi_pipeline("rf", "kpi_y+baseline").fit(X[tr], y[tr])
    assert (pipe.predict(X[te]) == y[te]).mean() > 0.8
