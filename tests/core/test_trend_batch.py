"""Batched f_m trend: predict/update apart, FmTrendBank's arrays against the per-nozzle filter.

``_RefTrend`` is the per-nozzle ``FmTrend`` as it was before the batch rewrite
(commit 9f0912a), kept verbatim as the reference the batch code must match.
"""

import math

import numpy as np
import pytest

from inkdiag_core import FmTrend, FmTrendBank
from inkdiag_core.trend import eta_deep, measurement_variance, predict, update


class _RefTrend:
    def __init__(self, accel_std=5e3, rel_floor=0.05, fm_deep=-1e6):
        self.accel_std, self.rel_floor, self.fm_deep = accel_std, rel_floor, fm_deep
        self.x = np.zeros(2)
        self.P = np.diag([np.inf, np.inf])
        self.t = math.nan
        self.n_updates = 0

    def update(self, t, fm, fm_std=0.0):
        t, fm = float(t), float(fm)
        if not math.isfinite(fm):
            return self
        r = (fm_std if math.isfinite(fm_std) else 0.0) ** 2 + (self.rel_floor * fm) ** 2
        r = max(r, 1e-12)
        if self.n_updates == 0:
            self.x = np.array([fm, 0.0])
            self.P = np.diag([r, (abs(fm) + math.sqrt(r)) ** 2])
        else:
            dt = t - self.t if t > self.t else 0.0
            F = np.array([[1.0, dt], [0.0, 1.0]])
            q = self.accel_std**2
            Q = q * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
            self.x = F @ self.x
            self.P = F @ self.P @ F.T + Q
            S = self.P[0, 0] + r
            K = self.P[:, 0] / S
            self.x = self.x + K * (fm - self.x[0])
            self.P = self.P - np.outer(K, self.P[0, :])
        self.t = max(t, self.t) if self.n_updates else t
        self.n_updates += 1
        return self

    @property
    def fm(self):
        return float(self.x[0]) if self.n_updates else math.nan

    @property
    def rate(self):
        return float(self.x[1]) if self.n_updates >= 2 else math.nan

    @property
    def eta_deep_s(self):
        if self.n_updates == 0:
            return math.nan
        if self.x[0] <= self.fm_deep:
            return 0.0
        if self.n_updates < 2 or not self.x[1] < 0:
            return math.nan
        return float((self.fm_deep - self.x[0]) / self.x[1])


def _random_states(rng, n):
    x = np.column_stack([-1e6 * rng.random(n), -1e5 * rng.standard_normal(n)])
    A = rng.standard_normal((n, 2, 2)) * np.array([1e4, 1e3])[None, :, None]
    return x, A @ A.transpose(0, 2, 1) + 1e2 * np.eye(2)


def test_predict_and_update_are_batched_kalman_steps():
    rng = np.random.default_rng(0)
    n = 7
    x, P = _random_states(rng, n)
    dt = np.r_[0.0, rng.random(n - 1)]
    z, r = x[:, 0] + 1e4 * rng.standard_normal(n), 1e8 * (1 + rng.random(n))
    x0, P0 = x.copy(), P.copy()
    xp, Pp = predict(x, P, dt, 5e3)
    u = update(xp, Pp, z, r)
    assert xp.shape == (n, 2) and Pp.shape == (n, 2, 2) and u.K.shape == (n, 2)
    assert np.array_equal(x, x0) and np.array_equal(P, P0)  # pure
    assert np.array_equal(xp[0], x[0]) and np.array_equal(Pp[0], P[0])  # dt = 0: no step
    H = np.array([[1.0, 0.0]])
    for i in range(n):  # textbook matrix form, one nozzle at a time
        F = np.array([[1.0, dt[i]], [0.0, 1.0]])
        Q = 5e3**2 * np.array([[dt[i] ** 3 / 3, dt[i] ** 2 / 2], [dt[i] ** 2 / 2, dt[i]]])
        xi, Pi = F @ x[i], F @ P[i] @ F.T + Q
        np.testing.assert_allclose(xp[i], xi, rtol=1e-12)
        np.testing.assert_allclose(Pp[i], Pi, rtol=1e-12)
        S = (H @ Pi @ H.T)[0, 0] + r[i]
        K = (Pi @ H.T)[:, 0] / S
        y = z[i] - xi[0]
        assert u.S[i] == pytest.approx(S, rel=1e-12) and u.y[i] == pytest.approx(y, rel=1e-12)
        np.testing.assert_allclose(u.K[i], K, rtol=1e-12)
        np.testing.assert_allclose(u.x[i], xi + K * y, rtol=1e-12)
        np.testing.assert_allclose(u.P[i], (np.eye(2) - np.outer(K, H)) @ Pi, rtol=1e-9, atol=1e-6)
    # broadcasting a scalar time step and the per-row helpers
    xs, _ = predict(x, P, 0.5, 5e3)
    np.testing.assert_allclose(xs[:, 0], x[:, 0] + 0.5 * x[:, 1])
    assert measurement_variance([0.0, -1e5], [np.nan, 3.0], 0.05).tolist() == [1e-12, 9.0 + 5e3**2]
    e = eta_deep(np.array([[-2e6, 1.0], [-5e5, -1e5], [-5e5, 1e5], [-5e5, -1e5]]), [1, 2, 2, 1], -1e6)
    assert e[0] == 0.0 and e[1] == pytest.approx(5.0) and np.isnan(e[2]) and np.isnan(e[3])


