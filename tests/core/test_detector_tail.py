"""FaultDetector.label's compiled tail (_kernels.detector_tail) labels as the numpy loop it replaces."""

import copy

import numpy as np
import pytest

from inkdiag_core import FaultClass, FaultDetector, HeadProfile, _kernels, baseline_training_kpis, simulate

SEED = 21


@pytest.fixture(scope="module")
def data():
    sim = simulate({c: 80 for c in FaultClass}, seed=SEED)
    return sim, baseline_training_kpis(sim, SEED)


@pytest.fixture(scope="module")
def detector(data):
    """Both branches and an open-set layer that can say unknown (60 calibration rows per class: rate 0.05)."""
    sim, base = data
    return FaultDetector(n_estimators=20, unknown_rate=0.05, random_state=SEED).fit(sim.traces, sim.label_values(),
                                                                                    baseline_kpis=base)


@pytest.fixture(scope="module")
def rows():
    """Every class, new nozzles, some rows far outside every class (unknown), some too weak for the open-set layer
    to judge (never unknown), one whose energy overflows float32."""
    sim = simulate({c: 12 for c in FaultClass}, seed=SEED + 1)
    base = baseline_training_kpis(sim, SEED + 1)
    x = sim.traces.astype(np.float32)
    rng = np.random.default_rng(SEED)
    odd = x[:6] * rng.uniform(4.0, 9.0, (6, 1)).astype(np.float32)  # far too strong: unlike every class
    huge = x[6:8] * np.float32(1e30)  # its KPI energy (~1e54 V^2 s) is not finite in float32: not classified
    weak = np.concatenate([x[9:11] * np.float32(0.01), rng.normal(0.0, 0.006, (2, x.shape[1])).astype(np.float32)])
    x = np.concatenate([x, odd, weak, x[8:9], huge])
    zero = base[8:9].copy()
    zero[0, 1] = -1e-30  # a frequency ratio of k / 0: infinite, the row not classified (and no other lost)
    base = np.concatenate([base, base[:6], base[9:13], zero, base[6:8]])
    base[::3] = np.nan  # a third of the rows have no baseline: the plain branch
    base[-3], base[-2] = zero[0], base[7]  # the zero baseline and one overflowing trace on the baseline branch,
    base[-1] = np.nan  # the other on the plain one
    return x, base


#: The rows of ``rows`` that are not classified: the zero baseline, the two overflowing traces.
BAD = [-3, -2, -1]
#: The rows of ``rows`` too weak for the open-set layer to judge.
WEAK = slice(-7, -3)


@pytest.fixture
def tail_calls(monkeypatch):
    """The row count of every compiled tail call (the kernel still runs)."""
    calls = []
    kernel = _kernels.detector_tail
    monkeypatch.setattr(_kernels, "detector_tail", lambda *a, **k: calls.append(len(a[0])) or kernel(*a, **k))
    return calls


def _label(det, x, base, tail: bool, monkeypatch):
    with monkeypatch.context() as m:
        if not tail:
            m.setattr(FaultDetector, "_label_tail", lambda *a, **k: None)
        return det.label(x, baseline_kpis=base)


def _assert_same(a, b):
    for name, x, y in zip(a._fields, a, b):
        assert x.dtype == y.dtype, name
        assert np.array_equal(x, y, equal_nan=x.dtype.kind == "f"), (name, np.flatnonzero(x != y)[:10])


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_the_tail_labels_every_row_as_the_numpy_loop(detector, rows, dtype, monkeypatch, tail_calls):
    x, base = rows
    x = x.astype(dtype)
    plain = np.isnan(base).any(1)
    fast = _label(detector, x, base, True, monkeypatch)
    assert sorted(tail_calls) == sorted([int(plain.sum()), int((~plain).sum())])
    slow = _label(detector, x, base, False, monkeypatch)
    _assert_same(fast, slow)
    assert (fast.classes[plain] == "unknown").sum() >= 2 and (fast.classes[~plain] == "unknown").sum() >= 2
    ok = np.ones(len(x), bool)
    ok[BAD] = False
    np.testing.assert_array_equal(fast.valid, ok)  # the bad rows alone are left out, on both branches
    assert np.isfinite(fast.unknown_score[ok]).all()
    assert (fast.classes[WEAK] == "unknown").all()  # weak, and no class of the default head ever is
    many, many_base = np.concatenate([x] * 4), np.concatenate([base] * 4)  # > 256 rows a branch: one call still
    _assert_same(_label(detector, many, many_base, True, monkeypatch),
                 _label(detector, many, many_base, False, monkeypatch))
    assert max(tail_calls) > 256


