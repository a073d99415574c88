"""FDI on a head profile: bands follow the head, screening in seconds, FaultDetector(profile=...),
its model file's head, training on a head (train_detector) and refusing another head's model."""

import json

import numpy as np
import pytest
from sklearn.base import clone

from inkdiag_core import (
    FaultClass,
    FaultDetector,
    FrameLabeller,
    HeadProfile,
    LabellerConfigError,
    ModelFileError,
    Recording,
    load_detector,
    make_fdi_pipeline,
    save_detector,
    train_detector,
)
from inkdiag_core.fdi import BAND_EDGES_HZ, head_band_edges_hz
from inkdiag_core.head_profile import ProfileError
from inkdiag_core.persistence import read_manifest
from inkdiag_core.residual import MODIFIED_BANDS_HZ, ResidualFilter, head_bands_hz
from inkdiag_core.screening import clip_run_samples, screen_traces

N_PER_CLASS = 24


def foreign_head(**changes):
    """A head of other geometry, ink and sampling (20 MHz x 1024)."""
    doc = dict(name="foreign20", sample_rate_hz=20e6, n_samples=1024,
               channel={"rho": 1100.0, "mu": 6e-3, "r_n": 11e-6, "L_n": 45e-6})
    doc.update(changes)
    return HeadProfile.default().replace(**doc)


@pytest.fixture(scope="module")
def head():
    return foreign_head()


@pytest.fixture(scope="module")
def head_detector(head):
    det, info = train_detector(head, n_per_class=N_PER_CLASS, seed=2)
    return det, info


# -- bands and screening follow the head ------------------------------------------------------


def test_bands_scale_with_the_heads_healthy_mode(head):
    scale = head.frequency_scale()
    assert 0.5 < scale < 1.0  # a smaller, lighter-ink nozzle: lower mode here
    np.testing.assert_allclose(head_bands_hz(head), np.array(MODIFIED_BANDS_HZ) * scale)
    np.testing.assert_allclose(head_band_edges_hz(head), np.array(BAND_EDGES_HZ) * scale)
    assert head_bands_hz(HeadProfile.default()) == MODIFIED_BANDS_HZ  # scale exactly 1
    # a head whose empty-channel band the sampling cannot hold: that band is left out, the filter works
    fast = HeadProfile.default().replace(name="fast5", sample_rate_hz=5e6, n_samples=256,
                                         channel={"r_n": 10e-6, "L_n": 30e-6, "V_ch": 2e-12})
    bands = head_bands_hz(fast)
    assert fast.frequency_scale() > 1.06 and len(bands) == 2 and max(bands) < 0.45 * 5e6
    sim = fast.simulate({c: 2 for c in FaultClass}, seed=0)
    ResidualFilter("modified", sample_rate_hz=5e6, params=fast.channel_params(), bands_hz=bands).fit(sim.traces)
    assert head_band_edges_hz(HeadProfile.default()) == BAND_EDGES_HZ


def test_a_pipeline_on_a_profile_uses_the_heads_model_and_bands(head):
    pipe = make_fdi_pipeline("rf", "rich", profile=head)  # at the profile's sample rate
    with pytest.raises(ValueError, match="sampled at"):
        make_fdi_pipeline("rf", "rich", sample_rate_hz=10e6, profile=head)
    union = pipe.named_steps["features"]
    raw = dict(union.transformer_list)["raw"]
    res = dict(union.transformer_list)["kpi_r_modified"].named_steps["residual"]
    assert raw.band_edges_hz == head_band_edges_hz(head) and raw.sample_rate_hz == 20e6
    assert res.params == head.channel_params() and res.bands_hz == head_bands_hz(head)
    sim = head.simulate({c: 3 for c in FaultClass}, seed=0)
    f = ResidualFilter("modified", sample_rate_hz=head.sample_rate_hz, params=head.channel_params(),
                       bands_hz=head_bands_hz(head)).fit(sim.traces)
    # the filter's band resonators sit at the head's bands, not the default head's
    peaks = np.abs(f.design_.frequency_response(head_bands_hz(head)))
    off = np.abs(f.design_.frequency_response(MODIFIED_BANDS_HZ))
    assert np.all(peaks > off)


