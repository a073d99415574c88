"""HeadProfile: the YAML file, its validation, and the default head as a shipped profile."""

import numpy as np
import pytest

from inkdiag_core import FaultClass, HeadProfile, InkChannelParams, ProfileError, simulate
from inkdiag_core.head_profile import NOMINAL_CHANNEL_KEYS
from inkdiag_core.simulation import DriveWaveform, Spreads


def _nominal_doc():
    doc = HeadProfile.default().to_dict()
    doc.pop("sensor")
    doc["channel"] = {k: doc["channel"][k] for k in NOMINAL_CHANNEL_KEYS}
    return doc


def test_default_profile_is_the_simulators_default_head():
    p = HeadProfile.default()
    assert p.is_complete and p.name == "default"
    assert p.channel_params() == InkChannelParams()
    assert p.drive == DriveWaveform()
    assert (p.sample_rate_hz, p.n_samples) == (10e6, 512)
    assert p.spreads() == Spreads()
    f0, zeta = p.healthy_mode()
    assert abs(f0 - 237e3) < 1e3 and 0.05 < zeta < 0.1
    counts = {FaultClass.HEALTHY_NOZZLE: 20, FaultClass.DEEPLY_DRIED: 20, FaultClass.EMPTY_CHANNEL_1: 5}
    np.testing.assert_array_equal(p.simulate(counts, seed=4).traces, simulate(counts, seed=4).traces)


def test_round_trip_through_yaml(tmp_path):
    p = HeadProfile.default().replace(name="h", channel={"r_r": 20e-6}, sensor={"offset_v": 0.05},
                                      spreads_overrides={"temperature_std_k": 0.5}, n_samples=1024,
                                      sample_rate_hz=20e6, calibration={"residual_rel": 0.01})
    path = p.save(tmp_path / "h.yaml")
    q = HeadProfile.load(path)
    assert q == p and q.sha256 == p.sha256
    assert q.channel["r_r"] == 20e-6 and q.n_samples == 1024 and q.spreads().temperature_std_k == 0.5
    # the name and the provenance do not change the head's hash; its physics does
    assert p.replace(name="other", calibration={"x": 1}).sha256 == p.sha256
    assert p.replace(channel={"b": 3e-18}).sha256 != p.sha256


def test_yaml_numbers_without_a_dot_are_numbers():
    text = HeadProfile.default().dumps().replace("r_n: 1.5e-05", "r_n: 15e-6")
    assert HeadProfile.loads(text).channel["r_n"] == 15e-6


def test_nominal_profile_loads_and_says_what_is_missing():
    p = HeadProfile.from_dict(_nominal_doc())
    assert not p.is_complete
    assert set(p.missing) == {"channel.r_r", "channel.L_r", "channel.B_act", "channel.b",
                              "sensor.gain_v_per_m3s"}
    with pytest.raises(ProfileError, match="nominal.*channel.r_r.*inkdiag calibrate"):
        p.simulate({"healthy_nozzle": 1})


