"""inkdiag_core.checks: one checker per kind of input, typed errors that subclass ValueError."""

import math

import numpy as np
import pytest

from inkdiag_core import InkChannelModel, InkChannelParams, checks, design_uio, extract_kpis
from inkdiag_core.checks import InputError, OptionError
from inkdiag_core.kpis import InvalidTraceError
from inkdiag_core.trend import FmTrend


def test_error_types():
    assert issubclass(InputError, ValueError)
    assert issubclass(OptionError, InputError) and issubclass(OptionError, TypeError)
    assert issubclass(InvalidTraceError, InputError)


@pytest.mark.parametrize("good", [1, 2.5, "3e6", np.float32(4.0)])
def test_positive_float_accepts(good):
    assert checks.positive_float("x", good) == float(good)


@pytest.mark.parametrize("bad", [0.0, -1.0, math.nan, math.inf, None, "abc", [1.0]])
def test_positive_float_refuses(bad):
    with pytest.raises(InputError, match=r"x must be a positive finite number, got "):
        checks.positive_float("x", bad)


def test_nonnegative_float():
    assert checks.nonnegative_float("r", 0) == 0.0
    for bad in (-1e-9, math.nan, "z"):
        with pytest.raises(InputError, match=r"r must be a finite number >= 0, got "):
            checks.nonnegative_float("r", bad)


def test_positive_int():
    assert checks.positive_int("n", np.int64(3)) == 3 and type(checks.positive_int("n", 3)) is int
    for bad in (0, -2, 2.0, True, np.bool_(True), "3", None):
        with pytest.raises(InputError, match=r"n must be a positive integer, got "):
            checks.positive_int("n", bad)


def test_sample_rate():
    assert checks.sample_rate(10e6) == 10e6 and checks.sample_rate(np.float32(2.0)) == 2.0
    for bad in (True, "10e6", None):
        with pytest.raises(InputError, match=r"sample_rate_hz must be a positive finite real "
                                             r"number, found .* of type"):
            checks.sample_rate(bad)
    for bad in (0, -1.0, math.nan, math.inf):
        with pytest.raises(InputError, match=r"sample_rate_hz must be positive and finite, found"):
            checks.sample_rate(bad)


def test_error_class_is_chosen_by_the_caller():
    with pytest.raises(InvalidTraceError):
        checks.sample_rate(-1.0, error=InvalidTraceError)


def test_finite_array():
    np.testing.assert_array_equal(checks.finite_array("A", [[1, 2]], shape=(1, 2)), [[1.0, 2.0]])
    with pytest.raises(InputError, match=r"model C must have shape \(1, 3\), got \(3, 1\)"):
        checks.finite_array("model C", np.zeros((3, 1)), shape=(1, 3))
    with pytest.raises(InputError, match="A contains non-finite entries"):
        checks.finite_array("A", [np.nan])


def test_traces_2d():
    y = checks.traces_2d(np.zeros(8, dtype=np.float32), min_samples=2)
    assert y.shape == (1, 8) and y.dtype == np.float32 and y.flags.c_contiguous
    assert checks.traces_2d(np.zeros((2, 8), dtype=int)).dtype == np.float64
    assert checks.traces_2d(np.zeros((2, 8), np.float32), dtype=np.float64).dtype == np.float64
    with pytest.raises(InputError, match=r"y must be a 2-D array of shape \(n_traces, n_samples\), "
                                         r"found ndim=1"):
        checks.traces_2d(np.zeros(8), "y", promote_1d=False)
    with pytest.raises(InputError, match=r"found ndim=3"):
        checks.traces_2d(np.zeros((1, 2, 8)))
    with pytest.raises(InputError, match=r"at least 16 samples per trace, found 8 \(shape \(2, 8\)\)"):
        checks.traces_2d(np.zeros((2, 8)), min_samples=16)
    with pytest.raises(InputError, match="must be real, found complex"):
        checks.traces_2d(np.zeros((2, 8), complex))
    with pytest.raises(InputError, match="real numeric array"):
        checks.traces_2d(np.array([["a"] * 8]))
    bad = np.zeros((4, 8))
    bad[2, 3] = np.inf
    with pytest.raises(InputError, match=r"finite, found 1 NaN or Inf value\(s\) \(non-finite\) "
                                         r"in 1 trace\(s\), first in trace 2"):
        checks.traces_2d(bad)


def test_trace_1d():
    assert checks.trace_1d([1, 2, 3]).dtype == np.float64
    with pytest.raises(InputError, match=r"y must be a 1-D array of shape \(n_samples,\), found ndim=2"):
        checks.trace_1d(np.zeros((2, 3)), "y")
    with pytest.raises(InputError, match="at least 16 samples"):
        checks.trace_1d(np.zeros(3), min_samples=16)


def test_the_core_raises_the_typed_errors():
    """model, observer, trend and kpis report bad inputs through the checks module."""
    with pytest.raises(InputError, match="r_n must be a positive finite number"):
        InkChannelParams(r_n=-1.0)
    with pytest.raises(InputError, match="B_extra must be a finite number >= 0"):
        InkChannelParams(B_extra=-1.0)
    with pytest.raises(InputError, match="sample_rate_hz must be"):
        InkChannelModel().discretize(True)
    A, C, B_f = InkChannelModel().observable()
    with pytest.raises(InputError, match="A contains non-finite entries"):
        design_uio(A * np.nan, C, B_f)
    with pytest.raises(InputError, match="accel_std must be a positive finite number"):
        FmTrend(accel_std=0.0)
    with pytest.raises(InputError, match="rel_floor must be a finite number >= 0"):
        FmTrend(rel_floor=-0.1)
    with pytest.raises(InvalidTraceError, match="sample_rate_hz must be"):
        extract_kpis(np.zeros((2, 16)), 0.0)
