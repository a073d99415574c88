"""Tests of inkdiag_core.kpis: accuracy against known damped sinusoids, edge cases,
input validation, the reconstruction round trip and the scikit-learn contract."""

import numpy as np
import pytest
from sklearn.utils.estimator_checks import parametrize_with_checks

from inkdiag_core.kpis import (
    KPI_NAMES,
    MIN_KPI_SAMPLES,
    InvalidTraceError,
    KpiExtractor,
    extract_kpis,
    reconstruct,
)

FS = 10e6
N = 512
COL = {name: i for i, name in enumerate(KPI_NAMES)}


def damped_sinusoids(n, rng, *, snr_db=None, ring_samples=None, n_samples=N, fs=FS):
    """Seeded random damped sinusoids with known parameters.

    Frequencies log-uniform in 150 kHz - 2.2 MHz, damping ratios uniform in 0.02 - 0.4,
    phases uniform, amplitudes log-uniform in 0.1 - 10, DC uniform in +-amplitude.

    ``ring_samples=R`` limits the damping so that the envelope falls by at most 1/e over
    the first R samples: ``zeta * w0 * R / fs <= 1``.

    ``snr_db`` adds white Gaussian noise with variance ``mean_k(s_k**2) / 10**(snr/10)``,
    where ``s`` is the noise-free damped sinusoid without its DC (its mean power over the
    whole window).

    Returns float32 traces (n, n_samples) and the true (n, 5) [dc, f_d, zeta, A, phi].
    """
    f_d = np.exp(rng.uniform(np.log(150e3), np.log(2.2e6), n))
    w_d = 2 * np.pi * f_d
    zeta_max = np.full(n, 0.4)
    if ring_samples is not None:
        # zeta w0 = zeta w_d / sqrt(1 - zeta^2) <= fs / R  <=>  zeta <= 1 / sqrt(1 + (R w_d / fs)^2)
        zeta_max = np.minimum(zeta_max, 1 / np.sqrt(1 + (ring_samples * w_d / fs) ** 2))
    zeta = 0.02 + rng.uniform(0, 1, n) * (zeta_max - 0.02)
    phi = rng.uniform(-np.pi, np.pi, n)
    amp = np.exp(rng.uniform(np.log(0.1), np.log(10), n))
    dc = rng.uniform(-1, 1, n) * amp
    t = np.arange(n_samples) / fs
    w0 = w_d / np.sqrt(1 - zeta**2)
    s = amp[:, None] * np.exp(-(zeta * w0)[:, None] * t) * np.cos(w_d[:, None] * t + phi[:, None])
    if snr_db is not None:
        noise_var = (s**2).mean(axis=1) / 10 ** (snr_db / 10)
        s = s + rng.standard_normal(s.shape) * np.sqrt(noise_var)[:, None]
    return (dc[:, None] + s).astype(np.float32), np.column_stack([dc, f_d, zeta, amp, phi])


def errors(kpis, truth):
    """Per-trace errors: relative f, zeta, A; absolute phase (rad); |dc error| / A."""
    return {
        "frequency": np.abs(kpis[:, 1] / truth[:, 1] - 1),
        "damping": np.abs(kpis[:, 2] / truth[:, 2] - 1),
        "amplitude": np.abs(kpis[:, 3] / truth[:, 3] - 1),
        "phase": np.abs(np.angle(np.exp(1j * (kpis[:, 4] - truth[:, 4])))),
        "dc": np.abs(kpis[:, 0] - truth[:, 0]) / truth[:, 3],
    }


def test_kpi_names_order():
    assert KPI_NAMES == (
        "dc_offset", "dominant_frequency_hz", "damping_ratio", "amplitude",
        "phase_rad", "energy", "magnitude",
    )


def test_noise_free_accuracy_p95():
    traces, truth = damped_sinusoids(400, np.random.default_rng(0))
    kpis = extract_kpis(traces, FS)
    assert kpis.shape == (400, 7) and kpis.dtype == np.float64
    p95 = {k: np.percentile(v, 95) for k, v in errors(kpis, truth).items()}
    assert p95["frequency"] <= 0.005
    assert p95["damping"] <= 0.05
    assert p95["amplitude"] <= 0.02
    assert p95["phase"] <= 0.05
    assert p95["dc"] <= 0.01