@pytest.mark.parametrize("edit, match", [
    (lambda d: d.update(schema="other"), "schema is 'other'"),
    (lambda d: d.update(schema_version=2), "schema_version is 2"),
    (lambda d: d["channel"].pop("mu"), r"channel\.mu: missing \(a number in Pa s\)"),
    (lambda d: d["channel"].update(r_n="abc"), r"channel\.r_n: expected a positive number in m, got 'abc'"),
    (lambda d: d["channel"].update(r_n=-1e-6), r"channel\.r_n: expected a positive number in m"),
    (lambda d: d["channel"].update(r_x=1.0), r"channel\.r_x: unknown key"),
    (lambda d: d["drive"].pop("fall_s"), r"drive\.fall_s: missing \(a number in s\)"),
    (lambda d: d["sampling"].update(n_samples=512.5), r"sampling\.n_samples: expected a positive integer"),
    (lambda d: d["sampling"].update(sample_rate_hz=float("nan")), r"sampling\.sample_rate_hz"),
    (lambda d: d.update(sensor={"noise_std_v": 0.01, "snr_db": 30.0}), "not both"),
    (lambda d: d.update(sensor={"snr_db": -300.0}), r"sensor\.snr_db: expected a number from 0 to 200 dB \(a sensing "
     r"chain's: about 20-60 dB\), got -300\.0"),
    # values that overflowed the simulation: a traceback, or NaN traces fitted into zero constants (helper-137)
    (lambda d: d["sensor"].update(snr_db=1e4), r"sensor\.snr_db: expected a number from 0 to 200 dB.*got 10000\.0"),
    (lambda d: d.update(spreads={"gain_rel": 1e300}), r"spreads\.gain_rel: expected a number from 0 to 1 "
     r"\(relative \(std\)\), got 1e\+300"),
    (lambda d: d.update(spreads={"offset_std_v": 11.0}), r"spreads\.offset_std_v: expected a number from 0 to 10 \(V\)"),
    (lambda d: d.update(spreads={"temperature_std_k": 40.0}), r"spreads\.temperature_std_k: .* from 0 to 30 \(K\)"),
    (lambda d: d["channel"].update(b=1e300), r"the nominal healthy trace overflows \(rms (inf|nan) V\): check "
     r"channel\.b"),
    (lambda d: d["channel"].update(f_act=1e300), r"channel\.f_act: the actuator's resonance 1e\+297 kHz is not below"),
    (lambda d: d.update(calibration={"vp_cal": {"a_sigma": 1e300, "b_sigma": 1.0, "a_omega": 1.0, "b_omega": 1.0}}),
     r"calibration\.vp_cal\.a_sigma: expected a number \(dimensionless, magnitude at most 1000\), got 1e\+300"),
    (lambda d: d.update(calibration={"vp_cal": {"a_sigma": "1e3", "b_sigma": 1.0, "a_omega": 1.0, "b_omega": 1.0}}),
     r"calibration\.vp_cal\.a_sigma: .*got '1e3'"),
    (lambda d: d.update(calibration={"vp_cal": {"a_sigma": 1.0, "b_sigma": 1.0, "a_omega": 1.0}}),
     r"calibration\.vp_cal\.b_omega: .*got None"),
    (lambda d: d.update(calibration={"vp_cal": [1.0]}), r"calibration\.vp_cal: expected a mapping"),
    (lambda d: d.update(sensor="x"), "sensor: expected a mapping"),
    (lambda d: d.update(extra=1), "extra: unknown key"),
    (lambda d: d["channel"].update(f_act=6e6), r"channel\.f_act: the actuator's resonance 6000 kHz is not below "
     r"the Nyquist frequency 5000\.0 kHz"),
    (lambda d: d["channel"].update(f_act=-1.0), r"channel\.f_act: expected a positive number in Hz"),
    # values train took silently, its model then useless (helper-125): a 1-bit ADC; a gain 1000 times low
    (lambda d: d["sensor"].update(adc_bits=1), r"sensor\.adc_bits: 4 to 32 bits \(a sensing ADC's: about 8-16\), "
     r"got 1"),
    (lambda d: d["sensor"].update(gain_v_per_m3s=1e7), r"the nominal healthy trace \(rms 0\.000185 V\) is smaller than "
     r"a quarter of one step of the ADC \(0\.000977 V: \+-2 V, 12 bits\): check sensor\.gain_v_per_m3s"),
    # ... also without adc_range_v (the simulator quantises at the default's 2 V), and before a noise_std_v the low
    # gain puts above the trace (helper-128: the noise was blamed)
    (lambda d: (d["sensor"].update(gain_v_per_m3s=1e7), d["sensor"].pop("adc_range_v")),
     r"smaller than a quarter of one step"),
    (lambda d: (d["sensor"].update(gain_v_per_m3s=1e7, noise_std_v=0.012), d["sensor"].pop("snr_db")),
     r"smaller than a quarter of one step"),
    # kHz written as Hz: calibrate refused it in a nominal profile, train took it in a complete one (helper-125)
    (lambda d: d["channel"].update(f_act=2174.0), r"channel\.f_act, 2\.174 kHz, is not above 2 times the healthy "
     r"mode \(237\.\d kHz\).*\(a value in kHz\?\)"),
    (lambda d: d["channel"].update(zeta_act=1.2), r"channel\.zeta_act: the actuator's damping ratio must be below 1"),
    # microseconds written as seconds (a blind walkthrough's profile, accepted and fitted before)
    (lambda d: d["drive"].update(rise_s=1.0), r"drive\.rise_s: 1 s is longer than 100 us: a drive's rise, dwell "
     r"and fall and the switch delay last microseconds \(about 0\.5-20 us\); the profile's times are in seconds, "
     r"1 us = 1\.0e-6"),
    (lambda d: d["drive"].update(dwell_s=0.9e-3), r"drive\.dwell_s: 0\.0009 s is longer than 100 us"),  # us as ms
    (lambda d: d["drive"].update(switch_delay_s=2e-3), r"drive\.switch_delay_s: 0\.002 s is longer"),
    # millivolts written as volts (helper-76's QA: trained without complaint, 31 % right), kilovolts
    (lambda d: d["drive"].update(amplitude_v=28000.0), r"drive\.amplitude_v: 28000 V is outside 1-500 V, a piezo "
     r"drive's range \(about 10-150 V\): the profile's amplitude is in volts, not mV"),
    (lambda d: d["drive"].update(amplitude_v=0.025), r"drive\.amplitude_v: 0\.025 V is outside 1-500 V.*in volts, not kV"),
    # a complete profile whose physics fails names the value in other units (a QA walkthrough: MHz as Hz, mPa s)
    (lambda d: d["sampling"].update(sample_rate_hz=16), r"above the Nyquist frequency 0\.0 kHz .*\(implausible: "
     r"sampling\.sample_rate_hz 16 Hz \(an inkjet head's: 100000 Hz or more\): a value in other units\?"),
    (lambda d: d["channel"].update(mu=7.0), r"no oscillating healthy mode .*implausible: channel\.mu 7 Pa s \(an "
     r"inkjet head's: 0\.0001 to 0\.5 Pa s\)"),
    (lambda d: d["channel"].update(V_ch=9.0), r"implausible: channel\.V_ch 9 m\^3"),
    # values whose arithmetic fails (helper-100's QA: OverflowError, ZeroDivisionError, a singular matrix later)
    (lambda d: d["channel"].update(r_n=1e308), r"channel values no inkjet head has \(implausible: channel\.r_n "
     r"1e\+308 m \(an inkjet head's: 1e-06 to 0\.0001 m\): more than 1000 times outside"),
    (lambda d: d["channel"].update(mu=1e-300), r"channel values no inkjet head has \(implausible: channel\.mu 1e-300"),
    (lambda d: d["channel"].update(r_r=1e308), r"the channel's model cannot be computed from its values "
     r"\(OverflowError"),
    (lambda d: d["sampling"].update(n_samples=2_000_000_000), r"sampling\.n_samples: at most 65536 samples"),
    (lambda d: d["sampling"].update(sample_rate_hz=1e15), r"sampling\.sample_rate_hz: at most 1e\+10 Hz"),
])
def test_bad_profiles_name_the_key_and_the_unit(edit, match):
    doc = HeadProfile.default().to_dict()
    edit(doc)
    with pytest.raises(ProfileError, match=match):
        HeadProfile.from_dict(doc, source="p.yaml")


