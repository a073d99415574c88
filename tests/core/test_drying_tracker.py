"""DryingTracker: trace messages and drying lists joined per (frame, nozzle range), either order."""

import numpy as np
import pytest

from inkdiag_core import (
    ESTIMATE_COLUMNS,
    DryingTracker,
    FaultClass,
    InkChannelModel,
    estimate_fm_batch,
    simulate_nozzles,
)

RANGE = 8  # nozzles per trace message
N_RANGES = 3
DRIED = {0: [2, 5], 1: [8, 9, 14], 2: [20]}  # per range: the head's dried nozzles


def _frame(frame_seed, dried=DRIED):
    """One frame of a 24-nozzle head, (24, 512) float32; the listed nozzles deeply dried."""
    classes = np.array([FaultClass.HEALTHY_NOZZLE.value] * RANGE * N_RANGES, dtype=object)
    classes[[nz for ids in dried.values() for nz in ids]] = FaultClass.DEEPLY_DRIED.value
    return simulate_nozzles(classes, seed=7, frame_seed=frame_seed).traces


def _traces(tr, x, frame_id, r, stamp=None):
    first = r * RANGE
    return tr.add_traces(x[first:first + RANGE], first_nozzle=first, frame_id=frame_id,
                         stamp=float(frame_id) if stamp is None else stamp, sample_rate_hz=10e6)


def _drying(tr, frame_id, r, ids):
    return tr.add_drying(frame_id, ids, first_nozzle=r * RANGE, n_nozzles=RANGE)


@pytest.mark.parametrize("traces_first", [True, False], ids=["traces_first", "drying_first"])
def test_each_range_is_estimated_with_its_own_frames_list_in_either_order(traces_first):
    x = _frame(1)
    tr = DryingTracker()
    out = []
    for r in range(N_RANGES):
        if traces_first:
            assert _traces(tr, x, 5, r) == []
            out += _drying(tr, 5, r, DRIED[r])
        else:
            assert _drying(tr, 5, r, DRIED[r]) == []
            out += _traces(tr, x, 5, r)
    assert [(e.frame_id, e.first_nozzle, e.n_nozzles) for e in out] == [(5, 0, 8), (5, 8, 8), (5, 16, 8)]
    for e, r in zip(out, range(N_RANGES)):
        assert list(e.columns) == list(ESTIMATE_COLUMNS) and e.nozzles.tolist() == DRIED[r]
        direct = estimate_fm_batch(x[DRIED[r]], InkChannelModel(), 10e6)
        np.testing.assert_array_equal(e.columns["fm"], direct.fm)
        np.testing.assert_array_equal(e.columns["fm_std"], direct.std)
        assert (e.columns["fm"] < 0).all() and e.stamp == 5.0 and e.note == ""
    assert tr.pending == (0, 0) and tr.ranges_joined == tr.ranges_estimated == 3
    assert tr.estimates == 6 and tr.traces_unmatched == tr.drying_unmatched == 0


def test_a_nozzle_is_estimated_in_its_first_dried_frame_and_not_after_it_recovered():
    tr = DryingTracker(recovery_frames=1)
    lists = {1: [2], 2: [2, 5], 3: [5]}  # range 0: 5 dries in frame 2, 2 recovers in frame 3
    got = {}
    for f, ids in lists.items():
        x = _frame(f, {0: ids})
        # the controller's traces come first, fdi's list after it labelled that frame
        assert _traces(tr, x, f, 0) == []
        (e,) = _drying(tr, f, 0, ids)
        got[f] = e.nozzles.tolist()
    assert got == lists
    assert tr.trends.trends[5].n_updates == 2
    # 2's trend (frames 1, 2) ended with frame 3's list, which leaves it out: it recovered
    assert tr.trends_recovered == 1 and tr.trends.n_updates[tr.trends.ids == 2] == 0


def test_listed_rows_beyond_max_estimates_are_counted():
    """fe's /diagnostics says how many listed rows the cap left out (helper-113: a list of 100 gave 64 estimates,
    with no mark)."""
    tr = DryingTracker(max_estimates=1)
    x = _frame(1, {0: [2, 5]})
    _traces(tr, x, 1, 0)
    (e,) = _drying(tr, 1, 0, [2, 5])
    assert e.nozzles.tolist() == [2] and tr.rows_capped == 1


