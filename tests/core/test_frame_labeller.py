"""inkdiag_core.frame_labeller: FrameLabeller labels as the previous label_frames path, each frame isolated."""

import numpy as np
import pytest

from inkdiag_core import (
    BaselineModel,
    BaselineRecorder,
    FaultClass,
    FrameFailure,
    FrameInputError,
    FrameLabeller,
    FrameLabels,
    LabellerConfigError,
    NozzleBaselines,
    label_frames_isolated,
    load_detector,
    simulate_nozzles,
)

HEAD, N, FIRST = 31, 96, 200


@pytest.fixture(scope="module")
def detector(fdi_baseline_model):
    return load_detector(fdi_baseline_model)


@pytest.fixture(scope="module")
def baselines():
    """Baselines of nozzles FIRST .. FIRST+N-1 of a seeded head, without FIRST+40 .. FIRST+59."""
    rec = BaselineRecorder(n_frames=4)
    for k in range(4):
        rec.add(FIRST, simulate_nozzles(["healthy_nozzle"] * N, seed=HEAD, frame_seed=k).traces)
    b = rec.baselines()
    keep = (b.nozzle_ids < FIRST + 40) | (b.nozzle_ids >= FIRST + 60)
    return NozzleBaselines(b.nozzle_ids[keep], b.kpis[keep], b.sample_rate_hz, b.n_samples, b.n_frames)


def _head_frames():
    """A seeded head's frame of every class, in 4 nozzle ranges, with invalid and hostile rows."""
    classes = np.array(list(FaultClass), dtype=object)[np.arange(N) % 12]
    x = simulate_nozzles(classes, seed=HEAD, frame_seed=77).traces.astype(np.float32)
    x[3, 10] = np.nan  # non_finite
    x[20, :] = 0.25  # flat
    x[50, 7] = 50.0  # beyond max_abs_v: out_of_range
    cuts = [0, 30, 41, 70, N]
    return [x[a:b] for a, b in zip(cuts, cuts[1:])], [FIRST + a for a in cuts[:-1]]


def _previous(detector, frames, firsts, baselines=None, max_abs_v=10.0):
    """The labels of the previous fdi path: label_frames_isolated with the detector's loose pieces."""
    base = None if baselines is None else BaselineModel(detector.baseline_pipeline_, baselines,
                                                        detector.baseline_fd_threshold_)
    return label_frames_isolated(detector.pipeline_, frames, fd_threshold=detector.fd_threshold_,
                                 first_nozzles=firsts, baseline=base, max_abs_v=max_abs_v)


def _same(got, want):
    assert len(got) == len(want)
    for g, w in zip(got, want):
        assert isinstance(g, FrameLabels)
        assert list(g.classes) == list(w.classes) and list(g.reasons) == list(w.reasons)
        np.testing.assert_array_equal(g.confidence, w.confidence)  # bit-identical, NaN where invalid
        np.testing.assert_array_equal(g.valid, w.valid)
        np.testing.assert_array_equal(g.baseline, w.baseline)
        _codes_are_the_classes(g)


def _codes_are_the_classes(labels):
    """A FrameLabeller's class codes name each row's class (invalid rows: "") from distinct names."""
    names = labels.class_names
    assert labels.class_codes.dtype == np.uint8 and len(set(names)) == len(names) and names[0] == ""
    assert np.array(names, dtype=object)[labels.class_codes].tolist() == labels.classes.tolist()


@pytest.mark.parametrize("with_baselines", [False, True])
def test_labels_are_bit_identical_to_the_previous_path(detector, baselines, with_baselines):
    frames, firsts = _head_frames()
    b = baselines if with_baselines else None
    got = FrameLabeller(detector, b, sample_rate_hz=10e6, n_samples=512, max_abs_v=10.0).label(frames, firsts)
    _same(got, _previous(detector, frames, firsts, b))
    reasons = np.concatenate([g.reasons for g in got])
    assert reasons[3] == "non_finite" and reasons[20] == "flat" and reasons[50] == "out_of_range"
    used = np.concatenate([g.baseline for g in got])
    assert used.sum() == (N - 20 - 2 if with_baselines else 0)  # 20 nozzles without a baseline, 2 invalid
    assert not used[40:60].any()