def test_noisy_accuracy_p95_at_30db_ringing_traces():
    traces, truth = damped_sinusoids(
        400, np.random.default_rng(1), snr_db=30.0, ring_samples=20
    )
    p95 = {k: np.percentile(v, 95) for k, v in errors(extract_kpis(traces, FS), truth).items()}
    assert p95["frequency"] <= 0.01
    assert p95["damping"] <= 0.15
    assert p95["amplitude"] <= 0.05


def test_phase_is_wrapped_to_half_open_interval():
    t = np.arange(N) / FS
    y = -np.cos(2 * np.pi * 300e3 * t) * np.exp(-2e4 * t)  # phi = +-pi
    phase = extract_kpis(y, FS)[0, COL["phase_rad"]]
    assert -np.pi < phase <= np.pi
    assert abs(abs(phase) - np.pi) < 1e-4


def test_multi_mode_returns_stronger_mode():
    rng = np.random.default_rng(2)
    t = np.arange(N) / FS
    f_strong = rng.uniform(200e3, 400e3, 50)
    f_weak = rng.uniform(1.2e6, 2.0e6, 50)
    strong = 2.0 * np.exp(-5e4 * t) * np.cos(2 * np.pi * f_strong[:, None] * t + 0.3)
    weak = 0.5 * np.exp(-1e5 * t) * np.cos(2 * np.pi * f_weak[:, None] * t - 1.0)
    kpis = extract_kpis((0.2 + strong + weak).astype(np.float32), FS)
    np.testing.assert_allclose(kpis[:, COL["dominant_frequency_hz"]], f_strong, rtol=0.01)
    # Swap the strengths: the other mode is returned.
    kpis = extract_kpis((0.25 * strong + 4.0 * weak).astype(np.float32), FS)
    np.testing.assert_allclose(kpis[:, COL["dominant_frequency_hz"]], f_weak, rtol=0.01)


@pytest.mark.parametrize("level", [0.0, 1.5, -3.0])
def test_constant_trace_is_finite_and_flat(level):
    y = np.full((3, N), level, dtype=np.float32)
    kpis = extract_kpis(y, FS)
    assert np.isfinite(kpis).all()
    np.testing.assert_allclose(kpis[:, COL["dc_offset"]], level)
    np.testing.assert_array_equal(kpis[:, 1:], 0.0)


def test_non_sinusoidal_traces_give_finite_kpis():
    rng = np.random.default_rng(3)
    y = np.concatenate([
        rng.standard_normal((20, N)),  # white noise
        np.repeat((np.arange(N) > 100).astype(float)[None], 2, axis=0),  # step
        np.exp(-np.arange(N) / 30.0)[None],  # overdamped decay
        np.eye(N)[:3] * 1e3,  # impulses
    ])
    kpis = extract_kpis(y, FS)
    assert np.isfinite(kpis).all()
    assert (kpis[:, COL["damping_ratio"]] >= 0).all() and (kpis[:, COL["damping_ratio"]] < 1).all()


@pytest.mark.parametrize(
    ("dtype", "scales"),
    [
        (np.float32, [1e-11, 1e-6, 1e6, 1e17, 1e20, 1e36]),
        (np.float64, [1e-250, 1e-150, 1e-60, 1e60, 1e160, 1e250]),
    ],
)
def test_kpis_scale_with_the_trace_over_the_whole_dtype_range(dtype, scales):
    # The power spectrum of a float32 trace overflows above ~1e16 and underflows below
    # ~1e-12, that of a float64 trace above ~1e150: the KPIs must not notice.
    unit, _ = damped_sinusoids(30, np.random.default_rng(11), snr_db=30.0)
    unit = unit.astype(dtype)
    ref = extract_kpis(unit, FS)
    for scale in scales:
        with np.errstate(all="raise"):
            kpis = extract_kpis(unit * dtype(scale), FS)
        assert np.isfinite(kpis).all(), scale
        # frequency, damping ratio, phase unchanged; dc, amplitude, magnitude ~ scale;
        # energy ~ scale**2.
        np.testing.assert_allclose(kpis[:, [1, 2, 4]], ref[:, [1, 2, 4]], rtol=1e-4, atol=1e-6)
        rel = (kpis[:, [0, 3, 6]] / scale - ref[:, [0, 3, 6]]) / ref[:, [3]]
        assert np.abs(rel).max() <= 1e-4, scale
        with np.errstate(all="ignore"):
            expected = ref[:, 5] * scale * scale
        normal = (expected > 1e-290) & (expected < 1e300)
        np.testing.assert_allclose(kpis[normal, 5], expected[normal], rtol=1e-4)
        # where sum y**2 itself leaves float64, the energy saturates or underflows
        assert (kpis[expected >= 1e300, 5] == np.finfo(np.float64).max).all()
        assert (kpis[expected <= 1e-290, 5] <= 1e-289).all()