def test_a_nozzle_that_recovers_and_dries_again_starts_a_new_trend():
    """helper-88: a nozzle dried, was purged (healthy, left out of its range's lists), dried again: its trend went on
    from the old drying, fm_rate the wrong sign for 6 frames and no ETA."""
    tr = DryingTracker(recovery_frames=1)
    lists = {1: [2], 2: [2], 3: [], 4: [2]}
    got = {}
    for f, ids in lists.items():
        x = _frame(f, {0: ids})
        _traces(tr, x, f, 0)
        out = _drying(tr, f, 0, ids)
        got[f] = {int(n): (fm, trend, rate) for e in out for n, fm, trend, rate in zip(
            e.nozzles, e.columns["fm"], e.columns["fm_trend"], e.columns["fm_rate"])}
    assert np.isfinite(got[2][2][2])  # its second frame of the first drying: a rate
    assert got[3] == {} and tr.trends_recovered == 1
    fm, trend, rate = got[4][2]
    assert trend == fm and np.isnan(rate)  # a new trend: its first estimate, no rate yet
    # a list that leaves out a nozzle it never listed, or one without a range, restarts nothing
    _drying(tr, 5, 1, [])
    tr.add_drying(5, [], first_nozzle=None)
    assert tr.trends_recovered == 1 and tr.trends.n_updates[tr.trends.ids == 2] == 1


def test_a_trend_ends_after_recovery_frames_in_a_row_without_the_nozzle():
    """helper-117: every frame fdi labelled a drying nozzle otherwise (unknown, partially blocked) ended its trend
    (20 restarts in 351 estimates), its rate and ETA lost. A trend now ends at the RECOVERY_FRAMES-th frame in a
    row that leaves its nozzle out; an estimate in between starts the count again; a frame given twice counts once."""
    from inkdiag_core.drying_tracker import RECOVERY_FRAMES

    assert RECOVERY_FRAMES == 3
    tr = DryingTracker()
    lists = [[2], [2], [], [], [2], [], [2], [], [], [], [2]]  # frames 1..11: 2 misses, 1, then 3 (ended)
    rates = {}
    for f, ids in enumerate(lists, start=1):
        _traces(tr, _frame(f, {0: ids}), f, 0)
        out = _drying(tr, f, 0, ids)
        if ids:
            rates[f] = out[0].columns["fm_rate"][0]
        if f == 4:  # frame 4's list again (a repeated message): the same news, not a third
            _traces(tr, _frame(f, {0: ids}), f, 0)
            _drying(tr, f, 0, ids)
    assert np.isfinite(rates[5]) and np.isfinite(rates[7])  # one trend from frame 1 to 7: frame 5 reset the count
    assert tr.trends_recovered == 1  # frame 10 ended it
    assert np.isnan(rates[11]) and tr.trends.n_updates[tr.trends.ids == 2] == 1  # frame 11: a new trend
    with pytest.raises(ValueError, match="recovery_frames must be >= 1"):
        DryingTracker(recovery_frames=0)
    # helper-122: a frame that lists the nozzle is no miss, estimated or not (here its trace is a misfit)
    tr = DryingTracker()
    t = np.arange(512) / 10e6
    for f, ids in enumerate([[2], [2], [], [2], [], [], [2]], start=1):
        x = _frame(f, {0: ids})
        if f == 4:
            x[2] = 0.3 * np.sin(2 * np.pi * 300e3 * t)  # listed as dried, not estimated
        _traces(tr, x, f, 0)
        out = _drying(tr, f, 0, ids)
        assert (f != 4) or (out == [] and tr.rows_no_fit == 1)
    assert tr.trends_recovered == 0 and np.isfinite(out[0].columns["fm_rate"][0])  # frames 5-6: two misses only
    with pytest.raises(ValueError, match="needs a finite time"):
        tr.trends.forget([2], after=3)