def test_a_bad_frame_costs_only_itself(detector, baselines):
    frames, firsts = _head_frames()
    lab = FrameLabeller(detector, baselines, max_abs_v=10.0)
    bad = [frames[0], np.zeros(512, np.float32), frames[1][:, :256], frames[2]]
    got = lab.label(bad, [firsts[0], 0, firsts[1], firsts[2]])
    assert [type(g).__name__ for g in got] == ["FrameLabels", "FrameFailure", "FrameFailure", "FrameLabels"]
    assert got[1].frame_index == 1 and isinstance(got[1].error, FrameInputError)
    assert isinstance(got[2].error, ValueError) and "(n, 512)" in got[2].why
    _same([got[0], got[3]], _previous(detector, [frames[0], frames[2]], [firsts[0], firsts[2]], baselines))


def test_a_frame_the_detector_refuses_fails_alone(detector, monkeypatch):
    frames, firsts = _head_frames()
    lab = FrameLabeller(detector, max_abs_v=10.0)
    real = type(detector).label

    def refuse_frame_two(self, X, **kw):  # the batch and frame 2 alone raise; the others label
        if any(np.array_equal(r, frames[2][0]) for r in np.asarray(X)[:1]) or len(X) > 60:
            raise RuntimeError("boom")
        return real(self, X, **kw)

    monkeypatch.setattr(type(detector), "label", refuse_frame_two)
    got = lab.label(frames, firsts)
    assert [isinstance(g, FrameFailure) for g in got] == [False, False, True, False]
    assert isinstance(got[2].error, RuntimeError) and got[2].why == "RuntimeError: boom"


def test_a_row_whose_features_overflow_is_invalid_not_its_frame(detector):
    frames, firsts = _head_frames()
    f = frames[0].astype(np.float64)
    f[5] = 1e30 * np.sign(np.sin(np.arange(512)) + 0.1)  # finite, but its energy overflows
    got = FrameLabeller(detector).label([f], [firsts[0]])[0]  # no max_abs_v: screening passes it
    assert got.reasons[5] == "non_finite_features" and not got.valid[5] and got.classes[5] == ""
    assert got.valid.sum() == f.shape[0] - 3  # and rows 3 (NaN) and 20 (flat)
    _same([got], _previous(detector, [f], [firsts[0]], max_abs_v=None))
    lab = FrameLabeller(detector)  # the same row in a later burst of a joint finish: its own frame's row 5 only
    other = frames[1].astype(np.float64)
    joint = lab.finish([lab.screen([other], [firsts[1]]), lab.screen([other, f], [firsts[1], firsts[0]])])
    _same([joint[0][0], joint[1][0], joint[1][1]], [lab.label([other], [firsts[1]])[0]] * 2 + [got])
    assert joint[1][1].reasons[5] == "non_finite_features" and joint[1][0].valid.all()


def test_compatibility_rules_are_typed_errors(detector, fdi_model, baselines):
    plain = load_detector(fdi_model)
    with pytest.raises(LabellerConfigError, match="the frames are 5000000 Hz"):
        FrameLabeller(detector, sample_rate_hz=5e6)
    with pytest.raises(LabellerConfigError, match="256"):
        FrameLabeller(detector, n_samples=256)
    other = NozzleBaselines(np.arange(3), np.ones((3, 7)), 10e6, 256, 4)
    with pytest.raises(LabellerConfigError, match="256 samples"):
        FrameLabeller(detector, other)
    with pytest.raises(LabellerConfigError, match="no baseline branch"):
        FrameLabeller(plain, baselines)
    with pytest.raises(LabellerConfigError, match="model_cache"):
        FrameLabeller(detector.pipeline_)
    assert issubclass(LabellerConfigError, ValueError) and issubclass(FrameInputError, ValueError)
    assert FrameLabeller(plain).model_id == plain.model_id and not FrameLabeller(plain).uses_baselines
    assert FrameLabeller(detector, baselines).model_id.startswith("fdi-rf-kpi_y+baseline-")


def test_results_pickle_for_the_labelling_process(detector, baselines):
    import pickle

    frames, firsts = _head_frames()
    lab = FrameLabeller(detector, baselines, max_abs_v=10.0)
    got = pickle.loads(pickle.dumps(lab)).label(frames + [np.zeros(3)], firsts + [0])
    _same(got[:-1], _previous(detector, frames, firsts, baselines))
    back = pickle.loads(pickle.dumps(got[-1]))
    assert isinstance(back, FrameFailure) and isinstance(back.error, FrameInputError) and back.frame_index == 4


