"""Frames are screened row by row."""

import numpy as np
import pytest

from inkdiag_core.screening import screen_traces


def test_screening_flags_each_kind_of_bad_row():
    t = np.arange(512) / 10e6
    good = np.exp(-1e5 * t) * np.cos(2 * np.pi * 237e3 * t)
    rows = np.tile(good, (5, 1))
    rows[1, 7] = np.nan
    rows[2] = 0.25
    rows[3] = np.clip(rows[3] * 2, -0.8, 0.8)
    rows[4, 100] = np.inf
    valid, reasons = screen_traces(rows)
    assert valid.tolist() == [True, False, False, False, False]
    assert reasons.tolist() == ["", "non_finite", "flat", "clipped", "non_finite"]


def test_screening_rejects_wrong_shape():
    with pytest.raises(ValueError, match="2-D"):
        screen_traces(np.zeros(5))


def test_quantised_simulated_traces_are_not_flagged_clipped():
    from inkdiag_core import FaultClass, simulate

    sim = simulate({c: 300 for c in FaultClass}, seed=0)  # 12-bit ADC, peaks repeat codes
    valid, reasons = screen_traces(sim.traces)
    assert valid.all(), sorted(set(reasons[~valid]))


def _screen_row(row, flat_tol, clip_run):
    """Reference: one row, read plainly."""
    if not np.all(np.isfinite(row)):
        return "non_finite"
    hi, lo = row.max(), row.min()
    if hi - lo <= flat_tol:
        return "flat"
    for extreme in (hi, lo):
        run = 0
        for v in row:
            run = run + 1 if v == extreme else 0
            if run >= clip_run:
                return "clipped"
    return ""


@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.int16])
def test_screening_matches_a_row_by_row_reading_on_random_frames(dtype):
    rng = np.random.default_rng(7)
    for _ in range(60):
        n, m = int(rng.integers(1, 25)), int(rng.integers(2, 40))
        x = (rng.integers(-3, 4, (n, m)) if dtype is np.int16 else rng.standard_normal((n, m)) * 3).astype(dtype)
        for _ in range(int(rng.integers(0, 6))):
            i, a, k = int(rng.integers(n)), int(rng.integers(m)), int(rng.integers(5))
            if k == 0 and dtype is not np.int16:
                x[i, a] = rng.choice([np.nan, np.inf, -np.inf])
            elif k == 1:
                x[i] = x[i, 0]
            else:  # a plateau at the row's max or min
                x[i, a:a + int(rng.integers(1, 8))] = x[i].max() if k == 2 else x[i].min()
        for flat_tol, clip_run in ((1e-6, 5), (0.5, 2), (0.0, 3)):
            valid, reasons = screen_traces(x, flat_tol=flat_tol, clip_run=clip_run)
            want = [_screen_row(r, flat_tol, clip_run) for r in x]
            assert list(reasons) == want and list(valid) == [w == "" for w in want]


@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.int16])
def test_screening_flags_rows_beyond_the_sensor_range_without_warnings(dtype):
    import warnings

    t = np.arange(512) / 10e6
    scale, limit = (500.0, 1000.0) if dtype == np.int16 else (1.5, 10.0)  # int16: ADC codes
    good = (scale * np.exp(-1e4 * t) * np.cos(2 * np.pi * 237e3 * t)).astype(dtype)
    big = np.iinfo(dtype).max if dtype == np.int16 else np.finfo(dtype).max
    rows = np.tile(good, (6, 1))
    rows[1, 50] = big  # one spike to the dtype's largest value
    rows[2, 50] = -big
    rows[3, ::2], rows[3, 1::2] = big, -big  # alternating extremes
    rows[4, 70] = 2000 if dtype == np.int16 else 1e30  # finite, far beyond any ADC
    rows[5, 60] = limit  # at the limit: still valid
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no RuntimeWarning may reach stderr
        valid, reasons = screen_traces(rows, max_abs_v=limit)
        _, unchecked = screen_traces(rows)
    assert reasons.tolist() == ["", "out_of_range", "out_of_range", "out_of_range", "out_of_range", ""]
    assert valid.tolist() == [True, False, False, False, False, True]
    # without a limit no row is out of range, and alternating extremes are not "flat"
    # (an int16 range 32767 - -32768 wraps to -1)
    assert "out_of_range" not in unchecked.tolist() and unchecked[3] != "flat"


def test_screening_non_finite_takes_precedence_and_limit_is_checked():
    rows = np.zeros((1, 16))
    rows[0, :2] = np.nan, 1e30
    assert screen_traces(rows, max_abs_v=10.0)[1].tolist() == ["non_finite"]
    with pytest.raises(ValueError, match="max_abs_v must be > 0"):
        screen_traces(rows, max_abs_v=0.0)


def test_rings_above_noise_tells_white_noise_from_ringing_where_the_sampling_can():
    """Rows that do not ring above their own noise (nozzles that did not fire), for calibration and baselines;
    a head sampled at fewer than 10 samples a period of its mode is not checked: its ringing's own second
    differences read as noise (a 169 kHz head at 1 MHz x 64 had every noise-free healthy trace refused)."""
    from inkdiag_core.screening import RINGING_MIN_SAMPLES_PER_PERIOD, rings_above_noise

    rng = np.random.default_rng(0)
    fs, n = 10e6, 512
    t = np.arange(n) / fs
    ring = np.exp(-t / 15e-6) * np.sin(2 * np.pi * 237e3 * t)  # the default head's mode, 42 samples a period
    x = np.vstack([ring + rng.normal(0, 0.03, (3, n)), rng.normal(0, 0.01, (3, n)), 1e-3 * ring[None]])
    want = [True, True, True, False, False, False, True]  # a scale of its own: rings, noise-free
    for mode in (None, 237e3):
        np.testing.assert_array_equal(rings_above_noise(x, sample_rate_hz=fs, mode_hz=mode), want)
    assert not rings_above_noise(rng.normal(0, 1, (2000, 64)), sample_rate_hz=fs, mode_hz=237e3).any()
    sparse = np.exp(-np.arange(64) / 20) * np.sin(2 * np.pi * (np.arange(64) / 4 + 0.125))  # 4 samples a period
    for mode in (None, fs / 4):
        assert rings_above_noise(sparse[None], sample_rate_hz=fs, mode_hz=mode).all()
    assert not rings_above_noise(sparse[None], sample_rate_hz=fs, mode_hz=fs / RINGING_MIN_SAMPLES_PER_PERIOD).all()
    assert rings_above_noise(np.zeros((0, n)), sample_rate_hz=fs).shape == (0,)
