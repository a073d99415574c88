"""Per-nozzle healthy baselines: twins, baseline KPIs, the baseline feature set."""

import re

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


def test_baseline_features_from_traces_and_baselines_apart():
    """The detector's hot path (issue 17) computes the baseline branch's features without stacking the
    traces and the baseline KPIs into one copy. Float64 traces: the stacked rows' features bit for bit.
    Float32 traces: their KPIs fitted in float32, as the plain branch fits them (the stacked rows with
    float64 baselines are float64), the relative features from those KPIs and the float64 baselines."""
    from inkdiag_core.kpis import kpis_of_checked

    sim = simulate({FaultClass.HEALTHY_NOZZLE: 20, FaultClass.DEEPLY_DRIED: 20}, seed=2)
    _, frames = healthy_twin_frames(40, seed=2, n_frames=4, noise_std_v=sim.noise_std_v)
    base = baseline_kpis(frames, FS)  # float64, as NozzleBaselines.lookup gives them
    step = BaselineKpis(FS).fit(with_baseline(sim.traces, base))
    f64 = sim.traces.astype(np.float64)
    np.testing.assert_array_equal(step._features_of(f64, base), step._transform_checked(with_baseline(f64, base)))
    f32 = sim.traces.astype(np.float32)
    got = step._features_of(f32, base)
    np.testing.assert_array_equal(got[:, :7], kpis_of_checked(f32, FS))
    stacked = step.transform(with_baseline(f32, base))  # float64 KPIs of the same samples
    assert not np.array_equal(got, stacked)
    np.testing.assert_allclose(got, stacked, rtol=1e-3, atol=1e-6)


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


# --- recording baselines from a head's frames, and their file -------------------------------

from inkdiag_core import BaselineFileError, BaselineRecorder, NozzleBaselines, simulate_nozzles  # noqa: E402


def _head_frames(n_nozzles, n_frames, head_seed=3):
    """Frames of one healthy simulated head (its nozzles persist across frames)."""
    return [simulate_nozzles(["healthy_nozzle"] * n_nozzles, seed=head_seed, frame_seed=f).traces
            for f in range(n_frames)]


def test_recorder_gives_each_nozzle_the_median_of_its_first_frames():
    frames = _head_frames(50, 10)
    rec = BaselineRecorder(n_frames=8)
    for f in frames:  # messages of 20, 20 and 10 nozzles; later frames are ignored
        for first in (40, 0, 20):
            rec.add(first, f[first:first + 20])
    assert rec.n_complete == 50
    b = rec.baselines()
    np.testing.assert_array_equal(b.nozzle_ids, np.arange(50))
    np.testing.assert_array_equal(b.kpis, baseline_kpis(np.stack(frames[:8], axis=1), FS))
    assert (b.sample_rate_hz, b.n_samples, b.n_frames) == (FS, 512, 8)


def test_a_nozzle_that_rings_unlike_the_heads_others_gets_no_baseline():
    """A nozzle dried at commissioning, taken as healthy, got a baseline f_m of -2.2e6 1/s, and its later deeply
    dried estimates came out wetter than healthy (helper-103's QA): it gets none, and the recorder says so."""
    classes = np.array(["healthy_nozzle"] * 40, dtype=object)
    classes[[5, 31]] = ["deeply_dried", "partially_blocked"]
    frames = [simulate_nozzles(classes, seed=3, frame_seed=f).traces for f in range(8)]
    rec = BaselineRecorder(n_frames=8)
    for f in frames:
        rec.add(0, f)
    b = rec.baselines()
    np.testing.assert_array_equal(b.nozzle_ids, np.delete(np.arange(40), [5, 31]))
    assert b.reference.shape == (38, 512)
    np.testing.assert_array_equal(b.kpis, np.delete(baseline_kpis(np.stack(frames, axis=1), FS), [5, 31], axis=0))
    np.testing.assert_array_equal(rec.unlike_head[0], [5, 31])
    note = rec.unlike_note()
    assert note.startswith("2 nozzle(s) ring unlike the head's others (its median 23") and "5 (1" in note, note
    # a healthy head, or too few nozzles to tell a head's spread: every nozzle kept, nothing said
    for n, cls in ((400, ["healthy_nozzle"] * 400), (7, list(classes[:7]))):
        rec = BaselineRecorder(n_frames=8)
        for f in range(8):
            rec.add(0, simulate_nozzles(cls, seed=4, frame_seed=f).traces)
        assert len(rec.baselines()) == n and rec.unlike_note() == ""


