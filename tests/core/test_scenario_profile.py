"""The simulated head and the baselines on any head profile (issue 14, items 1 and 7).

- ``simulate_head`` / ``HeadScenario`` take a :class:`HeadProfile`: its sampling,
  channel (healthy mode), drive, sensor gain and offset; the default head stays
  bit-identical (``test_simulation_split`` holds the recorded fingerprints).
- ``BaselineRecorder`` takes the profile: its sampling, its model for the f_m
  readings, its sha256 in the baselines file; old files read as the default head's.
"""

import json

import numpy as np
import pytest

from inkdiag_core import (BaselineRecorder, FaultClass, HeadProfile, NozzleBaselines, ProfileError,
                          estimate_fm_batch)
from inkdiag_core.baselines.store import BaselineFileError
from inkdiag_core.simulation import Spreads, simulate_nozzles
from inkdiag_core.simulation.scenario import HeadScenario, simulate_head


def foreign_head() -> HeadProfile:
    """Another head: other ink and nozzle, sampled at 20 MHz x 1024, another sense gain and offset."""
    return HeadProfile.default().replace(
        name="foreign", sample_rate_hz=20e6, n_samples=1024,
        channel={"rho": 1100.0, "mu": 6e-3, "r_n": 11e-6, "L_n": 45e-6},
        sensor={"gain_v_per_m3s": 2.0e10, "offset_v": 0.05})


def dominant_hz(traces, fs, pad=16):
    """Frequency of each trace's spectral peak, Hz (zero-padded FFT of the zero-mean trace)."""
    x = traces - traces.mean(axis=1, keepdims=True)
    n = pad * x.shape[1]
    spec = np.abs(np.fft.rfft(x, n=n, axis=1))
    return np.argmax(spec[:, 1:], axis=1).astype(float) / n * fs + fs / n


def test_simulate_head_default_profile_is_the_default_head_bit_for_bit():
    classes = [list(FaultClass)[i % 12] for i in range(24)]
    mu = np.full(24, np.nan)
    a = simulate_head(classes, mu, head_seed=3, rng=np.random.default_rng(5))
    b = simulate_head(classes, mu, head_seed=3, rng=np.random.default_rng(5), profile=HeadProfile.default())
    c = simulate_nozzles(classes, mu_nozzle=mu, seed=3, frame_seed=np.random.default_rng(5))
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)
    np.testing.assert_array_equal(a[0], c.traces)


def test_simulate_head_on_another_head_has_its_sampling_mode_gain_and_offset():
    prof = foreign_head()
    f0, _ = prof.healthy_mode()
    assert abs(f0 / HeadProfile.default().healthy_mode()[0] - 1) > 0.1  # really another mode
    classes = [FaultClass.HEALTHY_NOZZLE] * 30
    traces, labels, fm, _ = simulate_head(classes, np.full(30, np.nan), head_seed=1, rng=np.random.default_rng(2),
                                          profile=prof)
    assert traces.shape == (30, 1024) and traces.dtype == np.float32
    assert abs(np.median(dominant_hz(traces, 20e6)) / f0 - 1) < 0.03
    # the sensor: the same frame on the head with gain 1e10 and offset 0 is half the signal, 0.05 V lower
    plain = prof.replace(sensor={"gain_v_per_m3s": 1.0e10, "offset_v": 0.0})
    quiet = {"spreads": Spreads.none()}
    t2 = simulate_nozzles(classes, seed=1, sample_rate_hz=20e6, n_samples=1024, drive=prof.drive,
                          base_params=prof.channel_params(), sensor_gain_v_per_m3s=2e10, sensor_offset_v=0.05,
                          **quiet).traces
    t1 = simulate_nozzles(classes, seed=1, sample_rate_hz=20e6, n_samples=1024, drive=plain.drive,
                          base_params=plain.channel_params(), **quiet).traces
    np.testing.assert_allclose(t2 - 0.05, 2 * t1, atol=1e-5)


def test_scenario_dries_nozzles_in_factors_of_the_profiles_ink_viscosity():
    prof = foreign_head()
    sc = HeadScenario(n_nozzles=6, drying_nozzles=[4], drying_start_factor=2.0, drying_end_factor=8.0,
                      drying_duration_s=10.0, profile=prof)
    assert sc.profile is prof
    classes, mu = sc.at(5.0)
    assert mu[4] == pytest.approx(5.0 * 6e-3) and np.isnan(mu[:4]).all()
    traces, labels, fm, mu_true = sc.frame(5.0, head_seed=0, rng=np.random.default_rng(0))
    assert traces.shape == (6, 1024) and mu_true[4] == pytest.approx(5.0 * 6e-3, rel=0.05)  # ink temperature
    assert classes[4] == FaultClass.INTERMEDIATELY_DRIED and FaultClass(labels[4]) == classes[4]


def test_scenario_and_simulate_head_refuse_a_nominal_profile():
    nominal = HeadProfile.default().replace(channel={"r_r": None, "L_r": None, "B_act": None, "b": None})
    with pytest.raises(ProfileError, match="nominal .*channel.r_r"):
        HeadScenario(n_nozzles=4, profile=nominal)
    with pytest.raises(ProfileError, match="nominal"):
        simulate_head(["healthy_nozzle"], [np.nan], head_seed=0, rng=np.random.default_rng(0), profile=nominal)
    with pytest.raises(TypeError, match="HeadProfile"):
        HeadScenario(n_nozzles=4, profile="head.yaml")


