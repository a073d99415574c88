"""Closed-form checks of the ink-channel model (thesis 2.3, eq. 12, Appendix E-F)."""

import math

import numpy as np
import pytest
from scipy.linalg import expm

from inkdiag_core import InkChannelModel, InkChannelParams, alpha, fault_fm, fm_to_viscosity
from inkdiag_core.model import viscosity_to_fm

P = InkChannelParams()


def test_healthy_resonance_matches_closed_form_within_1_percent():
    f, zeta = InkChannelModel(P).dominant_mode()
    f_closed = math.sqrt((1.0 / P.I_r + 1.0 / P.I_n) / P.B_t) / (2.0 * math.pi)
    assert abs(f / f_closed - 1.0) < 0.01
    assert abs(f - 237.15e3) < 0.01 * 237.15e3  # Table 3
    assert 0.05 < zeta < 0.1


def test_derived_parameters_match_table_1_formulas():
    assert P.I_n == pytest.approx(1000 * (60e-6 + math.pi * 15e-6 / 4) / (math.pi * 15e-6**2))
    assert P.R_n == pytest.approx(8 * 10e-3 * 60e-6 / (math.pi * 15e-6**4))
    assert P.B_t == pytest.approx(P.B_act + P.V_ch / (P.rho * P.c**2))
    assert P.I_r / P.I_n == pytest.approx(1.03, abs=0.01)
    assert P.R_r / P.R_n == pytest.approx(0.5, abs=0.01)


def test_restrictor_only_resonance_when_nozzle_inertance_is_huge():
    # a closed nozzle is the limit I_n -> infinity: only the restrictor resonates
    A, _, _ = InkChannelModel(P).observable()
    A[2, 0] = 0.0  # 1 / (I_n B_t) -> 0
    lam = np.linalg.eigvals(A)
    f = np.abs(lam.imag).max() / (2 * math.pi)
    f0 = 1.0 / (2 * math.pi * math.sqrt(P.I_r * P.B_t))
    zeta = P.R_r / P.I_r / (2 * 2 * math.pi * f0)
    assert f == pytest.approx(f0 * math.sqrt(1 - zeta**2), rel=1e-9)
    assert f == pytest.approx(166.35e3, rel=0.01)  # Table 3 fully blocked


def test_alpha_and_fault_fm_against_hand_computed_appendix_f_numbers():
    # alpha = 8 L_n / (rho (L_n + pi r_n / 4) r_n^2)
    #       = 8 * 60e-6 / (1000 * 71.780972e-6 * 2.25e-10) = 2.972004e7  1/(Pa s^2)
    assert alpha(P) == pytest.approx(2.972004e7, rel=1e-6)
    # ink viscosity 10 -> 30 mPa s: f_m = -alpha * 0.02 = -5.944008e5 1/s
    assert fault_fm(P, 30e-3) == pytest.approx(-5.944008e5, rel=1e-6)
    # same thing from the model: change of entry (3, 3) of A
    m0 = InkChannelModel(P)
    m1 = InkChannelModel(P.replace(mu_nozzle=30e-3))
    dA = m1.observable()[0] - m0.observable()[0]
    assert dA[2, 2] == pytest.approx(fault_fm(P, 30e-3), rel=1e-12)
    assert np.count_nonzero(dA) == 1
    d_mu, mu = fm_to_viscosity(P, fault_fm(P, 30e-3))
    assert d_mu == pytest.approx(0.02) and mu == pytest.approx(0.03)
    assert viscosity_to_fm(P, 0.03) == pytest.approx(fault_fm(P, 0.03))


def test_drying_lowers_the_frequency_like_table_3():
    f = [InkChannelModel(P.replace(mu_nozzle=k * P.mu)).dominant_mode()[0] for k in (3, 4.5, 7.5)]
    assert f[0] > f[1] > f[2]
    np.testing.assert_allclose(np.array(f) / 1e3, [225.13, 212.73, 189.65], rtol=0.03)


def test_observable_form_is_the_reduction_of_the_4_state_model():
    m = InkChannelModel(P.replace(mu_nozzle=25e-3))
    A4, B4, C4 = m.full()
    A3, C3, B_f = m.observable()
    T = np.array([[1.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
    np.testing.assert_allclose(T @ A4, A3 @ T, rtol=1e-12, atol=0)
    np.testing.assert_allclose(T @ B4, m.input_matrix(), rtol=1e-12)
    np.testing.assert_allclose(C4, C3 @ T)
    np.testing.assert_array_equal(B_f.ravel(), [0.0, 0.0, 1.0])
    ev4 = np.sort_complex(np.linalg.eigvals(A4))
    ev3 = np.sort_complex(np.append(np.linalg.eigvals(A3), 0.0))
    np.testing.assert_allclose(ev4, ev3, rtol=1e-9, atol=1e-6 * np.abs(ev3).max())
    x4 = np.array([1e-17, -2e-17, 3e-11, 4e-11])
    np.testing.assert_allclose(m.reduce_state(x4), T @ x4)


def test_discretisations():
    m = InkChannelModel(P)
    fs = 10e6
    fm = fault_fm(P, 40e-3)
    A, _, _ = m.observable(fm)
    np.testing.assert_allclose(m.discretize(fs, fm), expm(A / fs), rtol=1e-12)
    # Appendix E: exact for fm = 0, first-order in fm dt otherwise
    np.testing.assert_allclose(m.discretize_appendix_e(fs), m.discretize(fs), rtol=1e-12)
    Ad_h, Ad_e, Ad_x = m.discretize(fs), m.discretize_appendix_e(fs, fm), m.discretize(fs, fm)
    assert (Ad_e - Ad_h)[2, 2] == pytest.approx(fm / fs, rel=1e-12)
    # the exact change of entry (3, 3) is fm dt only to first order: here fm dt = -0.089
    # and R_n/I_n dt = 0.03, and the exact change is -0.0825 (7.5 % smaller)
    assert (Ad_x - Ad_h)[2, 2] == pytest.approx(fm / fs, rel=0.1)
    assert not np.allclose(Ad_e, Ad_x, rtol=1e-9, atol=0)  # only an approximation


def test_free_response_decays_at_the_dominant_mode():
    m = InkChannelModel(P)
    y = m.free_response([0.0, 1e-11, 1e-11], 512, 10e6)
    assert y[0] == pytest.approx(2e-11)
    spec = np.abs(np.fft.rfft(y))
    assert spec.argmax() * 10e6 / 512 == pytest.approx(237e3, abs=10e6 / 512)


@pytest.mark.parametrize("name", ["r_n", "L_n", "mu", "rho", "B_act", "c"])
@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan")])
def test_non_positive_physical_parameters_raise_naming_the_argument(name, bad):
    with pytest.raises(ValueError, match=name):
        InkChannelParams(**{name: bad})


def test_fault_fm_rejects_non_positive_viscosity():
    with pytest.raises(ValueError, match="mu_faulty"):
        fault_fm(P, -1.0)