def test_rows_that_do_not_ring_above_their_noise_are_not_used():
    """A nozzle that did not fire at commissioning (white noise) got a baseline of noise (helper-103's QA)."""
    frames = _head_frames(10, 3)
    rng = np.random.default_rng(0)
    rec = BaselineRecorder(n_frames=3)
    for f in frames:
        f = f.copy()
        f[4] = rng.normal(0.0, 0.01, f.shape[1])
        rec.add(0, f)
    assert rec.rows_not_ringing == 3
    np.testing.assert_array_equal(rec.baselines().nozzle_ids, np.delete(np.arange(10), 4))


def test_a_nozzle_whose_phase_lies_near_pi_gets_its_own_phase_as_baseline():
    """The phase KPI is wrapped to (-pi, pi]: a nozzle near +-pi has rows at 3.14 and -3.14 rad, whose plain
    median came out near 0, and then every healthy trace of it looked pi off its baseline (a head whose sensing
    delay puts its healthy phase there: 2 of these 400 nozzles). The median is taken on the circle there."""
    from scipy.signal import hilbert

    from inkdiag_core import extract_kpis
    from inkdiag_core.baselines.features import PHASE, median_kpis

    frames = _head_frames(400, 8, head_seed=0)
    turn = np.pi - np.median(extract_kpis(frames[0], FS)[:, PHASE])  # the healthy phase turned to about pi
    frames = [np.real(hilbert(f, axis=1) * np.exp(1j * turn)).astype(np.float32) for f in frames]
    rec = BaselineRecorder(n_frames=8)
    for f in frames:
        rec.add(0, f)
    base = rec.baselines().kpis
    np.testing.assert_array_equal(base, baseline_kpis(np.stack(frames, axis=1), FS))
    rows = np.stack([extract_kpis(f, FS) for f in frames], axis=1)
    wraps = np.ptp(rows[:, :, PHASE], axis=1) > np.pi
    off = np.abs(np.angle(np.exp(1j * (rows[:, :, PHASE] - base[:, PHASE, None]))))
    assert wraps.sum() >= 2 and off.max() < 0.05, (wraps.sum(), off.max())  # each row near its baseline
    plain = np.median(rows, axis=1)
    np.testing.assert_array_equal(base[~wraps], plain[~wraps])  # elsewhere the plain median, bit for bit
    np.testing.assert_array_equal(np.delete(base[wraps], PHASE, 1), np.delete(plain[wraps], PHASE, 1))
    # the rule alone: both sides of pi, a NaN row left out, a nozzle with no row at all
    k = np.zeros((3, 4, 7))
    k[0, :, PHASE] = [3.1, -3.1, 3.12, -3.13]
    k[1, :, PHASE] = [0.1, 0.2, np.nan, 0.3]
    k[2] = np.nan
    with pytest.warns(RuntimeWarning, match="All-NaN slice"):  # np.nanmedian's, of the third nozzle
        got = median_kpis(k, skip_nan=True)
    assert abs(abs(got[0, PHASE]) - np.pi) < 0.05 and got[1, PHASE] == pytest.approx(0.2) and np.isnan(got[2]).all()