def test_a_late_frame_of_a_nozzle_that_recovered_starts_no_trend():
    """helper-117: a nozzle's trend ended (it recovered at frame 3); a copy of frame 2, older than that news, then
    started a new trend, and frame 4's dried estimate went on from it (frame 2 folded twice). It is stale: estimated,
    not folded; a later drying starts the new trend."""
    tr = DryingTracker(recovery_frames=1)
    for f, ids in ((1, [2]), (2, [2]), (3, [])):
        _traces(tr, _frame(f, {0: ids}), f, 0)
        _drying(tr, f, 0, ids)
    assert tr.trends_recovered == 1
    _traces(tr, _frame(2, {0: [2]}), 2, 0)  # frame 2 again, late
    late = _drying(tr, 2, 0, [2])
    assert np.isfinite(late[0].columns["fm"][0]) and np.isnan(late[0].columns["fm_trend"][0])
    assert tr.rows_stale == 1 and tr.trends.n_updates[tr.trends.ids == 2] == 0
    _traces(tr, _frame(4, {0: [2]}), 4, 0)
    new = _drying(tr, 4, 0, [2])[0].columns
    assert new["fm_trend"][0] == new["fm"][0] and np.isnan(new["fm_rate"][0])  # a new trend: its first estimate
    # a new clock (a restarted controller, stamps far back) starts over: frame 2's stamp is news there
    tr.trends.forget([2])
    _traces(tr, _frame(2, {0: [2]}), 2, 0, stamp=-1e4)
    assert np.isfinite(_drying(tr, 2, 0, [2])[0].columns["fm_trend"][0])


@pytest.mark.parametrize("traces_first", [True, False], ids=["traces_first", "drying_first"])
def test_a_list_with_entries_left_out_ends_no_trend(traces_first):
    """helper-93: an entry fe could not read (an id written 3.0, a class it does not know) was left out of the list,
    and its nozzle's trend ended as recovered. A list that is not complete ends no trend; the next complete one does."""
    tr = DryingTracker(recovery_frames=1)
    for f in (1, 2):
        _traces(tr, _frame(f, {0: [2]}), f, 0)
        _drying(tr, f, 0, [2])
    x = _frame(3, {0: [2]})
    if traces_first:
        _traces(tr, x, 3, 0)
        tr.add_drying(3, [], first_nozzle=0, n_nozzles=RANGE, complete=False)
    else:
        tr.add_drying(3, [], first_nozzle=0, n_nozzles=RANGE, complete=False)
        _traces(tr, x, 3, 0)
    assert tr.trends_recovered == 0 and 2 in tr.trends.ids
    _traces(tr, _frame(4, {0: []}), 4, 0)
    _drying(tr, 4, 0, [])
    assert tr.trends_recovered == 1


def test_an_empty_list_releases_its_range_and_a_list_without_traces_is_counted_not_estimated():
    x = _frame(2)
    tr = DryingTracker(max_pending=2)
    assert _traces(tr, x, 1, 1) == [] and tr.pending == (1, 0)
    assert _drying(tr, 1, 1, []) == [] and tr.pending == (0, 0)  # nothing dried: traces released
    assert tr.ranges_joined == 1 and tr.ranges_estimated == 0
    # lists of frames whose traces never came (lost on the best-effort topic): held, then dropped
    for f in (10, 11, 12):
        assert _drying(tr, f, 0, DRIED[0]) == []
    assert tr.pending == (0, 2) and tr.drying_unmatched == 1
    assert _traces(tr, x, 10, 0) == []  # frame 10's list was the one dropped
    assert tr.estimates == 0 and tr.pending == (1, 2)
    # traces whose lists never come: the oldest dropped
    for f in (20, 21):
        _traces(tr, x, f, 2)
    assert tr.traces_unmatched == 1 and tr.pending == (2, 2)
    (e,) = _traces(tr, x, 11, 0)  # a held list still finds its traces
    assert e.frame_id == 11 and e.nozzles.tolist() == DRIED[0] and tr.estimates == 2


def test_a_list_without_a_range_applies_to_every_range_of_its_frame():
    x = _frame(3)
    tr = DryingTracker()
    _traces(tr, x, 4, 0)
    _traces(tr, x, 4, 1)
    _traces(tr, x, 3, 2)  # another frame: not touched
    out = tr.add_drying(4, DRIED[0] + DRIED[1])  # first_nozzle unknown
    assert [(e.first_nozzle, e.nozzles.tolist()) for e in out] == [(0, DRIED[0]), (8, DRIED[1])]
    assert tr.pending == (1, 1)
    # an older fdi sends one such list per range: they add up, and later ranges of the frame match
    assert tr.add_drying(4, DRIED[2]) == []
    (e,) = _traces(tr, x, 4, 2)
    assert e.first_nozzle == 16 and e.nozzles.tolist() == DRIED[2] and e.frame_id == 4


