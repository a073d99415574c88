"""FmTrend: a Kalman trend of f_m, against closed-form cases."""

import math

import numpy as np
import pytest

from inkdiag_core import FmTrend, InkChannelParams, deeply_dried_fm, viscosity_to_fm
from inkdiag_core.faults import MECHANISMS, FaultClass


def test_deeply_dried_level_is_the_class_edge():
    p = InkChannelParams()
    k = MECHANISMS[FaultClass.DEEPLY_DRIED].low
    assert deeply_dried_fm(p) == pytest.approx(float(viscosity_to_fm(p, k * p.mu)))
    assert deeply_dried_fm() < 0


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_tracks_a_noisy_ramp_and_predicts_the_crossing(seed):
    rng = np.random.default_rng(seed)
    fm0, rate, deep = -4e5, -5e4, -1.4e6
    tr = FmTrend(fm_deep=deep)
    ts = np.arange(0, 10, 0.2)
    truth = fm0 + rate * ts
    for t, f in zip(ts, truth):
        tr.update(t, f + 0.03 * abs(f) * rng.standard_normal(), 0.01 * abs(f))
    assert abs(tr.fm - truth[-1]) < 2.5 * tr.fm_std  # within its own uncertainty
    assert tr.fm_std < 0.03 * abs(truth[-1])  # and that is smaller than one measurement's
    assert tr.rate == pytest.approx(rate, rel=0.2)
    eta_true = (deep - truth[-1]) / rate
    assert tr.eta_deep_s == pytest.approx(eta_true, rel=0.3)


def test_edge_cases():
    tr = FmTrend(fm_deep=-1e6)
    assert math.isnan(tr.fm) and math.isnan(tr.rate) and math.isnan(tr.eta_deep_s)
    tr.update(0.0, -5e5, 1e4)
    assert tr.fm == -5e5 and math.isnan(tr.rate) and math.isnan(tr.eta_deep_s)
    tr.update(1.0, float("nan"), 1e4)  # ignored
    assert tr.n_updates == 1
    tr.update(1.0, -1.2e6, 1e4)
    tr.update(2.0, -1.3e6, 1e4)
    assert tr.eta_deep_s == 0.0
    rising = FmTrend(fm_deep=-1e6)
    for t in range(5):
        rising.update(t, -5e5 + 1e4 * t, 1e3)
    assert rising.rate > 0 and math.isnan(rising.eta_deep_s)
    with pytest.raises(ValueError):
        FmTrend(accel_std=0)


def test_a_late_entry_before_a_recovery_on_the_same_clock_is_stale_whatever_the_trends_clock():
    """helper-119: a nozzle whose trend was last updated on an old clock, ended (forget) on the new one; an entry of
    the new clock older than that news started a new trend. The news's own clock decides, not the trend's."""
    from inkdiag_core.trend import FmTrendBank

    b = FmTrendBank()

    def fold(t, ids):
        return b.fold_newer(t, ids, np.full(len(ids), -1e5), np.full(len(ids), 1e3))[3]

    fold(100.0, [5]), fold(1000.0, [7]), fold(500.0, [7])  # 1000 -> 500: a new clock
    b.forget([5], before=600.0)  # nozzle 5's trend (old clock) ends at 600 s, on the new clock
    assert not fold(550.0, [5])[0]  # older than that news: stale
    assert fold(650.0, [5])[0] and b.n_updates[b.ids == 5] == 1  # newer: a new trend
