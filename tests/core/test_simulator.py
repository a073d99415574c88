"""Tests of the fault simulator (issue 3): exactness, physics, reproducibility, validation."""

import math

import numpy as np
import pytest
from scipy.linalg import expm

from inkdiag_core import FaultClass, InkChannelParams, SimulationResult, alpha, simulate
from inkdiag_core.faults import DRIED_CLASSES, HEALTHY_CLASSES, MECHANISMS, is_healthy
from inkdiag_core.simulator import DriveWaveform, Spreads

TABLE3_KHZ = {
    "ok_signal": 237.150, "healthy_nozzle": 237.170, "empty_channel_1": 2124.400,
    "empty_channel_2": 1423.400, "mature_air_bubble": 357.450,
    "intermediate_air_bubble": 330.780, "small_air_bubble": 189.720,
    "fully_blocked": 166.350, "partially_blocked": 200.480, "slightly_dried": 225.130,
    "intermediately_dried": 212.730, "deeply_dried": 189.650,
}
ALL = {c: 3 for c in FaultClass}


def test_fault_class_has_the_12_stable_values():
    assert [c.value for c in FaultClass] == list(TABLE3_KHZ)
    assert HEALTHY_CLASSES == {FaultClass.OK_SIGNAL, FaultClass.HEALTHY_NOZZLE}
    assert is_healthy("ok_signal") and not is_healthy(FaultClass.DEEPLY_DRIED)
    assert len(DRIED_CLASSES) == 3 and set(MECHANISMS) == set(FaultClass)


def test_shapes_dtypes_and_labels():
    r = simulate(ALL, n_samples=300, seed=1)
    assert isinstance(r, SimulationResult)
    assert r.traces.shape == (36, 300) and r.traces.dtype == np.float32
    assert r.labels.shape == (36,) and r.labels.dtype == object
    assert np.array([c.value for c in r.labels]).tolist() == [
        c.value for c in FaultClass for _ in range(3)
    ]
    for name in ("mu_nozzle", "mu", "fm", "frequency_hz", "damping_ratio", "sensor_gain",
                 "sensor_offset", "snr_db"):
        assert getattr(r, name).shape == (36,), name
    assert r.x0.shape == (36, 3) and r.A.shape == (36, 3, 3)
    assert all(v.shape == (36,) for v in r.params.values())
    assert np.isfinite(r.traces).all()


def test_string_keys_and_zero_counts():
    r = simulate({"deeply_dried": 2, FaultClass.OK_SIGNAL: 0})
    assert len(r) == 2 and set(r.labels) == {FaultClass.DEEPLY_DRIED}
    assert len(simulate({})) == 0


def test_seed_reproducible_to_the_bit():
    a = simulate(ALL, seed=123)
    b = simulate(ALL, seed=123)
    c = simulate(ALL, seed=124)
    assert a.traces.tobytes() == b.traces.tobytes()
    assert np.array_equal(a.x0, b.x0) and np.array_equal(a.sensor_gain, b.sensor_gain)
    assert not np.array_equal(a.traces, c.traces)
    d = simulate(ALL, seed=123, chunk_size=5)
    assert a.traces.tobytes() == d.traces.tobytes()


def _expm_reference(r, n_samples):
    """y[k] = C Ad^k x0 with Ad = expm(A / fs), per trace (independent of the simulator)."""
    out = np.empty((len(r), n_samples))
    for i in range(len(r)):
        Ad = expm(r.A[i] / r.sample_rate_hz)
        x = r.x0[i].copy()
        for k in range(n_samples):
            out[i, k] = x[1] + x[2]
            x = Ad @ x
    return out


def test_noise_free_traces_equal_exact_discretisation_of_the_model():
    r = simulate({c: 1 for c in FaultClass}, n_samples=200, seed=5, spreads=Spreads.none())
    ref = _expm_reference(r, 200)
    y = r.y_si()
    err = np.abs(y - ref).max(axis=1) / np.abs(ref).max(axis=1)
    assert err.max() < 1e-6  # float32 output


