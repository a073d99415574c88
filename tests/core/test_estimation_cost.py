"""Fixed cost per call of "vp"/"vp_cal" (the fe node's small batches): work that depends
only on the model, the sample rate and the trace length is not redone per call, a basis's
normal matrix is factored once for all its right-hand sides, and the results stay the bits
of tests/core/data/fm_reference.json (tests/core/test_estimation_split.py)."""

import numpy as np
import pytest

from inkdiag_core import InkChannelModel, estimate_fm_batch
from inkdiag_core.estimation import vp
from inkdiag_core.fe_datasets import synthetic_set

FS = 10e6


@pytest.fixture(scope="module")
def traces():
    ds = synthetic_set(InkChannelModel(), kind="ct", x0="random", n_levels=5, snr_db=40,
                       n_samples=200, seed=3)
    return ds.y


def _counting(monkeypatch, name):
    calls = []
    real = getattr(np.linalg, name)

    def counted(*a, **k):
        calls.append(1)
        return real(*a, **k)

    monkeypatch.setattr(np.linalg, name, counted)
    return calls


def test_stacked_right_hand_sides_give_the_bits_of_separate_solves(traces):
    sc_model = InkChannelModel()
    from inkdiag_core.estimation.base import model_matrices, scaled
    A, C, B_f, _ = model_matrices(sc_model)
    sc = scaled(A, C, B_f, FS)
    Ys = traces[:3] / np.sqrt(np.mean(traces[:3] ** 2, axis=1))[:, None]
    B = vp._vp_basis(sc, np.array([-0.3, -0.1, 0.02]), Ys.shape[1])[0]
    J = np.stack([Ys[::-1], Ys * 0.5 + 1.0])  # (2, n, N): two more right-hand sides
    fac = vp._vp_factor(B)
    th, res, R = vp._vp_solve(B, J, fac)
    for j in range(2):
        th1, res1, R1 = vp._vp_solve(B, J[j])
        assert np.array_equal(th[j], th1) and np.array_equal(res[j], res1)
        assert np.array_equal(R[j], R1)


def test_vp_cal_decomposes_each_matrix_once(monkeypatch, traces):
    model = InkChannelModel()
    estimate_fm_batch(traces[:2], model, FS, method="vp_cal")  # caches warm
    eig, eigvals = _counting(monkeypatch, "eig"), _counting(monkeypatch, "eigvals")
    bases = []
    real_basis = vp._vp_basis
    monkeypatch.setattr(vp, "_vp_basis", lambda *a, **k: bases.append(1) or real_basis(*a, **k))
    estimate_fm_batch(traces[:2], model, FS, method="vp_cal")
    # one eig per Gauss-Newton basis, one for the pair refit; the healthy omega is cached
    assert len(eig) == len(bases) + 1
    assert len(eigvals) == 0


def test_solves_per_call_bounded(monkeypatch, traces):
    model = InkChannelModel()
    estimate_fm_batch(traces[:2], model, FS, method="vp_cal")
    solve, inv = _counting(monkeypatch, "solve"), _counting(monkeypatch, "inv")
    bases = []
    real_basis = vp._vp_basis
    monkeypatch.setattr(vp, "_vp_basis", lambda *a, **k: bases.append(1) or real_basis(*a, **k))
    estimate_fm_batch(traces[:2], model, FS, method="vp_cal")
    # one inverse per basis's normal matrix and one per eigenvector matrix (vp: per basis;
    # pair refit: its modes once and 1 to 4 fits); every right-hand side is a product
    assert len(solve) == 0
    assert 2 * len(bases) + 2 <= len(inv) <= 2 * len(bases) + 5
