"""scripts/report restrictor: its per-head calibration runs, on a small recording."""

import importlib.util
import math
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def restrictor():
    spec = importlib.util.spec_from_file_location("restrictor_report", ROOT / "scripts/reports/restrictor.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_run_head_gives_every_condition(restrictor):
    out = restrictor.run_head("h20", [1], 60)
    assert math.isclose(out["true_ratio"], 0.783, rel_tol=0.01)
    for cond in restrictor.CONDITIONS:
        (ratio,), (err,) = out[cond]["ratio"], out[cond]["blocked_err"]
        assert 0.02 < ratio < 50 and math.isfinite(err)  # within calibration's bounds
    # without spreads the noise alone leaves the split near the truth on this head
    assert abs(out["noise only"]["ratio"][0] / out["true_ratio"] - 1) < 0.15


def test_blocked_mode_is_the_restrictor_branch(restrictor):
    # an undamped restrictor ringing with the chamber: 1 / (2 pi sqrt(I_r B_t))
    f = restrictor._blocked_mode_hz(1e-20, 1e-20, 1e8, 0.0)
    assert math.isclose(f, 1 / (2 * math.pi * math.sqrt(1e8 * 2e-20)), rel_tol=1e-12)
