"""inkdiag_core.gate: HealthyGate clears healthy rows against their nozzle's reference and never a fault row."""

import dataclasses
import json

import numpy as np
import pytest

from inkdiag_core import (BaselineRecorder, FaultClass, HealthyGate, NozzleBaselines, healthy_twin_frames, simulate,
                          simulate_heldout, simulate_nozzles)
from inkdiag_core.baselines import BaselineFileError
from inkdiag_core.gate import quantize_references

HEAD, N = 23, 240


@pytest.fixture(scope="module")
def recorded():
    """A head's baselines with references, from 4 healthy frames (each its own temperature and noise)."""
    rec = BaselineRecorder(n_frames=4)
    for k in range(4):
        rec.add(0, simulate_nozzles(["healthy_nozzle"] * N, seed=HEAD, frame_seed=k).traces)
    return rec.baselines()


def _twin_gate(n, seed):
    _, frames = healthy_twin_frames(n, seed=seed, n_frames=8, noise_std_v=simulate({"healthy_nozzle": 1}).noise_std_v)
    ref = np.median(frames, axis=1)
    return HealthyGate(NozzleBaselines(np.arange(n), np.zeros((n, 7)), 10e6, 512, 8, reference=ref))


def test_recorder_records_each_nozzles_median_trace(recorded):
    assert recorded.has_reference and recorded.reference.shape == (N, 512)
    assert recorded.reference.dtype == np.float32
    frames = np.stack([simulate_nozzles(["healthy_nozzle"] * N, seed=HEAD, frame_seed=k).traces for k in range(4)],
                      axis=1)
    np.testing.assert_allclose(recorded.reference, np.median(frames, axis=1), atol=1e-6)
    assert not BaselineRecorder(n_frames=2, reference=False).baselines().has_reference


