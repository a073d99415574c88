"""scripts/report restrictor_spread: one head and seed, the fit alone against a spread, on a small training."""

from _helpers import load_report

from inkdiag_core import FaultClass


def test_run_compares_the_draw_counts_on_one_recording(tmp_path):
    mod = load_report("restrictor_spread")
    ir_err, res = mod.run("h20", 1, [1, 3], 4, tmp_path, n_per_class=24)
    assert abs(ir_err) < 0.3 and set(res) == {1, 3}
    assert res[1]["sd"] == 0.0 and res[3]["sd"] == 0.03  # the fit alone; healthy traces alone: the scatter
    for r in res.values():
        assert set(r["per"]) == {c.value for c in FaultClass} and 0 <= r["fi"] <= 1
        assert r["per"][r["weakest"]] == min(r["per"].values())