def test_invalid_rows_and_the_cap_cost_only_themselves():
    x = np.array(_frame(4))
    x[DRIED[1][0]] = np.nan
    tr = DryingTracker(max_estimates=2)
    _traces(tr, x, 1, 1)
    (e,) = _drying(tr, 1, 1, DRIED[1])  # 8, 9, 14: the cap keeps 8, 9; 8 is NaN
    assert e.nozzles.tolist() == [9] and tr.rows_invalid == 1
    tr.max_estimates = 64
    _traces(tr, x, 2, 1)
    (e,) = _drying(tr, 2, 1, DRIED[1])
    assert e.nozzles.tolist() == [9, 14]


def test_bad_input_is_refused_and_changes_nothing():
    x = _frame(5)
    tr = DryingTracker()
    with pytest.raises(ValueError, match="2-D"):
        tr.add_traces(x[0], first_nozzle=0, frame_id=1, stamp=1.0, sample_rate_hz=10e6)
    with pytest.raises(ValueError, match="first_nozzle"):
        tr.add_traces(x[:8], first_nozzle=-8, frame_id=1, stamp=1.0, sample_rate_hz=10e6)
    with pytest.raises(ValueError, match="outside the range"):
        tr.add_drying(1, [3, 30], first_nozzle=0, n_nozzles=8)
    with pytest.raises(ValueError, match=">= 1"):
        DryingTracker(max_pending=0)
    assert tr.pending == (0, 0) and tr.traces_received == tr.drying_received == 0


def test_a_restarted_controllers_first_frame_is_not_dropped_by_an_old_frames_late_list():
    """helper-117: the controller restarted (frame ids from 0 again); its frame 0's traces came before the old frame
    100's list, which dropped them as a frame before 100 whose list could not come. Stamped after that list, they
    are held; traces older than it are still dropped."""
    x = _frame(1)
    tr = DryingTracker()
    _traces(tr, x, 100, 0, stamp=1000.0)
    _traces(tr, x, 99, 0, stamp=999.0)  # an old frame whose list was lost
    _traces(tr, x, 0, 0, stamp=1000.2)  # the restarted controller's first frame
    (e,) = tr.add_drying(100, DRIED[0], first_nozzle=0, n_nozzles=RANGE, stamp=1000.0)
    assert e.frame_id == 100 and tr.traces_unmatched == 1 and tr.pending == (1, 0)  # frame 99's dropped
    (e,) = tr.add_drying(0, DRIED[0], first_nozzle=0, n_nozzles=RANGE, stamp=1000.2)
    assert e.frame_id == 0 and e.stamp == 1000.2 and tr.pending == (0, 0) and tr.traces_unmatched == 1


def test_traces_whose_list_cannot_come_are_dropped_when_a_later_list_comes():
    # fdi answers a range's messages in frame order: once frame 7's list for range 0 is here,
    # frames 5 and 6 of range 0 (which fdi never had: lost on the best-effort topic) get none,
    # and their traces (a whole message each) are not held until max_pending of them pile up
    x = _frame(5)
    tr = DryingTracker(max_pending=128)
    for f in (5, 6, 7):
        assert _traces(tr, x, f, 0) == []
    assert _traces(tr, x, 6, 1) == []  # another range: its own list may still come
    (e,) = _drying(tr, 7, 0, DRIED[0])
    assert e.frame_id == 7 and e.nozzles.tolist() == DRIED[0]
    assert tr.pending == (1, 0) and tr.traces_unmatched == 2
    (e,) = _drying(tr, 6, 1, DRIED[1])
    assert e.first_nozzle == 8 and tr.pending == (0, 0) and tr.traces_unmatched == 2
    # a list that comes before its traces drops nothing that can still be joined
    assert _drying(tr, 9, 2, DRIED[2]) == [] and _traces(tr, x, 8, 2) == []
    assert tr.pending == (1, 1)
    (e,) = _traces(tr, x, 9, 2)
    assert e.frame_id == 9 and tr.pending == (1, 0) and tr.traces_unmatched == 2


def test_a_sample_no_sensor_can_produce_is_out_of_range_not_an_estimate():
    """A finite spike beyond 5x the head's ADC range is invalid (as fdi screens it); the other rows go on."""
    tr = DryingTracker(max_estimates=64)
    x = _frame(1)[:RANGE].copy()
    x[2, 100] = 1e30
    r = tr.estimate_rows(x[[2, 5]], np.array([2, 5]), stamp=0.0, sample_rate_hz=10e6)
    assert list(r.reasons) == ["out_of_range", ""]
    assert np.isnan(r.columns["fm"][0]) and np.isfinite(r.columns["fm"][1])
    assert tr.max_abs_v == 10.0  # 5x the default head's +-2 V
    with pytest.raises(ValueError, match="max_abs_v"):
        DryingTracker(max_abs_v=0.0)