def test_simulate_head_sampling_overrides_sample_the_same_head():
    prof = foreign_head()
    rng = lambda: np.random.default_rng(9)  # noqa: E731
    a = simulate_head(["healthy_nozzle"] * 3, [np.nan] * 3, head_seed=2, rng=rng(), profile=prof, n_samples=512)
    b = simulate_head(["healthy_nozzle"] * 3, [np.nan] * 3, head_seed=2, rng=rng(),
                      profile=prof.replace(n_samples=512))
    np.testing.assert_array_equal(a[0], b[0])
    with pytest.raises(ProfileError, match="Nyquist"):
        simulate_head(["healthy_nozzle"], [np.nan], head_seed=2, rng=rng(), profile=prof, sample_rate_hz=2e5)


def _healthy_frames(prof, n, n_frames):
    rng = np.random.default_rng(4)
    return [simulate_head(["healthy_nozzle"] * n, np.full(n, np.nan), head_seed=6, rng=rng, profile=prof)[0]
            for _ in range(n_frames)]


def test_baseline_recorder_on_a_profile_records_its_hash_and_uses_its_model(tmp_path):
    prof = foreign_head()
    rec = BaselineRecorder(n_frames=2, fm_frames=2, profile=prof)
    assert (rec.sample_rate_hz, rec.n_samples) == (20e6, 1024)
    frames = _healthy_frames(prof, 5, 2)
    for f in frames:
        rec.add(10, f)
    b = rec.baselines()
    assert b.head_sha256 == prof.sha256 != HeadProfile.default().sha256
    fm = np.stack([estimate_fm_batch(f, prof, 20e6, method="vp").fm for f in frames])  # raw, on the head's model
    np.testing.assert_allclose(b.fm, np.median(fm, axis=0), rtol=1e-6)
    back = NozzleBaselines.load(b.save(tmp_path / "b.npz"))
    assert back.head_sha256 == prof.sha256 and back.fm_method == b.fm_method == "vp"
    back.check_head(prof)
    with pytest.raises(BaselineFileError, match="another head"):
        back.check_head(HeadProfile.default())
    with pytest.raises(ProfileError, match="not head profile 'foreign'"):
        BaselineRecorder(n_frames=2, profile=prof, sample_rate_hz=10e6)
    with pytest.raises(ProfileError, match="n_samples 512"):
        BaselineRecorder(n_frames=2, profile=prof, n_samples=512)
    with pytest.raises(ProfileError, match="nominal"):
        BaselineRecorder(n_frames=2, profile=prof.replace(channel={"b": None}))


def test_baselines_without_a_head_are_the_default_heads(tmp_path):
    b = NozzleBaselines(np.arange(3), np.ones((3, 7)), 10e6, 512, 4)
    assert b.head_sha256 == HeadProfile.default().sha256
    assert BaselineRecorder(n_frames=1).baselines().head_sha256 == HeadProfile.default().sha256
    # a version-2 file (before head profiles) reads as the default head's
    path = b.save(tmp_path / "new.npz")
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(str(arrays["meta"]))
    assert meta["format_version"] == 5 and meta["head_sha256"] == b.head_sha256
    from inkdiag_core.baselines.store import _content_sha256

    old = {k: v for k, v in meta.items() if k not in ("head_sha256", "sha256", "has_reference", "fm_method")}
    old["format_version"] = 2
    old["sha256"] = _content_sha256(b.nozzle_ids, b.kpis, {k: v for k, v in old.items() if k != "sha256"})
    arrays["meta"] = np.array(json.dumps(old, sort_keys=True))
    np.savez(tmp_path / "v2.npz", **arrays)
    assert NozzleBaselines.load(tmp_path / "v2.npz").head_sha256 == HeadProfile.default().sha256
    with pytest.raises(ValueError, match="head_sha256"):
        NozzleBaselines(np.arange(3), np.ones((3, 7)), 10e6, 512, 4, head_sha256="abc")


@pytest.mark.parametrize("name", ["h20", "h5"])
def test_simulate_head_on_a_foreign_heads_true_profile_matches_the_independent_simulator(tmp_path, name):
    """Our simulated head against ``tests/foreign_head.py`` (independent code), given that head's true profile."""
    from foreign_head import simulate_foreign, write_true_yaml

    write_true_yaml(tmp_path / "true.yaml", name)
    prof = HeadProfile.load(tmp_path / "true.yaml")
    fs = prof.sample_rate_hz
    theirs = simulate_foreign(name, {"healthy_nozzle": 200}, seed=1)["traces"]
    ours = simulate_head(["healthy_nozzle"] * 200, np.full(200, np.nan), head_seed=1, rng=np.random.default_rng(1),
                         profile=prof)[0]
    assert ours.shape == theirs.shape == (200, prof.n_samples)
    f_ours, f_theirs = np.median(dominant_hz(ours, fs)), np.median(dominant_hz(theirs, fs))
    assert abs(f_ours / prof.healthy_mode()[0] - 1) < 0.03 and abs(f_ours / f_theirs - 1) < 0.01
    s_ours, s_theirs = np.median(ours.std(axis=1)), np.median(theirs.std(axis=1))
    assert abs(s_ours / s_theirs - 1) < 0.05  # the same drive, coupling and sense gain: the same amplitude