def test_recorder_skips_invalid_and_excluded_rows_and_waits_for_enough_frames():
    frames = _head_frames(6, 4)
    rec = BaselineRecorder(n_frames=3)
    for i, f in enumerate(frames):
        f = f.copy()
        f[1] = np.nan  # nozzle 101: never valid
        keep = np.ones(6, bool)
        keep[2] = i != 0  # nozzle 102: excluded once (e.g. not labelled healthy)
        rec.add(100, f, keep=keep)
    full = rec.baselines()
    np.testing.assert_array_equal(full.nozzle_ids, [100, 102, 103, 104, 105])
    # nozzle 102's baseline comes from frames 1-3
    np.testing.assert_array_equal(full.lookup([102])[1][0],
                                  baseline_kpis(np.stack([f[2] for f in frames[1:]])[None], FS)[0])
    rec2 = BaselineRecorder(n_frames=3)
    rec2.add(0, frames[0])
    assert len(rec2.baselines()) == 0 and len(rec2.baselines(min_frames=1)) == 6
    with pytest.raises(ValueError, match="min_frames"):
        rec2.baselines(min_frames=4)


def test_add_rows_takes_a_recordings_rows_as_add_takes_its_frames():
    """Rows of any nozzles in one call, repeated ids as later frames: the same baselines (KPIs,
    f_m readings, references) as the frames given one message at a time, in the same order."""
    frames = _head_frames(12, 5)
    by_frame = BaselineRecorder(n_frames=4, fm_frames=2)
    for f in frames:
        by_frame.add(0, f)
    x = np.concatenate(frames)  # frame by frame: nozzles 0..11, then 0..11 again, ...
    ids = np.tile(np.arange(12), 5)
    perm = np.random.default_rng(0).permutation(12)  # a shuffled nozzle order within each frame
    rows = np.concatenate([k * 12 + perm for k in range(5)])
    by_rows = BaselineRecorder(n_frames=4, fm_frames=2)
    assert by_rows.add_rows(ids[rows[:30]], x[rows[:30]]) == 30  # two calls, one cutting a frame
    assert by_rows.add_rows(ids[rows[30:]], x[rows[30:]]) == 48 - 30  # the 5th frame is beyond n_frames
    assert by_rows.n_complete == by_rows.n_seen == 12
    a, b = by_frame.baselines(), by_rows.baselines()
    np.testing.assert_array_equal(a.nozzle_ids, b.nozzle_ids)
    np.testing.assert_array_equal(a.kpis, b.kpis)
    np.testing.assert_array_equal(a.fm, b.fm)
    np.testing.assert_array_equal(a.reference, b.reference)


def test_add_rows_skips_invalid_and_excluded_rows_and_counts_only_what_it_keeps():
    frames = _head_frames(3, 3)
    x = np.concatenate(frames)
    x[0, 4] = np.nan  # nozzle 0's first frame: invalid, its later two frames are used
    keep = np.ones(9, bool)
    keep[1] = False  # nozzle 1's first frame excluded
    rec = BaselineRecorder(n_frames=3)
    assert rec.add_rows(np.tile([0, 1, 2], 3), x, keep=keep) == 7
    assert rec.n_complete == 1 and rec.n_seen == 3
    assert len(rec.baselines()) == 1 and len(rec.baselines(min_frames=2)) == 3


@pytest.mark.parametrize(("call", "match"), [
    (lambda r: r.add_rows([0, -1], np.zeros((2, 512))), ">= 0"),
    (lambda r: r.add_rows([0, 1, 2], np.zeros((2, 512))), "3 ids for 2 rows"),
    (lambda r: r.add_rows([0.5, 1], np.zeros((2, 512))), "integer"),
    (lambda r: r.add_rows([[0, 1]], np.zeros((2, 512))), "1-d"),
    (lambda r: r.add_rows([0, 2**24], np.zeros((2, 512))), "below"),
    (lambda r: r.add(-1, np.zeros((2, 512))), "first_nozzle"),
    (lambda r: r.add(0, np.zeros((2, 100))), "shape"),
    (lambda r: r.add(0, np.zeros(512)), "shape"),
    (lambda r: r.add(0, np.zeros((2, 512)), keep=[True]), "keep"),
    (lambda r: r.add(2**24 - 1, np.zeros((2, 512))), "below"),
    (lambda r: r.add(2**63, np.zeros((2, 512))), "below"),  # no int64 overflow
    (lambda r: r.add(2**63, np.zeros((0, 512))), "below"),  # nor with no rows
    (lambda r: r.add_rows(np.array([2**64 - 1, 0], np.uint64), np.zeros((2, 512))), "below"),  # checked before a cast
])
def test_recorder_rejects_bad_input(call, match):
    with pytest.raises(ValueError, match=match):
        call(BaselineRecorder())