def _sequence(seed, n_frames=40, n_ids=12):
    """Random frames: ids appear late, repeat within a frame, time goes back or stays, NaNs."""
    rng = np.random.default_rng(seed)
    t = 0.0
    frames = []
    for _ in range(n_frames):
        t = t + rng.choice([0.0, -0.3, 0.1, 0.7], p=[0.1, 0.1, 0.6, 0.2])
        k = int(rng.integers(0, 8))
        ids = rng.integers(0, n_ids, k) + rng.choice([0, 1000])
        fm = -4e5 - 1e6 * rng.random(k)
        fm[rng.random(k) < 0.15] = rng.choice([np.nan, np.inf, -np.inf])
        std = 1e4 * rng.random(k)
        std[rng.random(k) < 0.1] = np.nan
        frames.append((t, ids, fm, std))
    return frames


@pytest.mark.parametrize("seed", range(6))
def test_bank_matches_the_per_nozzle_filter(seed):
    kw = dict(accel_std=[5e3, 1e2, 3e5][seed % 3], rel_floor=[0.05, 0.0, 0.2][seed % 3], fm_deep=-1.1e6)
    bank, ref = FmTrendBank(**kw), {}
    for t, ids, fm, std in _sequence(seed):
        got = bank.update(t, ids, fm, std)
        want = np.full((3, ids.size), np.nan)
        for i, nz in enumerate(ids.tolist()):
            tr = ref.setdefault(nz, _RefTrend(**kw)).update(t, fm[i], std[i])
            want[:, i] = tr.fm, tr.rate, tr.eta_deep_s
        for g, w in zip(got, want):
            np.testing.assert_allclose(g, w, rtol=1e-12, atol=0)  # NaN where NaN
    assert sorted(ref) == bank.ids.tolist()  # a row per id seen, sorted
    for j, nz in enumerate(bank.ids.tolist()):  # and the state arrays themselves
        tr = ref[nz]
        assert bank.n_updates[j] == tr.n_updates
        if tr.n_updates:
            np.testing.assert_allclose(bank.x[j], tr.x, rtol=1e-12, atol=1e-9)
            np.testing.assert_allclose(bank.P[j], tr.P, rtol=1e-9, atol=1e-6)
            assert bank.t[j] == tr.t
        else:
            assert np.isnan(bank.t[j]) and np.isinf(bank.P[j, 0, 0])


@pytest.mark.parametrize("seed", range(3))
def test_single_nozzle_trend_matches_the_reference(seed):
    rng = np.random.default_rng(seed)
    a, b = FmTrend(fm_deep=-1.1e6), _RefTrend(fm_deep=-1.1e6)
    t = 0.0
    for _ in range(60):
        t += rng.choice([0.0, -0.2, 0.1, 0.5])
        f = rng.choice([np.nan, -4e5 - 1e6 * rng.random()], p=[0.1, 0.9])
        s = rng.choice([np.nan, 1e4 * rng.random()], p=[0.1, 0.9])
        n0, x0, t0 = a.n_updates, a.x.copy(), a.t
        a.update(t, f, s)
        b.update(t, f, s)
        if n0 >= 1 and np.isfinite(f):  # the update's residual and gain are kept
            dt = t - t0 if t > t0 else 0.0
            assert a.y == pytest.approx(f - (x0[0] + dt * x0[1]), rel=1e-9)
            assert 0 < a.K[0] < 1
        assert a.n_updates == b.n_updates and (a.t == b.t or (math.isnan(a.t) and math.isnan(b.t)))
        np.testing.assert_allclose([a.fm, a.rate, a.eta_deep_s], [b.fm, b.rate, b.eta_deep_s],
                                   rtol=1e-12, atol=0)