@pytest.mark.parametrize(
    "trace",
    [
        np.full(N, 3e38, dtype=np.float32) * np.where(np.arange(N) % 2, 1, -1).astype(np.float32),
        np.float32(3e38) * np.cos(2 * np.pi * 3e5 * np.arange(N) / FS).astype(np.float32),
        1.7e308 * np.cos(2 * np.pi * 3e5 * np.arange(N) / FS),
        np.full(N, 1e-45, dtype=np.float32) * (np.arange(N) % 3),
        5e-324 * (np.arange(N) % 4),
        np.full(N, 1e160),
        1e200 + np.cos(2 * np.pi * 3e5 * np.arange(N) / FS),
    ],
    ids=["f32-max-nyquist", "f32-max-sine", "f64-max-sine", "f32-denormal", "f64-denormal",
         "f64-flat-1e160", "f64-1e200-dc"],
)
def test_extreme_finite_traces_give_finite_kpis(trace):
    with np.errstate(all="raise"):
        kpis = extract_kpis(trace, FS)
    assert np.isfinite(kpis).all()


@pytest.mark.parametrize("n_samples", range(MIN_KPI_SAMPLES, 17))
def test_short_traces_give_finite_kpis(n_samples):
    y = np.random.default_rng(n_samples).standard_normal((30, n_samples))
    kpis = extract_kpis(y, FS)
    assert kpis.shape == (30, 7) and np.isfinite(kpis).all()


def test_single_trace_is_a_batch_of_one():
    traces, _ = damped_sinusoids(3, np.random.default_rng(4))
    np.testing.assert_array_equal(extract_kpis(traces[1], FS), extract_kpis(traces[1:2], FS))


def test_kpis_do_not_depend_on_the_batch():
    traces, _ = damped_sinusoids(20, np.random.default_rng(9), snr_db=20.0)
    full = extract_kpis(traces, FS)
    for i in range(len(traces)):
        np.testing.assert_array_equal(extract_kpis(traces[i : i + 1], FS), full[i : i + 1])


def test_empty_batch():
    assert extract_kpis(np.zeros((0, N), dtype=np.float32), FS).shape == (0, 7)


def test_float64_input_and_other_lengths():
    traces, truth = damped_sinusoids(
        50, np.random.default_rng(5), n_samples=300, fs=5e6, ring_samples=20
    )
    kpis = extract_kpis(traces.astype(np.float64), 5e6)
    assert np.percentile(errors(kpis, truth)["frequency"], 95) < 1e-4


def test_energy_and_magnitude_closed_form():
    # A cos on bin m0: sum of squares N A^2 / 2 (the mean is 0 after removal of dc);
    # the single-sided amplitude spectrum at bin m0 is exactly A.
    t = np.arange(N) / FS
    amp, m0, dc = 1.7, 25, 0.4
    y = dc + amp * np.cos(2 * np.pi * m0 * FS / N * t + 0.7)
    kpis = extract_kpis(y, FS)[0]
    np.testing.assert_allclose(kpis[COL["energy"]], N * amp**2 / 2 / FS, rtol=1e-10)
    np.testing.assert_allclose(kpis[COL["magnitude"]], amp, rtol=1e-10)
    np.testing.assert_allclose(kpis[COL["dominant_frequency_hz"]], m0 * FS / N, rtol=1e-9)
    np.testing.assert_allclose(kpis[COL["amplitude"]], amp, rtol=1e-5)
    np.testing.assert_allclose(kpis[COL["dc_offset"]], dc, atol=1e-9)
    assert kpis[COL["damping_ratio"]] < 1e-4
    # Energy of a damped sinusoid against its direct definition (mean-removed sum of squares).
    traces, _ = damped_sinusoids(20, np.random.default_rng(6))
    y64 = traces.astype(np.float64)
    expected = ((y64 - y64.mean(axis=1, keepdims=True)) ** 2).sum(axis=1) / FS
    np.testing.assert_allclose(extract_kpis(traces, FS)[:, COL["energy"]], expected, rtol=1e-5)