def test_noise_above_the_healthy_trace_names_its_key():
    """sensor.noise_std_v above the nominal healthy trace's rms: the simulator's SNR would be negative; the error
    names the profile's key (was: 'spreads.snr_db must be a number >= 0', a key not in the file). Refused at load,
    as docs/heads.md says (helper-126: it was refused only once the head was simulated)."""
    p = HeadProfile.default()
    with pytest.raises(ProfileError, match=r"profile 'default': sensor\.noise_std_v 1000 V is more than the nominal "
                                           r"healthy trace's rms, 0\.185 V"):
        p.replace(sensor={"snr_db": None, "noise_std_v": 1e3})
    assert p.replace(sensor={"snr_db": None, "noise_std_v": 0.18}).spreads().snr_db > 0  # below it: taken


def test_the_longest_drive_segment_is_accepted():
    doc = HeadProfile.default().to_dict()
    doc["drive"].update(dwell_s=1e-4)  # at the bound
    assert HeadProfile.from_dict(doc).drive.dwell_s == 1e-4
    doc["sensor"].update(adc_range_v=10.0)  # 500 V's healthy trace: 2.6 V rms, beyond the default head's +-2 V
    for volts in (1.0, 500.0):  # the amplitude's bounds
        doc["drive"].update(amplitude_v=volts)
        assert HeadProfile.from_dict(doc).drive.amplitude_v == volts