def test_an_estimate_that_means_a_viscosity_of_zero_or_less_is_not_an_estimate():
    """A row the ink-channel model does not describe (here a ringing with no damping at all, as the actuator
    alone of an empty channel rings on some heads) can come out with an f_m that means a viscosity <= 0: that
    row has the reason ``viscosity_not_positive`` and empty values; the others are estimated as the
    estimator gives them."""
    from inkdiag_core.drying_tracker import NONPHYSICAL_REASON

    x = _frame(1)[:6].copy()  # nozzles 2 and 5 deeply dried
    t = np.arange(x.shape[1]) / 10e6
    x[[1, 4]] = 0.5 * np.sin(2 * np.pi * 237e3 * t)  # the default head's healthy mode, undamped
    raw = estimate_fm_batch(x, InkChannelModel(), 10e6, method="vp_cal")
    neg = raw.viscosity <= 0
    assert list(np.flatnonzero(neg)) == [1, 4]  # what the estimator itself says
    tr = DryingTracker()
    r = tr.estimate_rows(x, np.arange(6), stamp=0.0, sample_rate_hz=10e6)
    assert list(r.reasons) == ["", NONPHYSICAL_REASON, "", "", NONPHYSICAL_REASON, ""] and tr.estimates == 4
    assert np.isnan(r.columns["viscosity"][neg]).all() and np.isnan(r.columns["fm_trend"][neg]).all()
    np.testing.assert_allclose(r.columns["viscosity"][~neg], raw.viscosity[~neg])


def test_a_fit_that_ends_at_its_search_intervals_edge_is_not_an_estimate():
    """helper-109's QA: fully blocked nozzles came out of estimate as f_m -6.3e6 1/s, 22x the ink's viscosity,
    and empty channels at exactly the interval's upper edge, with no reason. The fit's edge is now said
    (``at_search_bound``, empty values); drying nozzles, to 10x the ink's viscosity, are estimated as before."""
    from inkdiag_core import FaultClass, HeadProfile
    from inkdiag_core.drying_tracker import AT_BOUND_REASON

    classes = [FaultClass.FULLY_BLOCKED, FaultClass.EMPTY_CHANNEL_2, FaultClass.SLIGHTLY_DRIED,
               FaultClass.INTERMEDIATELY_DRIED, FaultClass.DEEPLY_DRIED, FaultClass.HEALTHY_NOZZLE]
    sim = HeadProfile.default().simulate({c: 20 for c in classes}, seed=3)
    lab = np.asarray(sim.label_values())
    raw = estimate_fm_batch(sim.traces, InkChannelModel(), 10e6, method="vp_cal")
    from inkdiag_core.estimation.base import default_bounds, model_matrices

    A, _, B_f, _ = model_matrices(InkChannelModel())
    vp = estimate_fm_batch(sim.traces, InkChannelModel(), 10e6, method="vp")
    np.testing.assert_allclose(vp.fm[lab == "fully_blocked"], default_bounds(A, B_f)[0], rtol=1e-6)  # the edge
    want = np.isin(lab, ["fully_blocked", "empty_channel_2"])
    np.testing.assert_array_equal(raw.at_bound, want)
    np.testing.assert_array_equal(vp.at_bound, want)
    assert raw[int(np.argmax(want))].at_bound and not raw[int(np.argmin(want))].at_bound  # FmEstimate too
    tr = DryingTracker()
    r = tr.estimate_rows(sim.traces, np.arange(lab.size), stamp=0.0, sample_rate_hz=10e6)
    assert (r.reasons[want] == AT_BOUND_REASON).all() and (r.reasons[~want] == "").all()
    assert tr.rows_no_fit == int(np.count_nonzero(want)) and tr.rows_invalid == 0  # fe's /diagnostics counts
    assert np.isnan(r.columns["fm"][want]).all() and tr.estimates == int(np.count_nonzero(~want))
    np.testing.assert_allclose(r.columns["fm"][~want], raw.fm[~want])