def test_window_start_state_matches_an_ode_solve_through_the_pulse():
    from scipy.integrate import solve_ivp

    drive = DriveWaveform()
    r = simulate({FaultClass.HEALTHY_NOZZLE: 1, FaultClass.EMPTY_CHANNEL_2: 1}, seed=2,
                 spreads=Spreads.none())
    for i in range(2):
        A = r.A[i]
        B = np.array([0.0, -A[1, 0], -A[2, 0]]) * r.params["b"][i] * r.params["drive_v"][i]
        sol = solve_ivp(lambda t, x: A @ x + B * drive.u(t), (0, drive.window_start_s),
                        np.zeros(3), method="DOP853", rtol=1e-11, atol=1e-30,
                        max_step=drive.rise_s / 8)
        np.testing.assert_allclose(r.x0[i], sol.y[:, -1], rtol=1e-6,
                                   atol=1e-8 * np.abs(sol.y[:, -1]).max())


def test_truth_frequency_and_damping_are_the_eigenvalues_of_A():
    r = simulate(ALL, seed=3)
    lam = np.linalg.eigvals(r.A)
    k = np.argmax(lam.imag, axis=1)
    top = lam[np.arange(len(r)), k]
    np.testing.assert_allclose(r.frequency_hz, top.imag / (2 * np.pi), rtol=1e-9)
    np.testing.assert_allclose(r.damping_ratio, -top.real / np.abs(top), rtol=1e-8)


def test_healthy_nominal_channel_is_the_model_default():
    r = simulate({FaultClass.HEALTHY_NOZZLE: 1}, spreads=Spreads.none())
    p = InkChannelParams()
    f_closed = math.sqrt((1 / p.I_r + 1 / p.I_n) / p.B_t) / (2 * math.pi)
    assert r.frequency_hz[0] == pytest.approx(f_closed, rel=0.01)
    assert r.fm[0] == 0.0 and r.mu_nozzle[0] == pytest.approx(p.mu)


def test_fully_blocked_is_the_restrictor_only_resonance():
    r = simulate({FaultClass.FULLY_BLOCKED: 4}, seed=4)
    I_r, B_t = r.params["I_r"], r.params["B_t"]
    f0 = 1 / (2 * np.pi * np.sqrt(I_r * B_t))
    zeta = r.params["R_r"] / I_r / (4 * np.pi * f0)
    np.testing.assert_allclose(r.frequency_hz, f0 * np.sqrt(1 - zeta**2), rtol=1e-9)
    np.testing.assert_allclose(r.x0[:, 2], 0.0)  # no nozzle flow


def test_fm_truth_follows_appendix_f():
    r = simulate({c: 3 for c in DRIED_CLASSES} | {FaultClass.PARTIALLY_BLOCKED: 2}, seed=6)
    dried = np.array([c in DRIED_CLASSES for c in r.labels])
    assert (r.fm[dried] < 0).all() and (r.fm[~dried] == 0).all()
    p = r.params
    a = 8 * p["L_n"] / (p["rho"] * (p["L_n"] + np.pi * p["r_n"] / 4) * p["r_n"] ** 2)
    np.testing.assert_allclose(r.fm[dried], (-a * (r.mu_nozzle - r.mu))[dried], rtol=1e-12)
    # nominal channel: f_m equals inkdiag_core.fault_fm
    r0 = simulate({FaultClass.DEEPLY_DRIED: 1}, spreads=Spreads.none())
    assert r0.fm[0] == pytest.approx(-alpha(InkChannelParams()) * (r0.mu_nozzle[0] - 10e-3))
    assert r0.A[0, 2, 2] - (-InkChannelParams().R_n / InkChannelParams().I_n) == pytest.approx(
        r0.fm[0], rel=1e-9)


def test_sensor_model_roundtrip_and_snr():
    r = simulate({FaultClass.HEALTHY_NOZZLE: 1}, spreads=Spreads(snr_db=math.inf, adc_bits=None),
                 seed=8)
    assert r.traces[0, 0] == pytest.approx(r.sensor_gain[0] * (r.x0[0, 1] + r.x0[0, 2])
                                           + r.sensor_offset[0], rel=1e-6)
    rn = simulate({FaultClass.HEALTHY_NOZZLE: 200}, seed=9)
    assert np.median(rn.snr_db) == pytest.approx(30.0, abs=1.5)
    lsb = 4.0 / 2**12  # 12 bit over +-2 V
    q = rn.traces[:5] / lsb
    np.testing.assert_allclose(q, np.rint(q), atol=1e-3)


def test_table_3_means_within_3_percent_on_a_small_sample():
    r = simulate({c: 40 for c in FaultClass}, seed=11)
    try:
        from inkdiag_core.kpis import extract_kpis

        f = extract_kpis(r.traces, r.sample_rate_hz)[:, 1]
    except ImportError:  # kpis not merged: the true dominant mode
        f = r.frequency_hz
    labels = np.array([c.value for c in r.labels])
    for name, f_khz in TABLE3_KHZ.items():
        mean = f[labels == name].mean() / 1e3
        assert abs(mean / f_khz - 1) < 0.03, (name, mean, f_khz)