def test_a_row_labelled_alone_or_with_others_gets_the_same_bits(detector, rows, monkeypatch, tail_calls):
    """One row, one good row and bad ones, the whole batch: a row's labels and unknown score do not depend on
    the rows labelled with it, by the tail and by the loop (the scores are computed row by row)."""
    x, base = rows
    whole = detector.label(x, baseline_kpis=base)
    picks = [[i] for i in (0, 1, 2, len(x) - 4)] + [[1, BAD[0], BAD[1]], [0, BAD[2]]]
    for tail in (True, False):
        for at in picks:
            got = _label(detector, x[at], base[at], tail, monkeypatch)
            _assert_same(got, type(got)(*(f[at] for f in whole)))
    assert 1 in tail_calls


def test_without_an_open_set_layer_the_labels_are_the_loops(data, rows, monkeypatch, tail_calls):
    sim, bk = data
    det = FaultDetector(n_estimators=10, unknown_rate=None, random_state=SEED).fit(sim.traces, sim.label_values(),
                                                                                  baseline_kpis=bk)
    x, base = rows
    _assert_same(_label(det, x, base, True, monkeypatch), _label(det, x, base, False, monkeypatch))
    assert len(tail_calls) == 2
    assert np.isnan(det.label(x, baseline_kpis=base).unknown_score).all()


def test_a_detector_the_tail_does_not_cover_labels_by_the_loop(data, rows, monkeypatch):
    """KNN, the rich features: no compiled call; the loop labels them as before."""
    sim, bk = data
    x, base = rows
    called = []
    monkeypatch.setattr(_kernels, "detector_tail", lambda *a, **k: called.append(1))
    for det in (FaultDetector(kind="knn", random_state=SEED).fit(sim.traces, sim.label_values(), baseline_kpis=bk),
                FaultDetector(features="rich", n_estimators=5, random_state=SEED).fit(sim.traces, sim.label_values())):
        got = det.label(x[:-3], baseline_kpis=base[:-3])
        assert got.valid.all() and not called


def test_the_layers_scores_of_a_row_do_not_depend_on_its_batch(detector, rows):
    x, base = rows
    use = ~np.isnan(base).any(1)
    use[BAD] = False
    feats = detector.baseline_pipeline_[0]._features_of(x[use], base[use])
    F = detector._openset_features(feats, x[use], True)
    layer = detector.baseline_openset_
    S = layer.scores(F)
    for i in range(len(F)):
        np.testing.assert_array_equal(layer.scores(F[i:i + 1])[0], S[i])
    np.testing.assert_array_equal(layer.scores(F[::7]), S[::7])


def test_detector_tail_refuses_mismatched_shapes():
    forest = (np.zeros(1, np.int64), np.full((1, 4), -1, np.int32), np.zeros(1), np.ones((1, 2)))
    with pytest.raises(ValueError, match="detector_tail"):
        _kernels.detector_tail(np.ones((2, 7)), np.ones((3, 7)), np.zeros((2, 8), np.float32), 1.0, forest,
                               np.array([True, False]), 0.5, None, eps=1e-30)


def test_weak_rows_are_judged_by_their_weakness_on_either_path(detector, rows, monkeypatch):
    """A row whose sinusoid is below SNR_FLOOR noise sigmas (noise_v_, estimated from the healthy training traces) is
    weak: against the chosen class's weak calibration rows. No class of the default head is ever weak, so it is
    unknown (P(faulty) 1), on the tail and on the loop alike; with classes that are weak in a share of their rows
    the classifier's class stands."""
    from inkdiag_core.openset import SNR_FLOOR

    assert detector.openset_.noise_v_ == pytest.approx(HeadProfile.default().noise_std_v(), rel=0.05)
    x, base = rows
    weak = WEAK
    amp = np.exp(detector._openset_features(detector.pipeline_[0].transform(x[weak]), x[weak], False)[:, 2])
    assert (amp < SNR_FLOOR * detector.openset_.noise_v_).all()
    for layer in (detector.openset_, detector.baseline_openset_):
        assert (layer.weak_q_ <= layer.rate).all()
    for tail in (True, False):
        out = _label(detector, x[weak], base[weak], tail, monkeypatch)
        assert (out.classes == "unknown").all() and (out.p_faulty == 1.0).all() and out.valid.all()
    accepting = copy.deepcopy(detector)
    for layer in (accepting.openset_, accepting.baseline_openset_):
        layer.weak_q_ = np.ones_like(layer.weak_q_)  # every class weak in many of its rows: the classifier's class
        layer.__dict__.pop("_tail", None)
    fast, slow = (_label(accepting, x[weak], base[weak], tail, monkeypatch) for tail in (True, False))
    _assert_same(fast, slow)
    assert "unknown" not in fast.classes.tolist() and (fast.unknown_score == 0.0).all()
    before, chosen = fast.classes.copy(), fast.classes[0]  # that class never weak: a weak row chosen as it is unknown
    for layer in (accepting.openset_, accepting.baseline_openset_):
        layer.weak_q_ = np.where(layer.classes_ == chosen, 0.0, 1.0)
    fast, slow = (_label(accepting, x[weak], base[weak], tail, monkeypatch) for tail in (True, False))
    _assert_same(fast, slow)
    assert ((fast.classes == "unknown") == (before == chosen)).all() and fast.classes[0] == "unknown"