def test_rows_beyond_the_sensors_range_are_not_used():
    """By default a row beyond the profile's bound (5x its ADC range, as fdi screens) is skipped."""
    frames = _head_frames(3, 2)
    x = np.concatenate(frames)
    x[4] *= 1e3  # nozzle 1's second frame: thousands of volts
    for rec, used in ((BaselineRecorder(n_frames=2), 5), (BaselineRecorder(n_frames=2, max_abs_v=1e6), 6)):
        assert rec.max_abs_v == (10.0 if used == 5 else 1e6)  # the default head: +-2 V ADC
        assert rec.add_rows(np.tile([0, 1, 2], 2), x) == used
    for bad in (0.0, np.inf, np.nan, True):
        with pytest.raises(ValueError, match="max_abs_v"):
            BaselineRecorder(max_abs_v=bad)


def test_lookup_finds_the_nozzles_that_have_a_baseline():
    kpis = np.arange(21, dtype=float).reshape(3, 7)
    b = NozzleBaselines(np.array([5, 9, 200]), kpis, FS, 512, 8)
    has, got = b.lookup([9, 6, 200, 0, 5, 1000])
    np.testing.assert_array_equal(has, [True, False, True, False, True, False])
    np.testing.assert_array_equal(got[has], kpis[[1, 2, 0]])
    assert np.isnan(got[~has]).all()
    assert not NozzleBaselines(np.empty(0, int), np.empty((0, 7)), FS, 512, 8).lookup([1])[0].any()


@pytest.mark.parametrize(("ids", "kpis", "match"), [
    ([2, 1], np.zeros((2, 7)), "increasing"),
    ([1, 2], np.zeros((2, 6)), "shape"),
    ([1, 2], np.full((2, 7), np.nan), "finite"),
    ([1.5, 2], np.zeros((2, 7)), "integer"),
])
def test_baselines_reject_inconsistent_arrays(ids, kpis, match):
    with pytest.raises(ValueError, match=match):
        NozzleBaselines(np.array(ids), kpis, FS, 512, 8)