def test_bank_exposes_gain_and_residual_and_keeps_its_api():
    bank = FmTrendBank(fm_deep=-1e6)
    trend, rate, eta = bank.update(0.0, [5, 3], [-5e5, np.nan], [1e4, 1e4])
    assert bank.ids.tolist() == [3, 5] and bank.n_updates.tolist() == [0, 1]
    assert trend[0] == -5e5 and np.isnan(trend[1]) and np.isnan(rate).all() and np.isnan(eta).all()
    assert np.isnan(bank.y).all()  # a first update has no residual
    x_prior = bank.x[1].copy()
    trend, rate, eta = bank.update(1.0, [5], [-6e5], [1e4])
    assert bank.y[1] == pytest.approx(-6e5 - (x_prior[0] + x_prior[1]))
    assert 0 < bank.K[1, 0] < 1 and rate[0] < 0 and eta[0] > 0
    assert trend[0] == pytest.approx(bank.x[1, 0])
    snap = bank.trends[5]
    assert isinstance(snap, FmTrend) and snap.fm == trend[0] and snap.rate == rate[0]
    with pytest.raises(KeyError):
        bank.trend(4)
    with pytest.raises(ValueError, match="one entry each"):
        bank.update(2.0, [5, 3], [-6e5], [1e4])
    with pytest.raises(ValueError):
        FmTrendBank(accel_std=0)
    with pytest.raises(TypeError):
        FmTrendBank(bogus=1)


def test_fold_newer_folds_each_nozzle_once_and_only_after_its_last_update():
    bank = FmTrendBank(fm_deep=-1e6)
    trend, rate, eta, folded, restarted = bank.fold_newer(1.0, [5, 3, 5], [-5e5, np.nan, -6e5], [1e4] * 3)
    assert folded.tolist() == [True, False, False] and not restarted.any()  # 3: no estimate; 5 twice: once
    assert trend[0] == -5e5 and np.isnan(trend[1:]).all() and bank.ids.tolist() == [5] and bank.n_updates[0] == 1
    _, _, _, folded, _ = bank.fold_newer(1.0, [5, 3], [-6e5, -5e5], [1e4] * 2)  # 5 again at 1 s: stale
    assert folded.tolist() == [False, True] and bank.n_updates.tolist() == [1, 1]
    _, rate, _, folded, _ = bank.fold_newer(0.5, [5], [-6e5], [1e4])  # before its last update: stale
    assert not folded.any() and np.isnan(rate).all() and bank.t.tolist() == [1.0, 1.0]
    _, rate, _, folded, _ = bank.fold_newer(2.0, [5], [-6e5], [1e4])
    assert folded.all() and rate[0] < 0 and bank.n_updates.tolist() == [1, 2]
    _, _, _, folded, restarted = bank.fold_newer(-7.0, [5], [-7e5], [1e4], reset_after_s=10.0)  # 9 s back: late
    assert not folded.any() and not restarted.any() and bank.epoch == 0
    # 10 s before the latest frame folded (2 s): a new clock. Each nozzle's trend restarts at its next entry,
    # also nozzle 3's (last at 1 s, 9 s after -8 s) and one whose last update is before the new stamp
    trend, rate, _, folded, restarted = bank.fold_newer(-8.0, [5], [-7e5], [1e4])
    assert folded.all() and restarted.all() and trend[0] == -7e5 and np.isnan(rate[0]) and bank.epoch == 1
    _, _, _, folded, restarted = bank.fold_newer(-7.5, [3, 5], [-7e5, -7e5], [1e4] * 2)
    assert folded.tolist() == [True, True] and restarted.tolist() == [True, False]
    assert bank.n_updates.tolist() == [1, 2] and bank.t.tolist() == [-7.5, -7.5]
    # a nozzle updated by update() is on the bank's clock too: not restarted by its next fold_newer
    other = FmTrendBank()
    other.update(1.0, [7], [-5e5], [1e4])
    _, rate, _, folded, restarted = other.fold_newer(2.0, [7], [-6e5], [1e4])
    assert folded.all() and not restarted.any() and rate[0] < 0
    # a NaN entry does not hide the nozzle's next one
    _, _, _, folded, _ = bank.fold_newer(-7.0, [3, 3], [np.nan, -7e5], [1e4] * 2)
    assert folded.tolist() == [False, True]
    with pytest.raises(ValueError):
        bank.fold_newer(float("nan"), [5], [-6e5], [1e4])