def test_physics_checks_of_a_complete_profile():
    doc = HeadProfile.default().to_dict()
    doc["sampling"]["sample_rate_hz"] = 400e3
    with pytest.raises(ProfileError, match="above the Nyquist frequency 200.0 kHz of sampling.sample_rate_hz$"):
        HeadProfile.from_dict(doc)  # plausible values: no hint
    doc = HeadProfile.default().to_dict()
    doc["sampling"].update(n_samples=16)
    with pytest.raises(ProfileError, match="periods of the healthy mode"):
        HeadProfile.from_dict(doc)
    # an ADC that would clip every healthy trace (its range in mV? 1e-300 made every row out of range)
    for key, value, what in (("adc_range_v", 0.15, r"rms 0.185 V about an offset of 0 V"),
                             ("adc_range_v", 1e-300, "rms 0.185 V"), ("offset_v", -2.5, "rms 0.185 V about an offset of -2.5 V")):
        doc = HeadProfile.default().to_dict()
        doc["sensor"][key] = value
        with pytest.raises(ProfileError, match=rf"sensor.adc_range_v .* clips the nominal healthy trace \({what}"):
            HeadProfile.from_dict(doc)
    doc = HeadProfile.default().to_dict()
    doc["sensor"].update(adc_range_v=0.2)  # just above: the peaks clip, the profile is the user's to give
    assert HeadProfile.from_dict(doc).adc_range_v == 0.2
    del doc["sensor"]["adc_range_v"]  # left out: the default's 2 V, not checked (a head of larger traces)
    doc["drive"].update(amplitude_v=500.0)
    assert HeadProfile.from_dict(doc).adc_range_v == 2.0


def test_missing_and_malformed_files(tmp_path):
    with pytest.raises(ProfileError, match="no such head profile file"):
        HeadProfile.load(tmp_path / "none.yaml")
    (tmp_path / "bad.yaml").write_text("schema: [")
    with pytest.raises(ProfileError, match="not valid YAML"):
        HeadProfile.load(tmp_path / "bad.yaml")
    # a hand-written profile's slip: said with where it is, lines and columns from 1
    (tmp_path / "indent.yaml").write_text("schema: inkdiag.head_profile\nchannel:\n  rho: 1000\n   mu: 3\n")
    with pytest.raises(ProfileError, match=r"not valid YAML at line 4, column 6: mapping values are not allowed here$"):
        HeadProfile.load(tmp_path / "indent.yaml")
    (tmp_path / "flow.yaml").write_text("sampling: {n_samples: [512\n")
    with pytest.raises(ProfileError, match=r"at line 2, column 1: expected ',' or ']', .* \(while parsing a flow "
                                           r"sequence at line 1, column 23\)$"):
        HeadProfile.load(tmp_path / "flow.yaml")
    (tmp_path / "twice.yaml").write_text("schema: a\nschema: b\n")
    with pytest.raises(ProfileError, match=r"at line 2, column 1: duplicate key 'schema'$"):
        HeadProfile.load(tmp_path / "twice.yaml")
    (tmp_path / "bell.yaml").write_text("schema: a\nname:\x07 x\n")  # a control character: its place in the text
    with pytest.raises(ProfileError, match=r"at line 2, column 6: unacceptable character #x0007"):
        HeadProfile.load(tmp_path / "bell.yaml")
    (tmp_path / "listkey.yaml").write_text("schema: a\n? [1, 2]\n: 3\n")  # was: TypeError, unhashable type: 'list'
    with pytest.raises(ProfileError, match=r"at line 2, column 3: a key that is a list, not a name$"):
        HeadProfile.load(tmp_path / "listkey.yaml")
    (tmp_path / "deep.yaml").write_text("schema: " + "[" * 5000 + "]" * 5000)
    with pytest.raises(ProfileError, match="not valid YAML: nested too deeply"):  # not a RecursionError
        HeadProfile.load(tmp_path / "deep.yaml")
    (tmp_path / "list.yaml").write_text("- 1\n- 2\n")
    with pytest.raises(ProfileError, match="not a head profile"):
        HeadProfile.load(tmp_path / "list.yaml")