def test_a_default_profile_builds_the_same_features_as_no_profile():
    sim = HeadProfile.default().simulate({c: 4 for c in FaultClass}, seed=1)
    for feats in ("rich", "kpi_y+r_modified"):
        a = make_fdi_pipeline("rf", feats)[:-1].fit(sim.traces, sim.label_values()).transform(sim.traces)
        b = make_fdi_pipeline("rf", feats, profile=HeadProfile.default())[:-1].fit(
            sim.traces, sim.label_values()).transform(sim.traces)
        np.testing.assert_array_equal(a, b)


def test_the_clipped_run_is_a_duration():
    assert clip_run_samples(10e6) == 5  # as tuned at 10 MHz
    assert clip_run_samples(20e6) == 10
    assert clip_run_samples(5e6) == 4  # never below 4 samples
    assert clip_run_samples(2e6) == 4


def test_a_5_mhz_heads_quantised_healthy_peaks_are_not_clipped():
    """helper-87: a 5 MHz x 256 head with a 10-bit ADC had 1 % of its healthy traces called clipped (3 equal codes
    at the peak, 0.86 V against a 2 V rail); a saturated trace still is."""
    from foreign_head import simulate_foreign

    s = simulate_foreign("h5", {"healthy_nozzle": 2000}, seed=2)
    x, fs = s["traces"], s["sample_rate_hz"]
    assert fs == 5e6
    reasons = screen_traces(x, sample_rate_hz=fs)[1]
    assert np.mean(reasons == "clipped") <= 0.002, np.mean(reasons == "clipped")
    sat = np.clip(x[:20] * 2.0, -0.9 * np.abs(x[:20]).max(axis=1, keepdims=True), None)  # overdriven into a rail
    assert (screen_traces(sat, sample_rate_hz=fs)[1] == "clipped").mean() >= 0.9
    # a 7-sample plateau (0.35 us at 20 MHz) is not clipping at 20 MHz; at 10 MHz it would be
    x = np.sin(np.linspace(0, 40, 1024))[None, :].repeat(2, axis=0)
    x[:, 100:107] = x.max() + 0.1
    assert screen_traces(x, sample_rate_hz=20e6)[1].tolist() == ["", ""]
    assert screen_traces(x, sample_rate_hz=10e6)[1].tolist() == ["clipped", "clipped"]
    x[1, 100:112] = x.max()
    assert screen_traces(x, sample_rate_hz=20e6)[1].tolist() == ["", "clipped"]


# -- FaultDetector with a profile --------------------------------------------------------------


def test_a_profile_is_a_proper_estimator_parameter(head):
    det = FaultDetector(profile=head, n_estimators=5)
    assert det.get_params()["profile"] is head
    c = clone(det)
    assert c.profile == head and c.profile.sha256 == head.sha256
    assert det.sample_rate_hz_ == 20e6 and FaultDetector().sample_rate_hz_ == 10e6
    assert FaultDetector(sample_rate_hz=5e6).sample_rate_hz_ == 5e6  # old callers
    assert det.head_sha256 == head.sha256
    assert FaultDetector().head_sha256 == HeadProfile.default().sha256


def test_a_detector_refuses_traces_and_rates_of_another_sampling(head):
    sim = HeadProfile.default().simulate({c: 4 for c in FaultClass}, seed=0)
    with pytest.raises(ValueError, match="1024"):
        FaultDetector(profile=head, n_estimators=5).fit(sim.traces, sim.label_values())
    with pytest.raises(ValueError, match="sampled at"):
        FaultDetector(profile=head, sample_rate_hz=10e6).fit(sim.traces, sim.label_values())
    nominal = head.replace(channel={"r_r": None})
    with pytest.raises(ValueError, match="calibrate"):
        FaultDetector(profile=nominal).fit(sim.traces, sim.label_values())