def test_nyquist_magnitude():
    y = 0.5 * (-1.0) ** np.arange(N)  # all power in the Nyquist bin
    assert extract_kpis(y, FS)[0, COL["magnitude"]] == pytest.approx(0.5, rel=1e-12)


def test_reconstruct_round_trip():
    traces, truth = damped_sinusoids(50, np.random.default_rng(7))
    rebuilt = reconstruct(extract_kpis(traces, FS), N, FS)
    assert rebuilt.shape == traces.shape and rebuilt.dtype == np.float64
    scale = truth[:, [3]]
    assert np.max(np.abs(rebuilt - traces) / scale) < 1e-4
    # And from the true parameters, which reconstruct must turn into the same traces.
    true_kpis = np.zeros((50, 7))
    true_kpis[:, :5] = truth
    np.testing.assert_allclose(reconstruct(true_kpis, N, FS), traces, atol=1e-5 * scale.max())


def test_reconstruct_validation():
    with pytest.raises(ValueError, match=r"shape \(n_traces, 7\)"):
        reconstruct(np.zeros((2, 5)), N, FS)
    with pytest.raises(ValueError, match=r"damping_ratio must be in \[0, 1\)"):
        reconstruct([0, 1e5, 1.0, 1, 0, 0, 0], N, FS)
    with pytest.raises(ValueError, match="n_samples must be at least 1"):
        reconstruct(np.zeros(7), 0, FS)


@pytest.mark.parametrize(
    ("traces", "match"),
    [
        (np.zeros((2, 3, N)), r"shape \(n_traces, n_samples\).*found ndim=3"),
        (np.zeros(()), r"found ndim=0"),
        (np.zeros((4, MIN_KPI_SAMPLES - 1)), r"at least 2 samples per trace, found 1"),
        (np.zeros((2, N), dtype=complex), "must be real, found complex"),
        (np.array([["a"] * N]), "real numeric array"),
    ],
)
def test_bad_traces_raise(traces, match):
    with pytest.raises(ValueError, match=match):
        extract_kpis(traces, FS)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_traces_raise(bad):
    y = np.zeros((5, N), dtype=np.float32)
    y[3, 10] = bad
    with pytest.raises(InvalidTraceError, match=r"finite, found 1 NaN or Inf.*first in trace 3"):
        extract_kpis(y, FS)


@pytest.mark.parametrize("fs", [0.0, -1.0, np.nan, np.inf, "10e6", None, True])
def test_bad_sample_rate_raises(fs):
    with pytest.raises(ValueError, match="sample_rate_hz must be"):
        extract_kpis(np.zeros(N), fs)


def test_exception_is_a_value_error():
    assert issubclass(InvalidTraceError, ValueError)


def test_extractor_matches_function_and_names():
    traces, _ = damped_sinusoids(10, np.random.default_rng(8))
    est = KpiExtractor(sample_rate_hz=FS).fit(traces)
    assert est.n_features_in_ == N
    np.testing.assert_array_equal(est.transform(traces), extract_kpis(traces, FS))
    assert tuple(est.get_feature_names_out()) == KPI_NAMES
    with pytest.raises(ValueError, match="sample_rate_hz must be"):
        KpiExtractor(sample_rate_hz=-1.0).fit(traces)


# All checks run: MIN_KPI_SAMPLES is low enough for the checks' 2- to 10-column data.
@parametrize_with_checks([KpiExtractor()])
def test_sklearn_contract(estimator, check):
    check(estimator)