def test_a_trace_the_drying_model_does_not_describe_is_a_misfit():
    """helper-113's QA: an undamped sine listed as dried came out of fe as an estimate. A row whose fitted drying
    channel leaves more than MISFIT_REL of its variation, and more than MISFIT_NOISE_FACTOR times the profile's
    noise, is ``misfit`` (empty values); dried rows are estimated, at a low SNR too."""
    from inkdiag_core import FaultClass, HeadProfile
    from inkdiag_core.drying_tracker import MISFIT_REASON, MISFIT_REL

    p = HeadProfile.default()
    dried = [FaultClass.SLIGHTLY_DRIED, FaultClass.INTERMEDIATELY_DRIED, FaultClass.DEEPLY_DRIED]
    sim = p.simulate({**{c: 20 for c in dried}, FaultClass.MATURE_AIR_BUBBLE: 10}, seed=5)
    lab = np.asarray(sim.label_values())
    t = np.arange(p.n_samples) / p.sample_rate_hz
    sines = 0.3 * np.sin(2 * np.pi * 1.2 * p.healthy_mode()[0] * t)[None, :] + np.random.default_rng(1).normal(
        0.0, p.noise_std_v(), (3, t.size))
    rows = np.vstack([sim.traces, sines])
    want = np.concatenate([lab == "mature_air_bubble", np.ones(3, bool)])
    vp = estimate_fm_batch(rows, p, p.sample_rate_hz, method="vp")
    assert (vp.residual_rel[~want] < MISFIT_REL).all() and (vp.residual_rel[want] > MISFIT_REL).all()
    dt = estimate_fm_batch(rows[:2], InkChannelModel(), 10e6, method="dt", x0=np.zeros(3))
    assert np.isnan(dt.residual_rel).all()
    tr = DryingTracker(profile=p, method="vp")
    r = tr.estimate_rows(rows, np.arange(want.size), stamp=0.0, sample_rate_hz=p.sample_rate_hz)
    assert (r.reasons[want] == MISFIT_REASON).all() and (r.reasons[~want] == "").all(), r.reasons
    assert np.isnan(r.columns["fm"][want]).all() and tr.rows_no_fit == int(want.sum())
    # a dried row drowned in noise leaves a large share unexplained, but only noise: estimated (or below_noise)
    rng = np.random.default_rng(2)
    noisy = sim.traces[lab != "mature_air_bubble"] + rng.normal(0.0, 0.04, (60, t.size))  # about 6 dB
    assert (estimate_fm_batch(noisy, p, p.sample_rate_hz, method="vp").residual_rel > MISFIT_REL).sum() > 40
    r = DryingTracker(profile=p.replace(sensor={"snr_db": None, "noise_std_v": 0.04}), method="vp").estimate_rows(
        noisy, np.arange(60), stamp=0.0, sample_rate_hz=p.sample_rate_hz)
    assert MISFIT_REASON not in set(r.reasons) and (r.reasons == "").sum() > 40, r.reasons


def test_a_row_resting_on_the_adcs_end_code_is_clipped_for_estimation():
    """helper-109's QA: traces whose peaks sat 3-4 samples on the ADC's rail (fewer than screening's 0.5 us) were
    estimated 13-16 % low with no reason. With a profile that states its ADC range, two samples at an end code
    make the row ``clipped``; the rest of the frame is estimated as before."""
    from inkdiag_core import FaultClass, HeadProfile, screen_traces

    p = HeadProfile.default()
    assert "adc_range_v" in p.sensor
    x = p.simulate({FaultClass.SLIGHTLY_DRIED: 6}, seed=4).traces.astype(np.float64)
    top = 2.0 - 4.0 / 2 ** 12  # the 12-bit ADC's highest code, V
    y = x.copy()
    y[:3] = np.clip(y[:3] * (2.8 / np.abs(y[:3]).max(axis=1, keepdims=True)), -2.0, top)
    assert screen_traces(y, sample_rate_hz=10e6, max_abs_v=10.0)[0].all()  # shorter than screening's clipped run
    tr = DryingTracker(profile=p, recovery_frames=1)
    r = tr.estimate_rows(y, np.arange(6), stamp=0.0, sample_rate_hz=10e6)
    assert list(r.reasons) == ["clipped"] * 3 + [""] * 3 and np.isnan(r.columns["fm"][:3]).all()
    ref = DryingTracker(profile=p, recovery_frames=1).estimate_rows(x, np.arange(6), stamp=0.0, sample_rate_hz=10e6)
    np.testing.assert_allclose(r.columns["fm"][3:], ref.columns["fm"][3:])
    # a profile that does not state its ADC range (the default 2 V assumed, not known): no rail to rest on
    loose = p.replace(sensor={"adc_range_v": None})
    assert "adc_range_v" not in loose.sensor
    assert "clipped" not in DryingTracker(profile=loose, method="vp").estimate_rows(  # vp: no vp_cal fit (seconds)
        y, np.arange(6), stamp=0.0, sample_rate_hz=10e6).reasons
    # nor one of a coarse ADC, whose end codes span much of its range (helper-110: 1 bit, every row clipped; a
    # profile now takes 4 bits or more, and a healthy trace of at least one step)
    from inkdiag_core.drying_tracker import MIN_RAIL_BITS, adc_rails

    assert adc_rails(p.replace(sensor={"adc_bits": MIN_RAIL_BITS - 1})) is None
    assert adc_rails(p.replace(sensor={"adc_bits": MIN_RAIL_BITS})) is not None
    coarse = p.replace(sensor={"adc_bits": 5})
    assert "clipped" not in DryingTracker(profile=coarse, method="vp").estimate_rows(
        x, np.arange(6), stamp=0.0, sample_rate_hz=10e6).reasons
    # a railed row is no news of a recovery either: it ends no trend; a row on the scale does
    tr.estimate_rows(x, np.arange(6), stamp=1.0, sample_rate_hz=10e6)
    assert tr.end_recovered([0, 1], y[:2], stamp=2.0, sample_rate_hz=10e6) == 0
    assert tr.end_recovered([0, 1], x[:2], stamp=2.0, sample_rate_hz=10e6) == 2


