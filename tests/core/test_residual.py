"""Residual filters (thesis 3.3)."""

import numpy as np
import pytest

from _helpers import FS, damped
from inkdiag_core import InkChannelModel
from inkdiag_core.kpis import extract_kpis
from inkdiag_core.residual import MODIFIED_BANDS_HZ, ResidualFilter, design_residual_filter


def healthy_traces(n, seed=0, n_samples=512):
    """Free responses of the healthy model from random initial states (independent path)."""
    rng = np.random.default_rng(seed)
    m = InkChannelModel()
    out = np.empty((n, n_samples))
    for i in range(n):
        x0 = np.array([rng.normal(0, 1e-12), rng.normal(1e-6, 2e-7), rng.normal(1e-6, 2e-7)])
        out[i] = m.free_response(x0, n_samples, FS)
    return out / np.abs(out).max()


@pytest.mark.parametrize("kind", ["original", "modified"])
def test_filters_are_stable_with_positive_margins(kind):
    d = design_residual_filter(kind)
    assert d.is_stable and np.all(np.abs(d.poles) < 1)
    assert np.all(d.poles_hz.real < 0)  # left half plane
    m = d.margins()
    assert m["phase_margin_deg"] > 30 and m["gain_margin_db"] > 0


def test_modified_filter_keeps_its_three_bands_and_rejects_dc():
    orig, mod = design_residual_filter("original"), design_residual_filter("modified")
    f = np.array(MODIFIED_BANDS_HZ)
    assert np.all(np.abs(mod.frequency_response(f)) > np.abs(orig.frequency_response(f)))
    assert abs(mod.frequency_response([1.0])[0]) < 0.01  # PI action: offsets do not pass
    with pytest.raises(ValueError, match="kind"):
        design_residual_filter("bogus")
    with pytest.raises(ValueError, match="twice the highest band"):
        design_residual_filter("modified", sample_rate_hz=2e6)


def test_healthy_residual_is_small_and_faulty_is_not():
    y_h = healthy_traces(20, seed=1)
    rf = ResidualFilter("original").fit(y_h)
    r_h = rf.transform(y_h)
    y_f = damped(2124e3, 0.05, 20, seed=2)
    r_f = rf.transform(y_f)
    e = lambda a: np.sum(a[:, 100:] ** 2, axis=1)  # after the observer transient
    assert np.median(e(r_h) / e(y_h)) < 0.05
    assert np.median(e(r_f) / e(y_f)) > 0.5


def test_residual_loses_the_empty_channel_frequency_and_modified_keeps_it():
    """Thesis Table 11: the residual's dominant peak moves to the healthy band."""
    y = damped(2124e3, 0.03, 30, seed=3) + 0.5 * healthy_traces(30, seed=4)
    r = ResidualFilter("modified").fit(healthy_traces(10)).transform(y)
    assert np.median(extract_kpis(r, FS)[:, 1]) == pytest.approx(2124e3, rel=0.02)