def test_a_detector_with_a_profile_round_trips_with_its_hash(head, head_detector, tmp_path):
    det, info = head_detector
    mpath = save_detector(det, tmp_path / "head.joblib", config=info)
    cfg = read_manifest(tmp_path / "head.joblib")["config"]
    assert cfg["profile_sha256"] == head.sha256 and cfg["profile_name"] == "foreign20"
    assert HeadProfile.from_dict(cfg["profile"]).sha256 == head.sha256
    assert (cfg["sample_rate_hz"], cfg["n_samples"]) == (20e6, 1024)
    assert cfg["n_per_class"] == N_PER_CLASS and cfg["profile_name"] == "foreign20"
    json.loads(mpath.read_text())
    back = load_detector(tmp_path / "head.joblib")
    assert back.profile == head and back.head_sha256 == head.sha256
    sim = head.simulate({c: 3 for c in FaultClass}, seed=9)
    np.testing.assert_array_equal(back.label(sim.traces).classes, det.label(sim.traces).classes)


def test_a_default_head_file_says_so_and_old_files_load_as_the_default_head(tmp_path):
    sim = HeadProfile.default().simulate({c: 8 for c in FaultClass}, seed=0)
    det = FaultDetector(n_estimators=5, min_samples_leaf=1).fit(sim.traces, sim.label_values())
    save_detector(det, tmp_path / "d.joblib")
    cfg = read_manifest(tmp_path / "d.joblib")["config"]
    assert cfg["profile"] is None and cfg["profile_sha256"] == HeadProfile.default().sha256
    assert cfg["sample_rate_hz"] == 10e6
    # a default-head model stays the default head's when the shipped default profile changes
    mpath = tmp_path / "d.joblib.manifest.json"
    m = json.loads(mpath.read_text())
    m["config"]["profile_sha256"] = "0" * 64
    mpath.write_text(json.dumps(m))
    FrameLabeller(load_detector(tmp_path / "d.joblib"), profile=HeadProfile.default())
    # a file from before profiles: no profile keys in its manifest, no profile attribute inside
    old = tmp_path / "old.joblib"
    del det.profile
    det.__dict__["sample_rate_hz"] = 10e6
    from inkdiag_core.persistence import save_model

    save_model(det, old, config={"estimator": "FaultDetector", "kind": "rf", "features": "kpi_y",
                                 "fd_threshold": float(det.fd_threshold_)})
    back = load_detector(old)
    assert back.profile is None and back.head_sha256 == HeadProfile.default().sha256
    FrameLabeller(back, profile=HeadProfile.default())  # accepted for the default head


def test_a_model_of_head_a_is_refused_for_head_b(head, head_detector, tmp_path):
    det, _ = head_detector
    with pytest.raises(LabellerConfigError, match="another head"):
        FrameLabeller(det, profile=HeadProfile.default())
    other = head.replace(name="foreign20b", channel={"mu": 7e-3})  # same sampling, other head
    with pytest.raises(LabellerConfigError, match="foreign20b"):
        FrameLabeller(det, profile=other)
    lab = FrameLabeller(det, profile=head)
    assert (lab.sample_rate_hz, lab.n_samples) == (20e6, 1024)
    # a manifest whose head is not the detector's inside is refused before use
    save_detector(det, tmp_path / "m.joblib")
    mpath = tmp_path / "m.joblib.manifest.json"
    m = json.loads(mpath.read_text())
    m["config"]["profile_sha256"] = HeadProfile.default().sha256
    mpath.write_text(json.dumps(m))
    with pytest.raises(ModelFileError, match="profile_sha256"):
        load_detector(tmp_path / "m.joblib")


# -- training on a head --------------------------------------------------------------------------