def test_check_traces_refuses_another_sampling():
    p = HeadProfile.default()
    p.check_traces(np.zeros((3, 512), np.float32), 10e6)
    with pytest.raises(ProfileError,
                       match="sampled at 20000000 Hz x 512 samples; profile 'default' is 10000000 Hz x 512"):
        p.check_traces(np.zeros((3, 512)), 20e6)
    with pytest.raises(ProfileError, match="traces of 256 samples"):
        p.check_traces(np.zeros((3, 256)), 10e6)


def test_profile_sensor_gain_and_noise_reach_the_simulator():
    p = HeadProfile.default().replace(sensor={"gain_v_per_m3s": 2e10, "offset_v": 0.3, "snr_db": None,
                                              "noise_std_v": 0.0, "adc_bits": 24})
    ref = HeadProfile.default().replace(sensor={"snr_db": None, "noise_std_v": 0.0, "adc_bits": 24})
    none = {"gain_rel": 0.0, "offset_std_v": 0.0}
    a = p.replace(spreads_overrides=none).simulate({"healthy_nozzle": 4}, seed=1)
    b = ref.replace(spreads_overrides=none).simulate({"healthy_nozzle": 4}, seed=1)
    np.testing.assert_allclose(a.traces, 2 * b.traces + 0.3, rtol=1e-5, atol=1e-5)
    assert p.spreads().snr_db == np.inf


def test_a_duplicate_key_is_an_error_not_the_last_value():
    text = HeadProfile.default().dumps().replace("rho: 1000.0", "rho: 1000.0\n  rho: 900.0")
    with pytest.raises(ProfileError, match="duplicate key 'rho'"):
        HeadProfile.loads(text, source="p.yaml")


def test_the_actuator_resonance_of_a_profile_reaches_the_empty_channel_classes(tmp_path):
    """channel.f_act / zeta_act (optional): the empty channel rings at f_act without a film; without them, the
    default head's actuator scaled to the profile's B_act (the default head itself: unchanged)."""
    import numpy as np

    p = HeadProfile.default()
    q = HeadProfile.load(p.replace(channel={"f_act": 1.5e6, "zeta_act": 0.05}).save(tmp_path / "q.yaml"))
    assert q.channel["f_act"] == 1.5e6 and q.channel_params().zeta_act == 0.05 and p.channel_params().f_act is None
    assert q.sha256 != p.sha256
    counts = {"empty_channel_1": 60}
    sev = {"empty_channel_1": np.zeros(60)}
    f_p, f_q = (np.median(h.simulate(counts, seed=1, severity=sev).frequency_hz) for h in (p, q))
    assert abs(f_p / 2.175e6 - 1) < 0.01 and abs(f_q / 1.5e6 - 1) < 0.01
    z_q = np.median(q.simulate(counts, seed=1, severity=sev).damping_ratio)
    assert abs(z_q / 0.05 - 1) < 0.05


