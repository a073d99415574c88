"""scripts/report restrictor: its per-head calibration runs, on a small recording."""

import math

import pytest
from _helpers import load_report


@pytest.fixture(scope="module")
def restrictor():
    return load_report("restrictor")


def test_run_head_gives_every_condition(restrictor):
    out = restrictor.run_head("h20", [1], 60)
    assert math.isclose(out["true_ratio"], 0.783, rel_tol=0.01)
    ratios = {cond: out[cond]["ratio"][0] for cond in restrictor.CONDITIONS}
    assert all(math.isfinite(out[cond]["blocked_err"][0]) for cond in restrictor.CONDITIONS)
    # three different recordings: the conditions change the traces (spreads off, noise off)
    assert len({ratios["as recorded"], ratios["noise only"], ratios["spreads only"]}) == 3
    assert out["joint_converged"] == [True]
    # without spreads the noise alone leaves the split near the truth on this head
    assert abs(ratios["noise only"] / out["true_ratio"] - 1) < 0.15


def test_blocked_mode_is_the_restrictor_branch(restrictor):
    # the restrictor ringing with the chamber: I_r q'' + R_r q' + q / B_t = 0, damped frequency
    I_r, R_r, B_t = 1e8, 4e13, 2e-20  # damping ratio 0.28
    w0, zeta = 1 / math.sqrt(I_r * B_t), R_r / 2 * math.sqrt(B_t / I_r)
    f = restrictor._blocked_mode_hz(1e-20, 1e-20, I_r, R_r)
    assert math.isclose(f, w0 * math.sqrt(1 - zeta**2) / (2 * math.pi), rel_tol=1e-12)
    assert f < restrictor._blocked_mode_hz(1e-20, 1e-20, I_r, 0.0)