def test_training_on_a_head_classifies_its_traces(head, head_detector):
    det, info = head_detector
    assert det.profile is head and info["training_data"] == "simulated"
    sim = head.simulate({c: 20 for c in FaultClass}, seed=11)
    out = det.label(sim.traces)
    assert np.mean(out.classes == sim.label_values()) > 0.8
    faulty = ~np.isin(sim.label_values(), ("healthy_nozzle", "ok_signal"))
    flagged = ~np.isin(out.classes.astype(str), ("healthy_nozzle", "ok_signal"))
    assert np.mean(flagged[faulty]) > 0.95


def test_training_refuses_a_nominal_profile(head):
    with pytest.raises(ProfileError, match="calibrate"):
        train_detector(head.replace(channel={"B_act": None}), n_per_class=8)


def test_the_default_head_trains_the_default_model():
    """train_detector on the default head = train_default_model's detector (same rows, same seed)."""
    from inkdiag_core import simulate

    det, _ = train_detector(HeadProfile.default(), n_per_class=10, seed=4)
    sim = simulate({c: 10 for c in FaultClass}, seed=4)
    ref = FaultDetector(sample_rate_hz=10e6, random_state=4).fit(sim.traces, sim.label_values())
    assert det.scores_ == ref.scores_ and det.fd_threshold_ == ref.fd_threshold_
    new = simulate({c: 5 for c in FaultClass}, seed=40)
    np.testing.assert_array_equal(det.label(new.traces).confidence, ref.label(new.traces).confidence)


def test_training_with_recorded_rows_weighs_each_recorded_class_as_its_simulated_one(head):
    rec_sim = head.simulate({FaultClass.HEALTHY_NOZZLE: 9, FaultClass.FULLY_BLOCKED: 5}, seed=30)
    x = rec_sim.traces.copy()
    x[0, 4] = np.nan  # rows labelling would call invalid are not trained on
    x[-1, :] = 0.1
    data = Recording.from_arrays(x, head.sample_rate_hz, label=rec_sim.label_values())
    det, info, td = train_detector(head, n_per_class=16, seed=3, data=data, return_data=True)
    assert info["n_real_rows"] == 12 and info["n_real_rows_invalid"] == 2
    assert info["n_real_rows_screened_out"] == 2 and info["real_rows_per_class"] == {"fully_blocked": 4,
                                                                                        "healthy_nozzle": 8}
    assert info["training_data"] == "simulated+recorded" and np.isfinite(td.traces).all()
    real = td.labels[td.real]
    # fitted part: replicated up to 12 rows (16 * 0.75) per class; validation part: 2 and 1 rows once
    assert (real == "healthy_nozzle").sum() == 12 + 2 and (real == "fully_blocked").sum() == 12 + 1
    assert det.scores_["n_validation"] == 12 * 4 + 3  # 25 % of the simulated rows and the held-out real ones
    with pytest.raises(ValueError, match="label"):
        train_detector(head, n_per_class=8, data=Recording.from_arrays(rec_sim.traces, head.sample_rate_hz))
    with pytest.raises(ProfileError, match="Hz"):
        train_detector(head, n_per_class=8, data=Recording.from_arrays(
            rec_sim.traces, 10e6, label=rec_sim.label_values()))


