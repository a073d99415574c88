"""The independent foreign-head simulator (tests/foreign_head.py), issue 14's test data."""

import dataclasses
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

import foreign_head as fh
from inkdiag_core import FaultClass, InkChannelParams, simulate
from inkdiag_core.faults import MECHANISMS
from inkdiag_core.simulation import PHYSICAL_CONSTANTS, DriveWaveform, Spreads

TESTS_DIR = Path(__file__).resolve().parents[1]

# healthy modes stated in foreign_head's docstring
STATED_HEALTHY_HZ = {"h20": 169e3, "h16": 174e3, "h12": 191e3, "h5": 135e3}


def fft_peak_hz(traces, fs):
    """Peak (Hz) of the 16x zero-padded spectrum of each mean-removed trace, (n,)."""
    x = traces - traces.mean(axis=1, keepdims=True)
    nfft = 16 * x.shape[1]
    spec = np.abs(np.fft.rfft(x, nfft, axis=1))
    return np.fft.rfftfreq(nfft, 1.0 / fs)[1 + np.argmax(spec[:, 1:], axis=1)]


def test_class_names_and_severity_numbers_are_the_cores():
    assert fh.CLASS_VALUES == tuple(c.value for c in FaultClass)
    for c, m in MECHANISMS.items():
        assert fh._MECH[c.value] == (m.kind, m.low, m.high, m.drive_factor)


@pytest.mark.parametrize("name", sorted(STATED_HEALTHY_HZ))
def test_healthy_mode_is_the_stated_one(name):
    assert f"healthy mode about {STATED_HEALTHY_HZ[name] / 1e3:.0f} kHz" in fh.__doc__
    sim = fh.simulate_foreign(name, {"healthy_nozzle": 1}, seed=0, ideal=True)
    peak = fft_peak_hz(sim["traces"].astype(float), sim["sample_rate_hz"])[0]
    assert abs(peak / STATED_HEALTHY_HZ[name] - 1) < 0.02
    assert 0.05 <= sim["damping_ratio"][0] <= 0.12
    head = fh.FOREIGN_HEADS[name]
    assert sim["traces"].shape == (1, head["sampling"]["n_samples"])


@pytest.mark.parametrize("name", sorted(fh.FOREIGN_HEADS))
def test_every_class_mode_stays_below_nyquist(name):
    counts = {c: 2 for c in fh.CLASS_VALUES}
    sev = {c: [lo, hi] for c, (_, lo, hi, _) in fh._MECH.items() if hi > lo}
    sim = fh.simulate_foreign(name, counts, seed=0, ideal=True, severity=sev)
    assert np.all(sim["frequency_hz"] < 0.45 * sim["sample_rate_hz"])


@pytest.mark.parametrize("name", sorted(fh.FOREIGN_HEADS))
def test_profile_fields_are_the_cores(name):
    head = fh.FOREIGN_HEADS[name]
    InkChannelParams(**head["channel"])
    DriveWaveform(**head["drive"])
    nom = fh.nominal_profile(name)
    assert set(nom) == {"name", "sampling", "drive", "channel"}
    assert set(nom["channel"]) == {"rho", "mu", "r_n", "L_n", "V_ch", "c"}
    assert nom["drive"] == head["drive"] and nom["sampling"] == head["sampling"]


def test_classes_are_distinct_physics():
    k = np.array([2.4, 3.0, 4.2, 5.4, 6.0, 9.6])
    counts = {"healthy_nozzle": 1, "fully_blocked": 1, "small_air_bubble": 1,
              "mature_air_bubble": 1, "empty_channel_1": 1, "deeply_dried": k.size}
    sim = fh.simulate_foreign("h20", counts, seed=0, ideal=True, severity={"deeply_dried": k})
    f = dict(zip(sim["labels"][:5], sim["frequency_hz"][:5]))
    f_dry = fft_peak_hz(sim["traces"][5:].astype(float), sim["sample_rate_hz"])
    assert np.all(np.diff(f_dry) < 0)  # drying lowers the frequency
    assert np.all(f_dry < f["healthy_nozzle"])
    assert f["fully_blocked"] < f["healthy_nozzle"] < f["mature_air_bubble"] < f["empty_channel_1"]
    assert f["small_air_bubble"] < f["healthy_nozzle"]
    dried = sim["labels"] == "deeply_dried"
    np.testing.assert_allclose(sim["viscosity_ratio"][dried], k)
    assert np.all(sim["fm"][dried] < 0) and np.all(sim["fm"][~dried] == 0)
    # ok_signal is the healthy channel at OK_SIGNAL_DRIVE_FACTOR of the drive
    ok = fh.simulate_foreign("h20", {"ok_signal": 1, "healthy_nozzle": 1}, seed=0, ideal=True)
    np.testing.assert_allclose(ok["traces"][0], 0.8 * ok["traces"][1], rtol=1e-5, atol=1e-6)