def test_baselines_file_round_trip_and_refusals(tmp_path):
    b = NozzleBaselines(np.array([3, 7]), np.random.default_rng(0).normal(size=(2, 7)), FS, 512, 8)
    path = b.save(tmp_path / "head.npz")
    again = NozzleBaselines.load(path)
    np.testing.assert_array_equal(again.nozzle_ids, b.nozzle_ids)
    np.testing.assert_array_equal(again.kpis, b.kpis)
    assert (again.sample_rate_hz, again.n_samples, again.n_frames) == (FS, 512, 8)

    with pytest.raises(BaselineFileError, match="no baselines file"):
        NozzleBaselines.load(tmp_path / "missing.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(BaselineFileError, match="not an inkdiag baselines file"):
        NozzleBaselines.load(tmp_path / "junk.npz")
    # an edited value (the file rewritten with the old checksum) is refused
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["kpis"] = arrays["kpis"].copy()
    arrays["kpis"][0, 1] *= 1.01
    np.savez(tmp_path / "edited.npz", **arrays)
    with pytest.raises(BaselineFileError, match="does not match its sha256"):
        NozzleBaselines.load(tmp_path / "edited.npz")
    # a damaged file (one byte flipped inside the kpis array, or cut short)
    raw = bytearray(path.read_bytes())
    at = raw.find(b"kpis.npy") + 200
    raw[at] ^= 0xFF
    (tmp_path / "flipped.npz").write_bytes(bytes(raw))
    (tmp_path / "cut.npz").write_bytes(path.read_bytes()[:100])
    for name in ("flipped.npz", "cut.npz"):
        with pytest.raises(BaselineFileError, match="damaged|sha256"):
            NozzleBaselines.load(tmp_path / name)
    np.savez(tmp_path / "other.npz", nozzle_ids=arrays["nozzle_ids"], kpis=arrays["kpis"],
             meta=np.array('{"format": "something-else"}'))
    with pytest.raises(BaselineFileError, match="not an inkdiag baselines file"):
        NozzleBaselines.load(tmp_path / "other.npz")
    np.savez(tmp_path / "deep.npz", nozzle_ids=arrays["nozzle_ids"], kpis=arrays["kpis"],
             meta=np.array("[" * 100_000 + "]" * 100_000))
    with pytest.raises(BaselineFileError, match="RecursionError"):  # its meta nested too deeply for json
        NozzleBaselines.load(tmp_path / "deep.npz")
    # not an .npz at all: said so (numpy's own message would suggest loading pickles unsafely)
    import pickle

    (tmp_path / "pickled.npz").write_bytes(pickle.dumps({"kpis": 1}))
    (tmp_path / "empty.npz").write_bytes(b"")
    for name, what in (("pickled.npz", "it starts with b'\\x80"), ("empty.npz", "an empty file")):
        with pytest.raises(BaselineFileError) as exc:
            NozzleBaselines.load(tmp_path / name)
        assert f"is not an inkdiag baselines file: not an .npz archive ({what}" in str(exc.value)


def test_recorder_takes_each_nozzles_healthy_fm_from_its_first_fm_frames():
    from inkdiag_core import InkChannelModel, estimate_fm_batch

    frames = _head_frames(12, 5, head_seed=4)
    rec = BaselineRecorder(n_frames=4, fm_frames=2)
    for i, f in enumerate(frames):
        f = f.copy()
        if i == 0:
            f[3] = np.nan  # nozzle 3: invalid in frame 0 only
        rec.add(0, f[:7])
        rec.add(7, f[7:])
    b = rec.baselines()
    assert b.fm is not None and b.fm.shape == (12,)
    fm = np.stack([estimate_fm_batch(f, InkChannelModel(), FS, method="vp").fm for f in frames])  # (frame, nozzle)
    want = np.median(fm[:2], axis=0)
    want[3] = np.median(fm[1:3, 3])  # its first two valid rows
    # estimate_fm_batch of rows in batches of 7 and 5 vs 12 agrees to ~1e-6 relative, not bit for bit
    np.testing.assert_allclose(b.fm, want, rtol=1e-5)
    has, got = b.lookup_fm([3, 99, 0])
    np.testing.assert_array_equal(has, [True, False, True])
    np.testing.assert_array_equal(got, [b.fm[3], 0.0, b.fm[0]])
    assert BaselineRecorder(n_frames=2).fm_frames == 0
    plain = BaselineRecorder(n_frames=1)
    plain.add(0, frames[0])
    assert plain.baselines().fm is None and not plain.baselines().lookup_fm([0])[0].any()


@pytest.mark.parametrize("fm_frames", [-1, 5, True, 1.5])
def test_recorder_rejects_bad_fm_frames(fm_frames):
    with pytest.raises(ValueError, match="fm_frames"):
        BaselineRecorder(n_frames=4, fm_frames=fm_frames)


def test_fm_baselines_round_trip_are_checked_and_version_1_files_still_load(tmp_path):
    import json

    from inkdiag_core.baselines.store import _content_sha256

    kpis = np.random.default_rng(1).normal(size=(3, 7))
    b = NozzleBaselines(np.array([1, 4, 9]), kpis, FS, 512, 8, fm=np.array([1e3, np.nan, -2e4]))
    again = NozzleBaselines.load(b.save(tmp_path / "fm.npz"))
    np.testing.assert_array_equal(again.fm, b.fm)
    np.testing.assert_array_equal(again.lookup_fm([4, 9])[0], [False, True])
    with np.load(tmp_path / "fm.npz") as z:
        arrays = {k: z[k] for k in z.files}
    edited = dict(arrays, fm=arrays["fm"] * 1.01)
    np.savez(tmp_path / "edited.npz", **edited)
    dropped = {k: v for k, v in arrays.items() if k != "fm"}
    np.savez(tmp_path / "dropped.npz", **dropped)
    for name, match in (("edited.npz", "sha256"), ("dropped.npz", "f_m column")):
        with pytest.raises(BaselineFileError, match=match):
            NozzleBaselines.load(tmp_path / name)
    # a file of format 1 (KPIs only, as the previous version wrote it)
    meta = {"format": "inkdiag-nozzle-baselines", "format_version": 1, "kpi_names": list(KPI_NAMES),
            "sample_rate_hz": FS, "n_samples": 512, "n_frames": 8}
    ids = np.array([1, 4, 9])
    meta["sha256"] = _content_sha256(ids, kpis, dict(meta))
    np.savez(tmp_path / "v1.npz", nozzle_ids=ids, kpis=kpis, meta=np.array(json.dumps(meta)))
    v1 = NozzleBaselines.load(tmp_path / "v1.npz")
    assert v1.fm is None
    np.testing.assert_array_equal(v1.kpis, kpis)
    with pytest.raises(ValueError, match="fm must have shape"):
        NozzleBaselines(ids, kpis, FS, 512, 8, fm=np.zeros(2))
    with pytest.raises(ValueError, match="fm must be finite"):
        NozzleBaselines(ids, kpis, FS, 512, 8, fm=np.array([0.0, np.inf, 0.0]))


# --- labelling against recorded baselines ---------------------------------------------------

def test_label_frames_uses_each_nozzles_baseline_where_it_has_one(tmp_path):
    from inkdiag_core import BaselineModel, label_frames, load_model
    from inkdiag_core.fdi import classify, train_default_model

    train_default_model(tmp_path / "plain.joblib", n_per_class=60)
    train_default_model(tmp_path / "base.joblib", n_per_class=60, features="kpi_y+baseline")
    plain, _ = load_model(tmp_path / "plain.joblib")
    based, manifest = load_model(tmp_path / "base.joblib")
    assert manifest["config"]["features"] == "kpi_y+baseline"

    n, head = 60, 21
    rec = BaselineRecorder(n_frames=4)
    for f in _head_frames(n, 4, head_seed=head):
        rec.add(500, f)
    baselines = rec.baselines()
    # drop nozzles 510-519's baselines: they are labelled without one
    keep = (baselines.nozzle_ids < 510) | (baselines.nozzle_ids >= 520)
    baselines = NozzleBaselines(baselines.nozzle_ids[keep], baselines.kpis[keep], FS, 512, 4)
    classes = np.array(list(FaultClass), dtype=object)[np.arange(n) % 12]
    frame = simulate_nozzles(classes, seed=head, frame_seed=99).traces
    frame[3] = np.nan
    model = BaselineModel(based, baselines, fd_threshold=0.5)
    a, b = label_frames(plain, [frame[:30], frame[30:]], first_nozzles=[500, 530], baseline=model)
    got = np.concatenate([a.classes, b.classes])
    used = np.concatenate([a.baseline, b.baseline])
    expect_used = np.ones(n, bool)
    expect_used[10:20] = False
    expect_used[3] = False  # invalid row
    np.testing.assert_array_equal(used, expect_used)
    assert got[3] == "" and a.reasons[3] == "non_finite"
    has, kpis = baselines.lookup(500 + np.arange(n))
    ref_b, _, _ = classify(based, with_baseline(frame[used], kpis[used]))
    ref_p, _, _ = classify(plain, frame[10:20])
    np.testing.assert_array_equal(got[used], ref_b)
    np.testing.assert_array_equal(got[10:20], ref_p)
    with pytest.raises(ValueError, match="first_nozzles"):
        label_frames(plain, [frame], baseline=model)


def test_f_m_readings_say_their_estimator(tmp_path):
    """Baselines with f_m are the raw vp readings unless said otherwise (None: a file before format 5);
    a format-5 file whose readings name no estimator is refused, not read as an old file's."""
    import json

    from inkdiag_core.baselines import FM_METHOD

    b = NozzleBaselines(np.arange(3), np.ones((3, 7)), FS, 512, 4, fm=np.zeros(3))
    assert b.fm_method == FM_METHOD == "vp"
    assert NozzleBaselines(np.arange(3), np.ones((3, 7)), FS, 512, 4).fm_method is None  # no f_m, no estimator
    assert NozzleBaselines.load(b.save(tmp_path / "b.npz")).fm_method == "vp"
    with np.load(tmp_path / "b.npz") as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(str(arrays["meta"]))
    from inkdiag_core.baselines.store import _content_sha256

    meta = {k: v for k, v in meta.items() if k != "sha256"}
    meta["fm_method"] = None
    meta["sha256"] = _content_sha256(b.nozzle_ids, b.kpis, {k: v for k, v in meta.items() if k != "sha256"}, b.fm)
    arrays["meta"] = np.array(json.dumps(meta, sort_keys=True))
    np.savez(tmp_path / "unsaid.npz", **arrays)
    with pytest.raises(BaselineFileError, match="fm_method None"):
        NozzleBaselines.load(tmp_path / "unsaid.npz")
    with pytest.raises(ValueError, match="fm_method"):
        NozzleBaselines(np.arange(3), np.ones((3, 7)), FS, 512, 4, fm=np.zeros(3), fm_method="vp_cal")


@pytest.mark.parametrize("n", [8, 64])
def test_gain_mismatch_says_a_head_whose_healthy_amplitude_is_not_its_profiles(n):
    from inkdiag_core import HeadProfile
    from inkdiag_core.baselines import GAIN_MISMATCH_LOG

    assert GAIN_MISMATCH_LOG == 0.06  # docs/controller.md's 0.9 and 1.1 fall beyond it

    p = HeadProfile.default()
    frames = np.stack([simulate_nozzles([FaultClass.HEALTHY_NOZZLE] * n, seed=21, frame_seed=f).traces
                       for f in range(3)], axis=1)
    for gain, said in ((1.0, False), (0.97, False), (0.8, True), (1.25, True), (-1.0, True), (-0.97, True),
                       (-1.5, True)):
        b = NozzleBaselines(np.arange(n), baseline_kpis(gain * frames, p.sample_rate_hz), p.sample_rate_hz,
                            p.n_samples, 3)
        got = b.gain_mismatch(p)
        assert bool(got) == said, (gain, got)
        if gain < 0:  # an inverted sign: the phase, pi off (the amplitude KPI is a magnitude)
            assert "out of phase" in got and "an inverted sensor sign?" in got, got
            assert abs(float(re.search(r"ring ([0-9.]+) rad out of phase", got).group(1)) - np.pi) < 0.1, got
        ratio = re.search(r"ring at ([0-9.]+)x the amplitude", got)
        assert (ratio is not None) == (said and abs(gain) != 1 and gain != -0.97), (gain, got)  # also with the phase
        if ratio is not None:  # the ratio, as far as n nozzles and the profile's 256 simulated ones tell it
            assert abs(float(ratio.group(1)) - abs(gain)) < 0.05 and "\n" not in got, got
    for shift, said in ((1, False), (3, True)):  # a later sensing window: 0.15 rad a sample at 237 kHz, 10 MHz
        late = np.concatenate([frames[..., shift:], frames[..., -1:].repeat(shift, axis=-1)], axis=-1)
        got = NozzleBaselines(np.arange(n), baseline_kpis(late, p.sample_rate_hz), p.sample_rate_hz, p.n_samples,
                              3).gain_mismatch(p)
        assert ("out of phase" in got and "switch_delay_s" in got) == said, (shift, got)
    assert NozzleBaselines(np.arange(2), np.ones((2, 7)), p.sample_rate_hz, p.n_samples, 3).gain_mismatch(p) == ""