def test_a_recordings_own_copies_stay_on_one_side_of_the_validation_split(head):
    """helper-120: a recording with every row twice put 278 of its 360 validation rows' twins in training, so the
    scores saw rows the model was fitted on. Identical rows of a class now go to one side together, counted; the
    recorded validation rows' own score is kept."""
    from inkdiag_core.training import _real_rows

    rec = head.simulate({FaultClass.HEALTHY_NOZZLE: 20, FaultClass.FULLY_BLOCKED: 12}, seed=31)
    x = np.concatenate([rec.traces, rec.traces[:20]])  # the healthy rows twice
    lab = np.concatenate([rec.label_values(), rec.label_values()[:20]])
    data = Recording.from_arrays(x, head.sample_rate_hz, label=lab)
    Xf, yf, Xv, yv, counts = _real_rows(data, head, 3, 0.25, 16)
    assert counts["n_real_rows_repeated"] == 20 and counts["n_real_rows_validation"] == len(yv) == 10 + 3
    fit_rows = {r.tobytes() for r in Xf}
    assert not any(r.tobytes() in fit_rows for r in Xv)  # no validation row is also a training row
    # helper-122: a large group of copies first in the permutation was held out whole (9 of 12 rows); groups that
    # do not fit in the class's quarter stay in training
    x9 = np.concatenate([np.repeat(rec.traces[:1], 9, axis=0), rec.traces[1:4]])
    for seed in range(6):
        _, _, _, yv9, c9 = _real_rows(Recording.from_arrays(x9, head.sample_rate_hz, label=lab[:12]), head, seed,
                                      0.25, 16)
        assert len(yv9) <= 3 and c9["n_real_rows_repeated"] == 8
    # without copies the split is as before: a quarter of each class, the first of a seeded permutation
    Xf1, _, Xv1, yv1, c1 = _real_rows(Recording.from_arrays(rec.traces, head.sample_rate_hz,
                                                            label=rec.label_values()), head, 3, 0.25, 16)
    assert c1["n_real_rows_repeated"] == 0 and len(yv1) == 5 + 3
    det, info = train_detector(head, n_per_class=16, seed=3, data=data)
    assert 0.0 <= info["validation_real_fi_accuracy"] <= 1.0
    # helper-120: a recording in millivolts said only "no row is usable"; the units are asked about
    with pytest.raises(ValueError, match=r"no row is usable .*52 of 52 rows have a sample beyond 10 V: are the "
                                         r"traces in volts \(not millivolts"):
        train_detector(head, n_per_class=8, data=Recording.from_arrays(x * 1e3, head.sample_rate_hz, label=lab))


def test_the_default_training_size_and_its_leaves():
    """inkdiag train's defaults are training's (N_PER_CLASS, POSTERIOR_DRAWS); the forest's leaves scale with the rows
    (3 per 1,000)."""
    import argparse
    import inspect

    from inkdiag_core.calibration import POSTERIOR_DRAWS
    from inkdiag_core.training import N_PER_CLASS, leaf_size
    from inkdiag_ros.verbs import train as train_verb

    parser = argparse.ArgumentParser()
    train_verb.add_arguments(parser)
    assert parser.get_default("n_per_class") == N_PER_CLASS == 5000 and leaf_size(N_PER_CLASS) == 15
    default_draws = inspect.signature(train_detector).parameters["posterior_draws"].default
    assert parser.get_default("posterior_draws") == default_draws == POSTERIOR_DRAWS == 5
    assert [leaf_size(n) for n in (8, 400, 1000, 1166, 1167, 1500, 2500, 3000)] == [3, 3, 3, 3, 4, 5, 8, 9]
    det, info = train_detector(HeadProfile.default(), n_per_class=2000, seed=1, unknown_rate=None, n_estimators=2)
    assert det.min_samples_leaf == 6 and info["n_per_class"] == 2000
    det, _ = train_detector(HeadProfile.default(), n_per_class=2000, seed=1, unknown_rate=None, n_estimators=2,
                            min_samples_leaf=3)  # given: kept
    assert det.min_samples_leaf == 3


def test_twin_frames_in_chunks_are_the_same_numbers():
    from inkdiag_core.simulation import healthy_twin_chunks, healthy_twin_frames

    kw = dict(seed=5, n_frames=3, noise_std_v=0.01, sample_rate_hz=10e6, n_samples=128)
    _, whole = healthy_twin_frames(11, **kw)
    parts = list(healthy_twin_chunks(11, chunk_rows=4, **kw))
    assert [a for a, _ in parts] == [0, 4, 8]
    np.testing.assert_array_equal(np.concatenate([f for _, f in parts]), whole)
    with pytest.raises(ValueError, match="chunk_rows must be an integer >= 1"):
        healthy_twin_chunks(11, chunk_rows=0, **kw)  # refused on the call, before any block