def test_baselines_of_another_head_are_refused(detector, baselines):
    """The baselines carry the head they were recorded on; a model of another head refuses them."""
    import dataclasses

    from inkdiag_core import HeadProfile

    other = HeadProfile.default().replace(channel={"L_r": 1.3 * HeadProfile.default().channel["L_r"]})
    foreign = dataclasses.replace(baselines, head_sha256=other.sha256)
    with pytest.raises(LabellerConfigError, match="another head"):
        FrameLabeller(detector, foreign)
    FrameLabeller(detector, baselines)  # the default head's own baselines still go


def test_gate_clears_healthy_rows_and_leaves_the_rest_to_the_detector(detector):
    """With reference traces the gate labels the healthy rows it clears; the others are labelled as before."""
    import dataclasses

    n = 240
    rec = BaselineRecorder(n_frames=4)
    for k in range(4):
        rec.add(FIRST, simulate_nozzles(["healthy_nozzle"] * n, seed=HEAD, frame_seed=k).traces)
    with_ref = rec.baselines()
    assert with_ref.has_reference
    no_ref = dataclasses.replace(with_ref, reference=None)
    classes = np.array(["healthy_nozzle", "ok_signal"] * (n // 2), dtype=object)
    faults = [c.value for c in FaultClass if c.value not in ("healthy_nozzle", "ok_signal")]
    classes[::12] = [faults[i % len(faults)] for i in range(n // 12)]  # 20 faulty nozzles, every fault class
    x = simulate_nozzles(classes, seed=HEAD, frame_seed=123).traces.astype(np.float32)
    x[5, 3] = np.nan
    frames, firsts = [x[:100], x[100:]], [FIRST, FIRST + 100]
    gated = FrameLabeller(detector, with_ref, max_abs_v=10.0)
    plain = FrameLabeller(detector, no_ref, max_abs_v=10.0)
    assert gated.uses_gate and not plain.uses_gate
    got, want = gated.label(frames, firsts), plain.label(frames, firsts)
    cleared = np.concatenate([g.gate_cleared for g in got])
    assert all(w.gate_cleared is None for w in want)
    healthy = np.isin(classes, ["healthy_nozzle", "ok_signal"])
    assert not cleared[~healthy].any() and not cleared[5]
    assert cleared[healthy].mean() > 0.9
    g = {k: np.concatenate([getattr(f, k) for f in got]) for k in ("classes", "confidence", "valid", "reasons",
                                                                     "baseline")}
    w = {k: np.concatenate([getattr(f, k) for f in want]) for k in g}
    for k in ("valid", "reasons", "baseline"):
        np.testing.assert_array_equal(g[k], w[k])
    np.testing.assert_array_equal(g["classes"][~cleared], w["classes"][~cleared])
    np.testing.assert_array_equal(g["confidence"][~cleared], w["confidence"][~cleared])  # bit-identical
    assert (g["classes"][cleared] == classes[cleared]).all() and (g["confidence"][cleared] == 1.0).all()
    assert np.mean(g["classes"][cleared] == w["classes"][cleared]) >= 0.97  # the full model's healthy class
    for f in got + want:
        _codes_are_the_classes(f)


def test_frames_screened_and_gated_one_by_one_label_as_the_stacked_batch(detector):
    """The labeller screens each frame and sums it against its references in place (no stacked copy):
    the same labels as screen_traces, HealthyGate.screen and the detector on the stacked rows, with frames
    that wrap around the head, invalid rows, nozzles without a reference and a float64 frame."""
    from inkdiag_core import HealthyGate, screen_traces

    n = 120
    rec = BaselineRecorder(n_frames=4)
    for k in range(4):
        rec.add(FIRST, simulate_nozzles(["healthy_nozzle"] * n, seed=HEAD, frame_seed=k).traces)
    base = rec.baselines()  # nozzles FIRST .. FIRST + 119
    classes = np.array(["healthy_nozzle", "ok_signal"] * (n // 2), dtype=object)
    classes[::10] = "partially_blocked"
    x = simulate_nozzles(classes, seed=HEAD, frame_seed=9).traces.astype(np.float32)
    x[7, 3], x[30] = np.inf, 0.0  # non_finite, flat
    x[64, 100:110] = x[64].max()  # clipped
    # the first frame's nozzles have no baseline (ids far beyond the head's), then the batch wraps around
    order = [(90, 120, 1000), (0, 50, 0), (50, 90, 50)]
    frames = [x[a:b] for a, b, _ in order]
    frames[2] = frames[2].astype(np.float64)
    firsts = [FIRST + f for _, _, f in order]
    labeller = FrameLabeller(detector, base, max_abs_v=10.0)
    assert labeller.uses_gate
    got = labeller._finish_rows([labeller._screen_rows(frames, firsts)])[0]  # the batch itself (label() would retry a failing batch frame by frame)

    rows = np.concatenate(frames)
    ids = np.concatenate([f + np.arange(a.shape[0]) for f, a in zip(firsts, frames)])
    valid, reasons = screen_traces(rows, max_abs_v=10.0, sample_rate_hz=detector.sample_rate_hz_)
    at = np.flatnonzero(valid)
    g = HealthyGate(base).screen(rows[at], ids[at])
    rest = at[~g.cleared]
    has, kpis = base.lookup(ids[rest])
    kpis[~has] = np.nan
    d = detector.label(rows[rest], baseline_kpis=kpis)
    want = np.full(len(rows), "", dtype=object)
    want[at[g.cleared]] = g.classes[g.cleared]
    want[rest] = d.classes
    conf = np.full(len(rows), np.nan)
    conf[at[g.cleared]] = 1.0
    conf[rest] = d.confidence

    cat = {k: np.concatenate([getattr(f, k) for f in got]) for k in ("classes", "confidence", "reasons", "gate_cleared")}
    np.testing.assert_array_equal(cat["reasons"], reasons)
    np.testing.assert_array_equal(cat["gate_cleared"][at], g.cleared)
    np.testing.assert_array_equal(cat["classes"], want)
    np.testing.assert_array_equal(cat["confidence"], conf)
    assert g.cleared.sum() > 50 and (~g.cleared).sum() > 20  # both paths taken
    where = {int(i): r for i, r in zip(ids, cat["reasons"]) if r}
    assert where == {FIRST + 7: "non_finite", FIRST + 30: "flat", FIRST + 64: "clipped"}


def test_frames_of_another_dtype_are_screened_and_gated_in_numpy_as_the_stacked_batch(detector):
    """Frames that are not float32/float64 (float16 here; ADC counts alike) take screening's and the gate's numpy
    passes on the stacked rows: the same labels as screen_traces, HealthyGate.screen and the detector, the
    gate's rows cleared with their class."""
    from inkdiag_core import HealthyGate, screen_traces

    n = 120
    rec = BaselineRecorder(n_frames=4)
    for k in range(4):
        rec.add(FIRST, simulate_nozzles(["healthy_nozzle"] * n, seed=HEAD, frame_seed=k).traces)
    base = rec.baselines()
    classes = np.array(["healthy_nozzle", "ok_signal"] * (n // 2), dtype=object)
    classes[::10] = "partially_blocked"
    x = simulate_nozzles(classes, seed=HEAD, frame_seed=9).traces.astype(np.float16)
    x[7, 3], x[30] = np.inf, 0.0  # non_finite, flat
    frames, firsts = [x[:50], x[50:]], [FIRST, FIRST + 50]
    got = FrameLabeller(detector, base, max_abs_v=10.0).label(frames, firsts)

    ids = FIRST + np.arange(n)
    valid, reasons = screen_traces(x, max_abs_v=10.0, sample_rate_hz=detector.sample_rate_hz_)
    at = np.flatnonzero(valid)
    g = HealthyGate(base).screen(x[at], ids[at])
    rest = at[~g.cleared]
    d = detector.label(x[rest], baseline_kpis=base.lookup(ids[rest])[1])
    want = np.full(n, "", dtype=object)
    want[at[g.cleared]] = g.classes[g.cleared]
    want[rest] = d.classes
    cat = {k: np.concatenate([getattr(f, k) for f in got]) for k in ("classes", "reasons", "gate_cleared", "valid")}
    np.testing.assert_array_equal(cat["reasons"], reasons)
    np.testing.assert_array_equal(cat["valid"], valid)
    np.testing.assert_array_equal(cat["gate_cleared"][at], g.cleared)
    np.testing.assert_array_equal(cat["classes"], want)
    assert g.cleared.sum() > 50 and (g.classes[g.cleared] == "ok_signal").any() and len(rest) > 10


def test_any_first_id_labels_without_baselines_and_read_only_ids_compile_nothing(detector, baselines):
    """Without baselines the ids select nothing: a first id beyond int64 labels as any other (the kernel is
    not given it); explicit read-only ids are copied, so a node's warmed-up kernels take them as they are."""
    from inkdiag_core import _kernels

    frames, _ = _head_frames()
    plain = FrameLabeller(detector, max_abs_v=10.0)
    _same(plain.label(frames[:1], [2**64]), plain.label(frames[:1], [0]))
    ids = np.arange(FIRST, FIRST + len(frames[0]))
    ids.flags.writeable = False
    labeller = FrameLabeller(detector, baselines, max_abs_v=10.0)
    before = len(_kernels._screen_gate_rows.signatures)
    _same(labeller.label(frames[:1], [FIRST], nozzles=[ids]), labeller.label(frames[:1], [FIRST]))
    assert len(_kernels._screen_gate_rows.signatures) == before


@pytest.mark.parametrize("max_abs_v", [0.0, -1.0, float("nan")])
def test_a_max_abs_v_that_is_not_positive_is_a_config_error(detector, max_abs_v):
    with pytest.raises(LabellerConfigError, match="max_abs_v must be > 0 V"):
        FrameLabeller(detector, max_abs_v=max_abs_v)


def test_frames_screened_in_bursts_and_finished_together_label_as_label_does(detector, baselines):
    """screen() per burst, one finish() for them all (the fdi node's flush): each frame's labels are
    label()'s, bit for bit, with and without the gate, bad frames failing alone in their burst; the
    detector runs once."""
    import dataclasses

    frames, firsts = _head_frames()
    rec = BaselineRecorder(n_frames=4)
    for k in range(4):
        rec.add(FIRST, simulate_nozzles(["healthy_nozzle"] * N, seed=HEAD, frame_seed=k).traces)
    with_ref = rec.baselines()
    for base in (baselines, with_ref, None, dataclasses.replace(with_ref, reference=None)):
        lab = FrameLabeller(detector, base, max_abs_v=10.0)
        want = lab.label(frames, firsts)
        bursts = [([frames[0]], [firsts[0]]), ([frames[1], np.zeros(512, np.float32), frames[2]],
                                                [firsts[1], 0, firsts[2]]), ([frames[3]], [firsts[3]])]
        screened = [lab.screen(f, fi) for f, fi in bursts]
        assert [len(s) for s in screened] == [1, 3, 1]
        assert sum(s.rows_left for s in screened) > 0
        got = lab.finish(screened)
        assert isinstance(got[1][1], FrameFailure) and got[1][1].frame_index == 1
        _same([got[0][0], got[1][0], got[1][2], got[2][0]], want)
        for g, w in zip([got[0][0], got[1][0], got[1][2], got[2][0]], want):
            assert (g.gate_cleared is None) == (w.gate_cleared is None)
            if w.gate_cleared is not None:
                np.testing.assert_array_equal(g.gate_cleared, w.gate_cleared)


def test_a_frame_the_detector_refuses_in_a_joint_finish_fails_alone(detector, monkeypatch):
    """finish() of several screened bursts: the joint detector call raises, so each burst alone, then
    each frame of the burst that still raises alone: only the frame at fault fails."""
    frames, firsts = _head_frames()
    lab = FrameLabeller(detector, max_abs_v=10.0)
    real = type(detector).label
    calls = []

    def refuse_frame_two(self, X, **kw):
        calls.append(len(X))
        if any(np.array_equal(r, frames[2][0]) for r in np.asarray(X)):
            raise RuntimeError("boom")
        return real(self, X, **kw)

    want = lab.label([frames[0], frames[1], frames[3]], [firsts[0], firsts[1], firsts[3]])
    monkeypatch.setattr(type(detector), "label", refuse_frame_two)
    screened = [lab.screen(frames[:2], firsts[:2]), lab.screen(frames[2:], firsts[2:])]
    got = lab.finish(screened)
    assert [isinstance(g, FrameFailure) for g in got[0] + got[1]] == [False, False, True, False]
    assert got[1][0].frame_index == 0 and got[1][0].why == "RuntimeError: boom"
    _same([got[0][0], got[0][1], got[1][1]], want)
    assert len(calls) == 5  # joint, burst 1, burst 2, then its frames alone


def test_a_class_outside_the_labellers_names_is_an_error_not_a_wrong_code(detector):
    lab = FrameLabeller(detector)
    names = lab._class_names
    np.testing.assert_array_equal(lab._codes_of(np.array(["unknown", "deeply_dried"], dtype=object)),
                                  [names.index("unknown"), names.index("deeply_dried")])
    with pytest.raises(ValueError, match="outside"):
        lab._codes_of(np.array(["deeply_dried", "zz_not_a_class"], dtype=object))
