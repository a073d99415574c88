"""scripts/report actuator: one head, two actuator ratios, one spread and --empty, on a small training."""

import pytest

from _helpers import load_report

from inkdiag_core import FaultClass


def test_run_labels_heads_whose_actuator_rings_at_the_ratios_asked(tmp_path):
    mod = load_report("actuator")
    res = mod.run("h20", [0.72, 1.0], [0.12], 1, 4, 12, tmp_path, n_per_class=24)
    # the rule is the actuator calibrate assumed for this profile, and the head's own is 1.6 MHz
    assert res["rule_hz"] == pytest.approx(res["report_rule_hz"], rel=1e-12)
    assert res["own"] == pytest.approx(1.6e6 / res["rule_hz"], rel=1e-12) and 0.9 < res["own"] < 1.0
    assert [(r, how) for r, how, _ in res["rows"]] == [
        (0.72, "assumed, spread 0.12"), (0.72, "--empty (12 traces)"),
        (1.0, "assumed, spread 0.12"), (1.0, "--empty (12 traces)")]
    for _, _, sc in res["rows"]:
        assert set(sc["per"]) == {c.value for c in FaultClass} and 0 <= sc["fi"] <= 1
    # the spread reached training; the --empty calibrations measured the test heads' actuators (their dry
    # channels' mode, mass-loaded by a film of at most a tenth: up to 5 % below it)
    assert res["models"][0.12].profile.spreads().actuator_resonance_rel == 0.12
    for r, f in res["f_act"].items():
        assert 0.93 < f / (r * res["rule_hz"]) < 1.02, (r, f, res["rule_hz"])