def _zero_padded_fft_peak_hz(traces, fs, n_fft=2**16):
    """The thesis's Table 3 measure: peak bin of |FFT| of the mean-removed, zero-padded trace."""
    out = []
    for blk in np.array_split(np.asarray(traces, dtype=np.float64), max(1, len(traces) // 128)):
        spec = np.abs(np.fft.rfft(blk - blk.mean(axis=1, keepdims=True), n=n_fft, axis=1))
        out.append((np.argmax(spec[:, 1:], axis=1) + 1) * fs / n_fft)
    return np.concatenate(out)


def test_table_3_means_within_3_percent_under_both_measures():
    # issue 12 item 8: the independent check's setup (200 traces per class, seed 123);
    # the thesis measured Table 3 as the zero-padded FFT peak, we as the fitted damped
    # frequency: every class mean must be within 3 % of Table 3 under both
    from inkdiag_core.kpis import extract_kpis

    r = simulate({c: 200 for c in FaultClass}, seed=123)
    labels = np.array([c.value for c in r.labels])
    measures = {"extract_kpis": extract_kpis(r.traces, r.sample_rate_hz)[:, 1],
                "zero-padded FFT peak": _zero_padded_fft_peak_hz(r.traces, r.sample_rate_hz)}
    bad = []
    for how, f in measures.items():
        for name, f_khz in TABLE3_KHZ.items():
            dev = f[labels == name].mean() / 1e3 / f_khz - 1
            if abs(dev) >= 0.03:
                bad.append((how, name, round(100 * dev, 2)))
    assert not bad, bad


def test_classes_are_not_separated_by_frequency_alone():
    # spreads are physical and wide: neighbouring drying classes overlap
    r = simulate({c: 100 for c in DRIED_CLASSES}, seed=12)
    f = {c: r.frequency_hz[r.labels == c] for c in DRIED_CLASSES}
    assert f[FaultClass.SLIGHTLY_DRIED].min() < f[FaultClass.INTERMEDIATELY_DRIED].max()
    assert f[FaultClass.INTERMEDIATELY_DRIED].min() < f[FaultClass.DEEPLY_DRIED].max()


@pytest.mark.parametrize(
    "counts, kwargs, match",
    [
        ({FaultClass.OK_SIGNAL: -1}, {}, "counts"),
        ({FaultClass.OK_SIGNAL: 2.5}, {}, "counts"),
        ({FaultClass.OK_SIGNAL: "3"}, {}, "counts"),
        ({"no_such_class": 1}, {}, "counts"),
        ([1, 2], {}, "counts"),
        ({FaultClass.EMPTY_CHANNEL_1: 1}, {"sample_rate_hz": 3e6}, "sample_rate_hz"),
        ({FaultClass.OK_SIGNAL: 1}, {"sample_rate_hz": -1.0}, "sample_rate_hz"),
        ({FaultClass.OK_SIGNAL: 1}, {"n_samples": 0}, "n_samples"),
        ({FaultClass.OK_SIGNAL: 1}, {"n_samples": 2.0}, "n_samples"),
    ],
)
def test_bad_arguments_raise_value_error_naming_the_argument(counts, kwargs, match):
    with pytest.raises(ValueError, match=match):
        simulate(counts, **kwargs)


def test_low_sample_rate_is_fine_for_low_frequency_classes():
    r = simulate({FaultClass.HEALTHY_NOZZLE: 1}, sample_rate_hz=3e6, n_samples=64)
    assert r.traces.shape == (1, 64)


def test_non_positive_physical_parameters_raise():
    with pytest.raises(ValueError, match="r_n"):
        simulate({FaultClass.OK_SIGNAL: 1}, base_params=InkChannelParams(r_n=0.0))
    with pytest.raises(ValueError, match="rise_s"):
        DriveWaveform(rise_s=-1e-6)
    with pytest.raises(ValueError, match="gain_rel"):
        Spreads(gain_rel=-0.1)


# --- nonlinear variant --------------------------------------------------------------------

from inkdiag_core import simulate_nonlinear  # noqa: E402
from inkdiag_core.nonlinear import DEFAULT_COUPLING_M3_PER_V, NonlinearTerms  # noqa: E402

NL = {FaultClass.HEALTHY_NOZZLE: 1, FaultClass.DEEPLY_DRIED: 1, FaultClass.MATURE_AIR_BUBBLE: 1,
      FaultClass.FULLY_BLOCKED: 1, FaultClass.EMPTY_CHANNEL_1: 1}


def test_nonlinear_with_terms_off_is_the_linear_simulator():
    base = InkChannelParams(b=DEFAULT_COUPLING_M3_PER_V)
    a = simulate_nonlinear(NL, seed=1, n_samples=128, spreads=Spreads.none(),
                           terms=NonlinearTerms.off())
    b = simulate(NL, seed=1, n_samples=128, spreads=Spreads.none(), base_params=base)
    ya, yb = a.y_si(), b.y_si()
    assert (np.abs(ya - yb).max(axis=1) / np.abs(yb).max(axis=1)).max() < 1e-6
    np.testing.assert_allclose(a.x0, b.x0, rtol=1e-6, atol=1e-9 * np.abs(b.x0).max())


def test_nonlinear_same_format_and_same_channels_as_linear():
    base = InkChannelParams(b=DEFAULT_COUPLING_M3_PER_V)
    a = simulate_nonlinear(NL, seed=4, n_samples=64)
    b = simulate(NL, seed=4, n_samples=64, base_params=base)
    assert isinstance(a, SimulationResult)
    assert a.traces.dtype == np.float32 and a.traces.shape == (5, 64)
    for k in ("r_n", "L_n", "temperature_k", "B_t"):
        np.testing.assert_array_equal(a.params[k], b.params[k])
    np.testing.assert_array_equal(a.fm, b.fm)
    assert a.traces.tobytes() == simulate_nonlinear(NL, seed=4, n_samples=64).traces.tobytes()


def test_nonlinear_is_amplitude_dependent_but_close_to_linear():
    counts = {FaultClass.HEALTHY_NOZZLE: 1}
    ys = []
    for volts in (10.0, 30.0):
        r = simulate_nonlinear(counts, n_samples=256, spreads=Spreads.none(),
                               drive=DriveWaveform(amplitude_v=volts))
        ys.append(r.y_si()[0] / volts)
    lin = simulate(counts, n_samples=256, spreads=Spreads.none(),
                   base_params=InkChannelParams(b=DEFAULT_COUPLING_M3_PER_V)).y_si()[0] / 20.0
    peak = np.abs(lin).max()
    diff = np.abs(ys[0] - ys[1]).max() / peak
    assert 3e-3 < diff < 0.1  # clearly nonlinear, but a perturbation
    # frequency stays within 1 % of the linear model's (FFT peak of a zero-padded trace)
    f = [np.argmax(np.abs(np.fft.rfft(y - y.mean(), 2**15))) * 10e6 / 2**15 for y in (ys[1], lin)]
    assert f[0] == pytest.approx(f[1], rel=0.01)


def test_nonlinear_bad_arguments():
    with pytest.raises(ValueError, match="rtol"):
        simulate_nonlinear({FaultClass.OK_SIGNAL: 1}, rtol=0.0)
    with pytest.raises(ValueError, match="counts"):
        simulate_nonlinear({"bogus": 1})
    with pytest.raises(ValueError, match="sample_rate_hz"):
        simulate_nonlinear({FaultClass.EMPTY_CHANNEL_1: 1}, sample_rate_hz=2e6)


def test_severity_override_sets_the_drying_level_and_leaves_other_traces_alone():
    k = np.array([1.0, 2.0, 5.0])
    counts = {FaultClass.HEALTHY_NOZZLE: 2, FaultClass.DEEPLY_DRIED: 3}
    r = simulate(counts, seed=2, severity={"deeply_dried": k})
    r0 = simulate(counts, seed=2)
    np.testing.assert_allclose(r.mu_nozzle[2:] / r.mu[2:], k)
    np.testing.assert_array_equal(r.traces[:2], r0.traces[:2])
    assert r.fm[2] == 0.0 and r.fm[4] < r.fm[3] < 0
    with pytest.raises(ValueError, match="severity"):
        simulate(counts, severity={FaultClass.DEEPLY_DRIED: [1.0]})
    with pytest.raises(ValueError, match="severity"):
        simulate(counts, severity={FaultClass.DEEPLY_DRIED: [1.0, -2.0, 3.0]})
    with pytest.raises(ValueError, match="severity"):
        simulate(counts, severity={FaultClass.HEALTHY_NOZZLE: [1.0, 2.0]})


def test_simulate_nozzles_keeps_nozzle_order_and_given_viscosities():
    from inkdiag_core.simulator import simulate_nozzles

    classes = ["healthy_nozzle", "deeply_dried", "slightly_dried", "healthy_nozzle",
               "fully_blocked", "slightly_dried"]
    mu = np.array([np.nan, np.nan, 0.035, np.nan, np.nan, np.nan])
    res = simulate_nozzles(classes, mu_nozzle=mu, seed=3)
    assert res.label_values().tolist() == classes
    assert res.traces.shape == (6, 512)
    # the given viscosity factor is used as it is (the channel's own ink viscosity scales it)
    assert res.params["severity"][2] == pytest.approx(3.5)
    slight = MECHANISMS[FaultClass.SLIGHTLY_DRIED]
    assert slight.low <= res.params["severity"][5] <= slight.high
    assert res.fm[0] == 0 and res.fm[1] < res.fm[2] < 0  # deeper drying, larger |f_m|
    again = simulate_nozzles(classes, mu_nozzle=mu, seed=3)
    assert np.array_equal(again.traces, res.traces)


NOZZLE_OWN = ("r_n", "L_n", "r_r", "B_act", "b")  # geometry, piezo, coupling


def test_simulate_nozzles_frames_of_one_head_keep_each_nozzles_tolerances():
    from inkdiag_core.simulator import simulate_nozzles

    before = ["healthy_nozzle", "slightly_dried", "healthy_nozzle", "partially_blocked", "ok_signal"]
    after = ["healthy_nozzle", "deeply_dried", "fully_blocked", "partially_blocked", "ok_signal"]
    f1 = simulate_nozzles(before, seed=11, frame_seed=1)
    f2 = simulate_nozzles(after, seed=11, frame_seed=2)
    # every nozzle keeps its tolerances, sensor and drive while two change condition
    for key in NOZZLE_OWN:
        np.testing.assert_array_equal(f1.params[key], f2.params[key], err_msg=key)
    np.testing.assert_array_equal(f1.sensor_gain, f2.sensor_gain)
    np.testing.assert_array_equal(f1.sensor_offset, f2.sensor_offset)
    # a partly blocked nozzle keeps its blockage; the unchanged nozzles differ only by the frame
    assert f1.params["severity"][3] == f2.params["severity"][3]
    assert f2.params["severity"][1] > f1.params["severity"][1]  # dried deeper
    # ...which draws its own ink temperature and sensor noise
    assert not np.array_equal(f1.params["temperature_k"], f2.params["temperature_k"])
    assert not np.array_equal(f1.traces[0], f2.traces[0])
    same_frame = simulate_nozzles(after, seed=11, frame_seed=2)
    np.testing.assert_array_equal(same_frame.traces, f2.traces)
    # another head: other nozzles
    other = simulate_nozzles(after, seed=12, frame_seed=2)
    assert not np.array_equal(other.params["r_n"], f2.params["r_n"])


def test_simulate_frame_seed_changes_only_temperature_and_noise():
    counts = {FaultClass.HEALTHY_NOZZLE: 4, FaultClass.MATURE_AIR_BUBBLE: 3}
    a = simulate(counts, seed=4, frame_seed=1)
    b = simulate(counts, seed=4, frame_seed=2)
    for key in NOZZLE_OWN + ("severity",):
        np.testing.assert_array_equal(a.params[key], b.params[key], err_msg=key)
    assert not np.array_equal(a.params["temperature_k"], b.params["temperature_k"])
    # without frame_seed everything comes from seed, as before
    np.testing.assert_array_equal(simulate(counts, seed=4).traces, simulate(counts, seed=4).traces)
    with pytest.raises(ValueError, match="draw_order must be a permutation"):
        simulate(counts, seed=4, draw_order=[0, 1, 2, 3, 4, 5, 5])
    with pytest.raises(ValueError, match="draw_order must be a permutation"):
        simulate(counts, seed=4, draw_order=np.arange(6))


def test_simulate_nozzles_rejects_bad_arguments():
    from inkdiag_core.simulator import simulate_nozzles

    with pytest.raises(ValueError, match="classes"):
        simulate_nozzles(["leaky"])
    with pytest.raises(ValueError, match="one value per nozzle"):
        simulate_nozzles(["deeply_dried"], mu_nozzle=[0.1, 0.2])
    with pytest.raises(ValueError, match="at least one nozzle"):
        simulate_nozzles([])