def test_noisy_run_is_deterministic_and_well_formed():
    counts = {FaultClass.HEALTHY_NOZZLE: 3, "slightly_dried": 3, "empty_channel_2": 2}
    a = fh.simulate_foreign("h5", counts, seed=7)
    b = fh.simulate_foreign("h5", counts, seed=7)
    c = fh.simulate_foreign("h5", counts, seed=8)
    for key in ("traces", "labels", "mu_nozzle", "fm", "nozzle"):
        np.testing.assert_array_equal(a[key], b[key])
    assert not np.array_equal(a["traces"], c["traces"])
    assert a["traces"].dtype == np.float32 and a["traces"].shape == (8, 256)
    assert list(a["labels"]) == ["healthy_nozzle"] * 3 + ["empty_channel_2"] * 2 + ["slightly_dried"] * 3
    assert np.all(np.abs(a["traces"]) <= 2.0)
    dried = a["labels"] == "slightly_dried"
    assert np.all((a["viscosity_ratio"][dried] >= 2.4) & (a["viscosity_ratio"][dried] <= 4.2))
    assert np.all(a["viscosity_ratio"][~dried] == 1.0)
    np.testing.assert_array_equal(a["nozzle"], np.arange(8))


def test_nozzle_seed_keeps_a_nozzles_spreads_from_one_recording_to_the_next():
    ids = np.array([4, 0, 4, 9])
    a = fh.simulate_foreign("h20", {"healthy_nozzle": 4}, seed=1, nozzles=ids, nozzle_seed=5)
    b = fh.simulate_foreign("h20", {"deeply_dried": 2, "healthy_nozzle": 2}, seed=2, nozzles=ids[::-1],
                            nozzle_seed=5)
    np.testing.assert_array_equal(a["nozzle"], ids)
    for key in ("gain", "drive_v"):  # the nozzle's own (drive: both classes at the full pulse)
        np.testing.assert_array_equal(a[key][[0, 2]], a[key][0])  # nozzle 4 twice in one recording
        np.testing.assert_array_equal(b[key][::-1], a[key])  # the same nozzles in another
    assert not np.array_equal(a["offset_v"][[0]], a["offset_v"][[2]])  # the frame's own
    assert a["gain"][0] != a["gain"][1]  # another nozzle
    c = fh.simulate_foreign("h20", {"healthy_nozzle": 2}, seed=3, nozzles=[0, 4000], nozzle_seed=5)
    assert c["gain"][0] == a["gain"][1]  # nozzle 0 is nozzle 0 in a head of any size
    # the default: each row its own nozzle, drawn from seed alone (today's recordings unchanged)
    plain = fh.simulate_foreign("h20", {"healthy_nozzle": 4}, seed=1)
    np.testing.assert_array_equal(fh.simulate_foreign("h20", {"healthy_nozzle": 4}, seed=1,
                                                      nozzles=np.arange(4))["traces"], plain["traces"])
    with pytest.raises(ValueError, match="integer ids >= 0"):
        fh.simulate_foreign("h20", {"healthy_nozzle": 2}, nozzles=[0, -1], nozzle_seed=5)


def test_bad_input_is_a_clear_error():
    with pytest.raises(ValueError, match="unknown fault class"):
        fh.simulate_foreign("h20", {"wet": 1})
    with pytest.raises(ValueError, match="int >= 0"):
        fh.simulate_foreign("h20", {"healthy_nozzle": -1})
    with pytest.raises(ValueError, match="unknown foreign head"):
        fh.simulate_foreign("h99", {"healthy_nozzle": 1})
    with pytest.raises(ValueError, match="physical bounds"):
        fh.simulate_foreign("h20", {"partially_blocked": 1}, severity={"partially_blocked": [1.2]})
    assert fh.simulate_foreign("h20", {}, seed=0)["traces"].shape == (0, 1024)


