"""scripts/report actuator: one head, two actuator ratios, one spread and --empty, on a small training."""

import numpy as np

from _helpers import load_report

from inkdiag_core import FaultClass
from inkdiag_core.kpis import extract_kpis


def test_run_labels_heads_whose_actuator_rings_at_the_ratios_asked(tmp_path):
    mod = load_report("actuator")
    own, rows = mod.run("h20", [0.72, 1.0], [0.085], 1, 4, 12, tmp_path, n_per_class=24)
    assert abs(own - 1.6e6 / mod.rule_hz("h20")) < 1e-12  # h20's own actuator: 1.6 MHz
    assert [(r, how) for r, how, _ in rows] == [(0.72, "assumed, spread 0.085"), (0.72, "--empty (12 traces)"),
                                                (1.0, "assumed, spread 0.085"), (1.0, "--empty (12 traces)")]
    for _, _, sc in rows:
        assert set(sc["per"]) == {c.value for c in FaultClass} and 0 <= sc["fi"] <= 1
    # the test heads' dry channels ring where the ratio puts their actuator
    fs = mod.fh.FOREIGN_HEADS["h20"]["sampling"]["sample_rate_hz"]
    f = [np.median(extract_kpis(mod.fh.simulate_foreign(mod._head("h20", r * mod.rule_hz("h20")),
                                                        {"empty_channel_1": 20}, 3)["traces"], fs)[:, 1])
         for r in (0.72, 1.0)]
    assert abs(f[0] / f[1] - 0.72) < 0.03, f