def test_a_row_that_does_not_ring_above_the_sensor_noise_is_not_estimated():
    """White noise came out as f_m -4.6e6 1/s, and traces a thousand times too small as any other, with no reason
    (helper-103's QA): with a profile, a row whose AC rms is at most 2x its noise_std_v is ``below_noise``."""
    from inkdiag_core import HeadProfile
    from inkdiag_core.drying_tracker import BELOW_NOISE_REASON

    head = HeadProfile.default()
    x = _frame(1)[:6].astype(np.float64)  # nozzles 2 and 5 deeply dried
    x[1] = np.random.default_rng(0).normal(0.0, head.noise_std_v(), x.shape[1])  # a nozzle that did not fire
    x[5] *= 1e-3  # a dried row in kilovolts
    tr = DryingTracker(profile=head)
    assert tr.min_ac_rms_v == pytest.approx(2 * head.noise_std_v())
    r = tr.estimate_rows(x, np.arange(6), stamp=0.0, sample_rate_hz=10e6)
    assert list(r.reasons) == ["", BELOW_NOISE_REASON, "", "", "", BELOW_NOISE_REASON] and tr.estimates == 4
    assert np.isnan(r.columns["fm"][[1, 5]]).all() and np.isfinite(r.columns["fm"][[0, 2, 3, 4]]).all()
    assert tr.rows_invalid == 2
    ref = DryingTracker(profile=head).estimate_rows(x[[0, 2, 3, 4]], np.array([0, 2, 3, 4]), stamp=0.0,
                                                   sample_rate_hz=10e6)
    np.testing.assert_array_equal(r.columns["fm"][[0, 2, 3, 4]], ref.columns["fm"])  # the others as alone
    assert BELOW_NOISE_REASON not in DryingTracker().estimate_rows(  # no profile: no noise level to go by
        x, np.arange(6), stamp=0.0, sample_rate_hz=10e6).reasons