def test_healthy_rows_of_later_frames_are_mostly_cleared_with_their_class(recorded):
    gate = HealthyGate(recorded)
    classes = ["healthy_nozzle", "ok_signal"] * (N // 2)
    got = gate.screen(simulate_nozzles(classes, seed=HEAD, frame_seed=99).traces, 0)
    assert got.cleared.mean() >= 0.9
    c = got.cleared
    assert (got.classes[c] == np.array(classes, dtype=object)[c]).all()
    assert (got.classes[~c] == "").all()


@pytest.mark.parametrize("cls", [c for c in FaultClass if c.value not in ("healthy_nozzle", "ok_signal")])
def test_fault_rows_are_not_cleared(cls):
    sev = {FaultClass.SLIGHTLY_DRIED: np.full(300, 2.4)} if cls is FaultClass.SLIGHTLY_DRIED else None
    sim = simulate({cls: 300}, seed=4, severity=sev)
    assert not _twin_gate(300, 4).screen(sim.traces, 0).cleared.any()


@pytest.mark.parametrize("cond", ["poor_contact", "crosstalk", "foreign_body", "truncated_pulse"])
def test_mild_heldout_rows_are_not_cleared(cond):
    h = simulate_heldout(cond, 300, seed=6, severity=(0.0, 0.2))
    assert not _twin_gate(300, 6).screen(h.traces, 0).cleared.any()


def test_no_reference_clears_nothing(recorded):
    frame = simulate_nozzles(["healthy_nozzle"] * N, seed=HEAD, frame_seed=50).traces
    bare = dataclasses.replace(recorded, reference=None)
    assert not HealthyGate(bare).active
    assert not HealthyGate(bare).screen(frame, 0).cleared.any()
    gate = HealthyGate(recorded)
    got = gate.screen(frame, 10_000)  # nozzles without a baseline
    assert not got.cleared.any() and np.isnan(got.gain).all()
    ids = np.arange(N)
    ids[::2] += 10_000  # every other row's nozzle unknown: only the others can be cleared
    got = gate.screen(frame, ids)
    assert not got.cleared[::2].any() and got.cleared[1::2].mean() > 0.9
    # a gathered (non-contiguous) lookup gives the contiguous view's numbers
    perm = np.random.default_rng(0).permutation(N)
    np.testing.assert_allclose(gate.screen(frame[perm], perm).gain, gate.screen(frame, 0).gain[perm], rtol=1e-5)


def test_bad_rows_and_bad_input(recorded):
    gate = HealthyGate(recorded)
    frame = simulate_nozzles(["healthy_nozzle"] * N, seed=HEAD, frame_seed=51).traces.copy()
    before = gate.screen(frame, 0).cleared
    assert before[1] and before[2] and before.mean() > 0.9
    frame[1, 3] = np.nan
    frame[2] = 0.25  # constant
    got = gate.screen(frame, 0)
    assert not got.cleared[1] and not got.cleared[2]
    np.testing.assert_array_equal(np.delete(got.cleared, [1, 2]), np.delete(before, [1, 2]))
    with pytest.raises(ValueError, match="shape"):
        gate.screen(frame[:, :100], 0)
    with pytest.raises(ValueError, match="nozzle_ids"):
        gate.screen(frame, np.arange(3))
    with pytest.raises(ValueError, match="max_residual_fraction"):
        HealthyGate(recorded, max_residual_fraction=0)
    with pytest.raises(ValueError, match="overlap"):
        HealthyGate(recorded, ok_gain=(0.7, 0.95))


def test_references_round_trip_and_are_checked(recorded, tmp_path):
    p = recorded.save(tmp_path / "b.npz")
    back = NozzleBaselines.load(p)
    np.testing.assert_array_equal(back.reference, recorded.reference)
    with np.load(p) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["reference"] = arrays["reference"].copy()
    arrays["reference"][0, 0] += 1e-3
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(BaselineFileError, match="sha256"):
        NozzleBaselines.load(tmp_path / "bad.npz")
    del arrays["reference"]
    np.savez(tmp_path / "gone.npz", **arrays)
    with pytest.raises(BaselineFileError, match="reference"):
        NozzleBaselines.load(tmp_path / "gone.npz")
    assert json.loads(str(arrays["meta"]))["format_version"] == 5
    with pytest.raises(ValueError, match="reference"):
        NozzleBaselines(recorded.nozzle_ids, recorded.kpis, 10e6, 512, 4, reference=np.zeros((N, 100)))


def test_float32_rows_get_the_float64_decisions(recorded):
    classes = ["healthy_nozzle", "ok_signal", "slightly_dried", "healthy_nozzle"] * (N // 4)
    x = simulate_nozzles(classes, seed=HEAD, frame_seed=77).traces
    x32 = (x + 0.05).astype(np.float32)  # with a sensor offset
    gate = HealthyGate(recorded)
    a, b = gate.screen(x32, 0), gate.screen(x32.astype(np.float64), 0)
    np.testing.assert_array_equal(a.cleared, b.cleared)
    np.testing.assert_allclose(a.residual_fraction, b.residual_fraction, rtol=1e-3, atol=1e-6)
    np.testing.assert_allclose(a.gain, b.gain, rtol=1e-5)


def test_version_3_files_load_without_references_and_gate_nothing(recorded, tmp_path):
    from inkdiag_core.baselines.store import _content_sha256

    p = dataclasses.replace(recorded, reference=None).save(tmp_path / "v4.npz")
    with np.load(p) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(str(arrays["meta"]))
    old = {k: v for k, v in meta.items() if k not in ("sha256", "has_reference", "fm_method")}
    old["format_version"] = 3
    old["sha256"] = _content_sha256(recorded.nozzle_ids, recorded.kpis, {k: v for k, v in old.items() if k != "sha256"})
    arrays["meta"] = np.array(json.dumps(old, sort_keys=True))
    np.savez(tmp_path / "v3.npz", **arrays)
    b = NozzleBaselines.load(tmp_path / "v3.npz")
    assert not b.has_reference and not HealthyGate(b).active
    np.testing.assert_array_equal(b.kpis, recorded.kpis)


def test_each_row_meets_its_own_nozzles_reference_whatever_the_id_order(recorded):
    """Ids whose ends span a contiguous range but that repeat or go out of order (a recording's
    rows, overlapping frames) are gathered: a row is never fitted to another nozzle's reference."""
    gate = HealthyGate(recorded)
    x = simulate_nozzles(["healthy_nozzle"] * N, seed=HEAD, frame_seed=98).traces
    ids = np.array([0, 2, 1, 3])
    got = gate.screen(x[ids], ids)  # each row with its own id, out of order
    assert got.cleared.all()
    wrong = gate.screen(x[[0, 1, 2]], np.array([0, 0, 2]))  # row 1 is nozzle 1's trace, claims nozzle 0
    assert wrong.cleared.tolist() == [True, False, True]
    swapped = gate.screen(x[[0, 1, 2, 3]], ids)  # rows 1 and 2 claim each other's nozzle
    assert swapped.cleared.tolist() == [True, False, False, True]


def test_compiled_codes_are_decides_verdicts_on_every_kind_of_row(recorded):
    """HealthyGate.codes (the labeller's compiled loop) against decide (numpy): the same verdict on every row,
    real rows of every class and the edges: rows at each band's and the residual bound's limits, a constant
    row (var 0), NaN and Inf sums, a negative var, rows without a reference."""
    from inkdiag_core._kernels import row_sums
    from inkdiag_core.gate import GATE_CLASSES

    gate = HealthyGate(recorded)
    classes = np.array(list(FaultClass), dtype=object)[np.arange(N) % 12]
    x = simulate_nozzles(classes, seed=HEAD, frame_seed=5).traces
    pos = gate.positions(np.arange(N))
    pos[::17] = -1
    x1, xx, xr = row_sums(x, gate.references, np.where(pos >= 0, pos, 0))
    rng = np.random.default_rng(0)
    k = 60  # hand-made sums at the limits: gains at and around each band edge, residual fraction at the bound
    p = rng.integers(0, len(gate.references), k)
    rr = gate._rr[p]
    edges = np.array([*gate.jetting_gain, *gate.ok_gain, 1.0, 0.8, 0.5, 1.5])
    g = np.repeat(edges, k // len(edges) + 1)[:k] * (1 + rng.choice([-1e-15, 0.0, 1e-15], k))
    f = rng.choice([0.0, gate.max_residual_fraction, 0.5, -0.1, 1.2], k)  # the residual fraction aimed at
    hx1 = rng.normal(size=k)
    hxr = g * rr
    var = g * hxr / (1.0 - f)  # f = (var - g xr) / var: at the bound give or take a rounding; 1.2: var < 0
    hxx = var + hx1 * hx1 / gate.n_samples
    odd = np.array([[0.0, 0.0, 0.0], [np.nan, 1.0, 1.0], [1.0, np.inf, 1.0], [1.0, 1.0, -np.inf], [1.0, -5.0, 0.1]])
    X1 = np.concatenate([x1, hx1, odd[:, 0]])
    XX = np.concatenate([xx, hxx, odd[:, 1]])
    XR = np.concatenate([xr, hxr, odd[:, 2]])
    P = np.concatenate([pos, p, np.zeros(len(odd), np.int64)])
    want = gate.decide(X1, XX, XR, P)
    got = gate.codes(X1, XX, XR, P)
    np.testing.assert_array_equal(got > 0, want.cleared)
    np.testing.assert_array_equal(GATE_CLASSES[got], want.classes)
    assert 0 < (got[:N] > 0).sum() < N and (got[N:] == 1).any() and (got[N:] == 2).any()


def test_positions_by_table_are_the_searched_ones(recorded):
    """HealthyGate.positions looks ids up in a table by id: the same rows as searching the baselines' ids
    (-1 for a nozzle without a baseline, without a usable reference, or an id beyond the table)."""
    ids = recorded.nozzle_ids[::2] * 3  # gaps between the ids
    ref = recorded.reference[::2].copy()
    ref[5] = np.nan  # no usable reference
    b = NozzleBaselines(ids, recorded.kpis[::2], recorded.sample_rate_hz, recorded.n_samples, recorded.n_frames,
                        reference=ref)
    gate = HealthyGate(b)
    assert gate._table is not None
    q = np.concatenate([np.arange(-3, ids[-1] + 5), np.random.default_rng(0).integers(0, 10**6, 50)])
    has, pos = b.reference_rows(q)
    usable = np.isfinite(ref).all(axis=1)
    want = np.where(has & usable[pos], pos, -1)
    np.testing.assert_array_equal(gate.positions(q), want)
    inside = q[(q >= 0) & (q <= ids[-1])]
    np.testing.assert_array_equal(gate.positions(inside), want[(q >= 0) & (q <= ids[-1])])
    assert (gate.positions([ids[5]]) == -1).all() and (gate.positions([ids[6]]) == 6).all()


def test_range_positions_are_the_positions_of_the_range(recorded):
    """HealthyGate.range_positions(first, n) (the labeller's consecutive ids, a slice of the table) is
    positions(arange(first, first + n)): inside the table, across and beyond its ends, with the table and
    without one (ids too sparse for it), and writing to it does not touch the gate."""
    sparse = NozzleBaselines(recorded.nozzle_ids * 1000, recorded.kpis, recorded.sample_rate_hz, recorded.n_samples,
                             recorded.n_frames, reference=recorded.reference)
    for b in (recorded, sparse):
        gate = HealthyGate(b)
        assert (gate._table is None) == (b is sparse)
        last = int(b.nozzle_ids[-1])
        for first, n in ((0, 10), (5, 200), (last - 3, 10), (-4, 8), (last + 1, 5), (3, 0), (0, last + 1)):
            got = gate.range_positions(first, n)
            np.testing.assert_array_equal(got, gate.positions(np.arange(first, first + n)))
            assert got.dtype == np.int64 and got.shape == (n,)
        got = gate.range_positions(0, 5)
        got[:] = -1
        assert (gate.range_positions(0, 5) >= 0).all() or b is sparse
    assert HealthyGate(dataclasses.replace(recorded, reference=None)).range_positions(0, 4).tolist() == [-1] * 4


def test_quantized_references_are_within_half_a_step_of_the_rows():
    """quantize_references: int16 within 2**14, a power-of-two scale per row, each value within 2**-14 of its
    row's peak and float32-exact; rows of any magnitude, a row of zeros."""
    rng = np.random.default_rng(3)
    ref = rng.standard_normal((6, 512)) * np.array([1e-7, 1e-3, 1.0, 7.5, 3e3, 0.0])[:, None]
    ref[2, 5] = 2.0 ** 3  # a peak that is a power of two: the largest |q|
    q, scale = quantize_references(ref.astype(np.float32))
    assert q.dtype == np.int16 and scale.dtype == np.float64 and np.abs(q).max() <= 2 ** 14
    assert (np.frexp(scale)[0] == 0.5).all()  # powers of two
    back = q * scale[:, None]
    peak = np.abs(ref.astype(np.float32)).max(axis=1, keepdims=True)
    assert (np.abs(back - ref.astype(np.float32)) <= 2.0 ** -14 * peak).all()
    assert np.abs(q[:5]).max(axis=1).min() >= 2 ** 13  # every row uses its range
    np.testing.assert_array_equal(back.astype(np.float32).astype(np.float64), back)
    assert not q[5].any()


def test_the_gate_fits_rows_to_its_quantized_references(recorded):
    """The gate's references are int16 with a scale per row (half the bytes each trace's sums read), re-centred;
    its sums are the float sums against them, and those references are the recorded ones to within 2**-13 of each
    peak."""
    from inkdiag_core._kernels import row_sums

    gate = HealthyGate(recorded)
    q, rr, *_, scale, mean = gate.verdict_params
    assert q.dtype == np.int16 and scale.shape == mean.shape == (len(recorded),)
    ref = gate.references
    centred = recorded.reference - recorded.reference.mean(axis=1, keepdims=True)
    assert (np.abs(ref - centred) <= 2.0 ** -13 * np.abs(centred).max(axis=1, keepdims=True) + 1e-7).all()
    assert np.abs(ref.astype(np.float64).sum(axis=1)).max() < 1e-4  # re-centred (float32 rounding aside)
    np.testing.assert_allclose(rr, (ref.astype(np.float64) ** 2).sum(axis=1), rtol=1e-6)
    x = simulate_nozzles(["healthy_nozzle"] * N, seed=HEAD, frame_seed=9).traces.astype(np.float32)
    pos = gate.positions(np.arange(N))
    want = row_sums(x, ref, pos)
    got = row_sums(x, q, pos, scale, mean)
    for a, b in zip(got, want):
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-9)
    with pytest.raises(ValueError, match="need their ref_scale"):
        row_sums(x, q, pos)
    with pytest.raises(ValueError, match=r"ref_scale must be float64 of shape"):
        row_sums(x, q, pos, scale[:-1])
    with pytest.raises(ValueError, match=r"ref_mean must be float64 of shape"):
        row_sums(x, q, pos, scale, mean[:-1])
    with pytest.raises(ValueError, match="a ref_mean goes with a ref_scale"):
        row_sums(x, ref, pos, None, mean)
    with pytest.raises(ValueError, match="float32, float64 or int16"):
        row_sums(x, q.astype(np.int32), pos, scale)


@pytest.mark.parametrize("offset", [0.5, -1.0, 3.0])
def test_an_offset_changes_no_gain_and_no_residual_fraction(recorded, offset):
    """x and x + c have the same gain and residual fraction against a reference that sums to 0 (helper-143:
    references rounded to int16 and not re-centred leaked c into x.r, and cleared a row just above the bound once
    offset), in HealthyGate.screen and in the labeller's kernel."""
    from inkdiag_core._kernels import screen_gate_frames

    gate = HealthyGate(recorded)
    classes = np.array([c.value for c in FaultClass], dtype=object)[np.arange(N) % len(FaultClass)]
    x = simulate_nozzles(classes, seed=HEAD, frame_seed=5).traces.astype(np.float32)
    x[0] = gate.references[0] + 0.09 * np.sin(np.arange(x.shape[1]) * 0.37).astype(np.float32)  # reference + more
    plain, moved = gate.screen(x, 0), gate.screen(x + np.float32(offset), 0)
    np.testing.assert_allclose(moved.gain, plain.gain, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(moved.residual_fraction, plain.residual_fraction, rtol=1e-4, atol=1e-7)
    np.testing.assert_array_equal(moved.cleared, plain.cleared)
    codes = [screen_gate_frames([a], 1e-6, 10.0, 5, [gate.range_positions(0, N)], gate.verdict_params, [0])[0]
             for a in (x, x + np.float32(offset))]
    np.testing.assert_array_equal(codes[1], codes[0])
    assert plain.cleared.sum() > 10 and (~plain.cleared).sum() > 10


def test_quantizing_refuses_what_it_cannot_hold_and_the_gate_leaves_such_rows_out(recorded):
    with pytest.raises(ValueError, match="NaN or Inf"):
        quantize_references(np.array([[1.0, np.nan, 0.5]]))
    for peak in (1e-36, 3e38):
        with pytest.raises(ValueError, match="float32-exact steps"):
            quantize_references(np.array([[peak, -peak / 2, 0.0]]))
    ref = recorded.reference.copy()
    ref[3] *= 1e-35  # a row too faint to quantize: that nozzle has no reference, the others are gated as before
    gate = HealthyGate(dataclasses.replace(recorded, reference=ref))
    pos = gate.positions(recorded.nozzle_ids)
    assert pos[3] == -1 and (np.delete(pos, 3) >= 0).all()