def test_recording_and_nominal_yaml_round_trip(tmp_path):
    sim = fh.simulate_foreign("h20", {"healthy_nozzle": 2, "deeply_dried": 2}, seed=3)
    path = tmp_path / "rec.npz"
    fh.write_recording(path, sim)
    with np.load(path, allow_pickle=False) as z:
        np.testing.assert_array_equal(z["traces"], sim["traces"])
        assert z["traces"].dtype == np.float32
        assert float(z["sample_rate_hz"]) == 20e6 and z["sample_rate_hz"].shape == ()
        np.testing.assert_array_equal(z["nozzle"], np.arange(4))
        assert z["frame_id"].shape == (4,) and z["stamp"].shape == (4,)
        assert list(z["label"]) == list(sim["labels"])
    ypath = tmp_path / "h20.yaml"
    fh.write_nominal_yaml(ypath, "h20")
    doc = yaml.safe_load(ypath.read_text())
    assert doc["schema"] == "inkdiag.head_profile" and doc["schema_version"] == 1
    assert doc["name"] == "h20" and "sensor" not in doc
    nom = fh.nominal_profile("h20")
    for sec in ("sampling", "channel", "drive"):
        assert doc[sec] == nom[sec]
        for key, v in doc[sec].items():
            assert type(v) is (int if key == "n_samples" else float), (sec, key, v)


def test_module_does_not_import_the_core():
    code = (
        "import sys; sys.path.insert(0, sys.argv[1]); import foreign_head as fh; "
        "fh.simulate_foreign('h5', {'healthy_nozzle': 1, 'small_air_bubble': 1}, seed=0); "
        "bad = [m for m in sys.modules if m.startswith('inkdiag_core')]; "
        "print(bad); sys.exit(1 if bad else 0)"
    )
    out = subprocess.run([sys.executable, "-c", code, str(TESTS_DIR)], capture_output=True, text=True,
                         timeout=60, env=dict(os.environ))
    assert out.returncode == 0, out.stdout + out.stderr


def test_same_physics_as_our_simulator_on_the_default_head():
    """Independent code, one model: on the default head every class's noise-free trace matches."""
    p, d = InkChannelParams(), DriveWaveform()
    head = {
        "sampling": {"sample_rate_hz": 10e6, "n_samples": 512},
        "channel": {k: getattr(p, k) for k in ("rho", "mu", "r_n", "L_n", "r_r", "L_r", "V_ch", "c", "B_act", "b")},
        "drive": dataclasses.asdict(d),
        "sensor": {"gain_v_per_m3s": 1e10, "offset_v": 0.0, "noise_std_v": 0.0, "adc_range_v": 2.0,
                   "adc_bits": None},
        "physics": {k: PHYSICAL_CONSTANTS[k]
                    for k in ("p0_pa", "sigma_n_per_m", "kappa_gas", "f_act_hz", "zeta_act", "film_loss_factor")},
    }
    counts = {c: 1 for c in FaultClass}
    sev = {c: [0.5 * (m.low + m.high)] for c, m in MECHANISMS.items() if m.high > m.low}
    ours = simulate(counts, spreads=Spreads.none(), sample_rate_hz=10e6, n_samples=512, seed=0, severity=sev)
    mine = fh.simulate_foreign(head, counts, seed=0, ideal=True, severity=sev)
    assert list(mine["labels"]) == [getattr(c, "value", c) for c in ours.labels]
    a, b = mine["traces"].astype(float), ours.traces.astype(float)
    corr = np.sum(a * b, axis=1) / np.sqrt(np.sum(a * a, axis=1) * np.sum(b * b, axis=1))
    assert np.all(corr > 0.99), dict(zip(mine["labels"], corr))
    np.testing.assert_allclose(mine["frequency_hz"], ours.frequency_hz, rtol=1e-6)


def test_batched_expm_matches_scipy():
    from scipy.linalg import expm

    rng = np.random.default_rng(0)
    M = rng.standard_normal((5, 6, 6)) * np.array([0.01, 1.0, 30.0, 100.0, 0.0])[:, None, None]
    E = fh._expm(M)
    for i in range(M.shape[0]):
        np.testing.assert_allclose(E[i], expm(M[i]), rtol=1e-9, atol=1e-12 * np.abs(expm(M[i])).max())