def test_a_repeated_or_late_frame_is_estimated_but_not_folded_into_the_trends():
    """A controller that sends a frame twice, or a frame that arrives after a later one, must not move the
    trends as a new measurement would: its estimates come out (with a note), its trend columns are NaN,
    and the trends end where the frames in order leave them. A nozzle's trend is its own clock: a late
    frame whose nozzles were not updated since (the range's frame in between listed none) is folded."""
    frames = {k: _frame(k) for k in range(1, 6)}

    def run(order, listed=lambda k: DRIED[0]):
        tr, out = DryingTracker(recovery_frames=1), []
        for k in order:
            _traces(tr, frames[k], k, 0)
            out += _drying(tr, k, 0, listed(k))
        return tr, out

    ref, _ = run([1, 2, 4])
    tr, out = run([1, 2, 2, 4, 3])  # frame 2 twice; frame 3 after frame 4
    assert tr.rows_stale == 4 and ref.rows_stale == 0 and tr.trend_restarts == 0 and tr.ranges_estimated == 5
    stale = [e for e in out if e.note]
    assert [e.frame_id for e in stale] == [2, 3]
    assert all("2 estimate(s) at" in e.note and "not folded into their nozzle's trend" in e.note for e in stale)
    for e in stale:
        assert np.isnan(e.columns["fm_trend"]).all() and np.isnan(e.columns["fm_rate"]).all()
        direct = estimate_fm_batch(frames[e.frame_id][DRIED[0]], InkChannelModel(), 10e6)
        np.testing.assert_array_equal(e.columns["fm"], direct.fm)  # the estimates themselves are given
    np.testing.assert_array_equal(tr.trends.x, ref.trends.x)  # the trends of frames 1, 2, 4, in order
    np.testing.assert_array_equal(tr.trends.n_updates, [3, 3])
    # frame 3 listed no dried nozzle (they recovered: their trends of frame 1 end); frame 2 comes after it: older
    # than that news, so stale, not a new trend (helper-117: it was folded as one)
    tr, out = run([1, 3, 2], listed=lambda k: [] if k == 3 else DRIED[0])
    assert tr.rows_stale == 2 and [e.frame_id for e in out if e.note] == [2] and tr.trends.n_updates.tolist() == [0, 0]
    assert tr.trends_recovered == 2


def test_a_restarted_clock_restarts_the_trends_instead_of_freezing_them():
    """Stamps that jump back 10 s or more (a controller restarted, a recording replayed again) are a new
    clock: each nozzle's trend starts again from the frame, said in the note, not left frozen until the
    new stamps pass the old ones."""
    tr = DryingTracker()
    for k, stamp in ((1, 100.0), (2, 100.5), (3, 1.0), (4, 1.5)):
        _traces(tr, _frame(k), k, 0, stamp=stamp)
        e, = _drying(tr, k, 0, DRIED[0])
        assert np.isfinite(e.columns["fm_trend"]).all()
        assert ("2 nozzle trend(s) restarted" in e.note) == (k == 3)
        assert np.isfinite(e.columns["fm_rate"]).all() == (k in (2, 4))  # a rate from a trend's second frame
    assert tr.trend_restarts == 2 and tr.rows_stale == 0 and tr.trends.n_updates.tolist() == [2, 2]
    assert tr.trends.t.tolist() == [1.5, 1.5]
    # a nozzle first seen again on the new clock restarts too, though its old stamp (100.5) is not 10 s after
    # this one: range 1's nozzles, last at 100.5, listed at 95
    tr = DryingTracker()
    for k, stamp, r in ((1, 100.0, 1), (2, 100.5, 1), (3, 1.0, 0), (4, 95.0, 1)):
        _traces(tr, _frame(k), k, r, stamp=stamp)
        e, = _drying(tr, k, r, DRIED[r])
        assert np.isfinite(e.columns["fm_trend"]).all() and (("restarted" in e.note) == (k == 4))
    assert tr.trend_restarts == 3 and tr.rows_stale == 0


def test_a_late_list_or_an_unreadable_trace_does_not_end_a_trend():
    """helper-89: a list of an older frame (late), or a range whose trace of the nozzle screening refuses (fdi labels
    it invalid, not dried), is no news of a recovery: the trend goes on."""
    tr = DryingTracker(recovery_frames=1)
    for f in (1, 2):
        _traces(tr, _frame(f, {0: [2]}), f, 0)
        _drying(tr, f, 0, [2])
    late = _frame(0, {0: []})
    _traces(tr, late, 0, 0, stamp=0.5)  # frame 0, stamped before the trend's updates, comes last
    _drying(tr, 0, 0, [])
    clipped = _frame(3, {0: [2]})
    clipped[2, 100:140] = clipped[2].max()
    _traces(tr, clipped, 3, 0)
    assert _drying(tr, 3, 0, []) == []
    nan = _frame(4, {0: [2]})
    nan[2, 7] = np.nan
    _drying(tr, 4, 0, [])  # the list first, then the traces
    _traces(tr, nan, 4, 0)
    assert tr.trends_recovered == 0 and tr.trends.n_updates[tr.trends.ids == 2] == 2
    _traces(tr, _frame(5, {0: []}), 5, 0)  # a readable healthy trace, left out: recovered
    _drying(tr, 5, 0, [])
    assert tr.trends_recovered == 1 and tr.trends.n_updates[tr.trends.ids == 2] == 0