def test_a_profile_too_large_or_expanding_too_far_is_refused_before_it_costs(tmp_path):
    """helper-125: a 200 MB profile had PyYAML parse for minutes; nested aliases of a few hundred bytes in
    `calibration:` (not checked) went into a 173 MB manifest. Both are refused at once; a plain alias still loads."""
    from inkdiag_core.head_profile import MAX_PROFILE_BYTES

    text = HeadProfile.default().dumps()
    big = tmp_path / "big.yaml"
    big.write_text(text + "# " + "x" * MAX_PROFILE_BYTES + "\n")
    with pytest.raises(ProfileError, match=r"big\.yaml: 1,04\d,\d{3} bytes is not a head profile"):
        HeadProfile.load(big)
    with pytest.raises(ProfileError, match="characters is not a head profile"):
        HeadProfile.loads(big.read_text())
    levels = ['a: &a ["x", "x", "x", "x", "x", "x", "x", "x", "x"]']
    levels += [f"{c}: &{c} [{', '.join([f'*{p}'] * 9)}]" for p, c in zip("abcdef", "bcdefg")]  # 9**7 values
    bomb = text + "calibration:\n" + "".join(f"  {line}\n" for line in levels)
    with pytest.raises(ProfileError, match="more than 100,000 values once its YAML aliases are expanded"):
        HeadProfile.loads(bomb)
    shared = text + "calibration:\n  a: &a [1, 2]\n  b: *a\n"
    assert HeadProfile.loads(shared).calibration["b"] == [1, 2]
    # the same through YAML's pair lists, which load as tuples (helper-128: not counted, a 70 MB manifest)
    pairs = ['a: &a ["x", "x", "x", "x", "x", "x", "x", "x", "x"]']
    pairs += [f"{c}: &{c} !!pairs [{', '.join([f'k: *{p}'] * 9)}]" for p, c in zip("abcdef", "bcdefg")]
    with pytest.raises(ProfileError, match="more than 100,000 values once its YAML aliases are expanded"):
        HeadProfile.loads(text + "calibration:\n" + "".join(f"  {line}\n" for line in pairs))


@pytest.mark.parametrize("entry, match", [
    ("when: 2026-11-29", r"calibration\.when: a date is not a plain value .*quote a date"),
    ("s: !!set {a, b}", r"calibration\.s: a set is not a plain value"),
    ("1: x", r"calibration: the key 1 is not a name: quote it"),
    ("on: 3", r"calibration: the key True is not a name: quote it \(YAML reads on, off, yes and no as true"),
])
def test_a_calibration_section_of_other_than_plain_data_is_refused_at_load(entry, match):
    """A YAML date or set in `calibration:` loaded, then broke the profile's sha256 and a model's manifest with a
    TypeError (helper-128's review); quoted, a date is a string and loads; a pair list is a list of lists."""
    text = HeadProfile.default().dumps() + "calibration:\n"
    with pytest.raises(ProfileError, match=match):
        HeadProfile.loads(text + f"  {entry}\n", source="p.yaml")
    assert HeadProfile.loads(text + "  when: '2026-11-29'\n").sha256 == HeadProfile.default().sha256
    assert HeadProfile.loads(text + "  p: !!pairs [{a: 1}]\n").dumps().count("- a") == 1
    # from Python: numbers (numpy's too) go; a numpy date or complex would break the sha256 later (helper-129)
    head = HeadProfile.default()
    assert head.replace(calibration={"x": np.float64(1.5), "v": np.arange(3), "b": [np.bool_(True)]}).sha256
    for odd in (np.datetime64("2026-11-29"), np.complex128(1 + 2j), np.array([{1}], dtype=object)):
        with pytest.raises(ProfileError, match=r"calibration\.t: a .* is not a plain value"):
            head.replace(calibration={"t": odd})


def test_a_coarse_adc_is_taken_where_the_trace_spans_its_steps():
    """4 bits (the fewest) on the default head: the healthy trace's rms, 0.185 V, is most of a 0.25 V step, taken."""
    assert HeadProfile.default().replace(sensor={"adc_bits": 4}).adc_bits == 4
