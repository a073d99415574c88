"""The compiled per-row kernels give what the numpy passes they replace give (inkdiag_core._kernels)."""

import numpy as np
import pytest

from inkdiag_core import _kernels, gate, screening


def _adversarial(dtype, m=64, seed=0):
    """Rows a sensor or a transfer can produce, each kind several times, in random order."""
    rng = np.random.default_rng(seed)
    t = np.arange(m)
    rows = []
    for k in range(40):
        a = rng.uniform(0.1, 2.0)
        r = a * np.exp(-t / 20) * np.sin(0.6 * t + rng.uniform(0, 6)) + 0.01 * rng.standard_normal(m)
        kind = k % 20
        if kind == 1:
            r[rng.integers(m)] = np.nan
        elif kind == 2:
            r[rng.integers(m)] = -np.nan  # the sign bit set: maps below -Inf
        elif kind == 3:
            r[rng.integers(m)] = np.inf
        elif kind == 4:
            r[rng.integers(m)] = -np.inf
        elif kind == 5:
            r[rng.integers(m)] = 1e30 if dtype == np.float64 else np.finfo(np.float32).max
        elif kind == 6:
            r[:] = 0.25  # flat
        elif kind == 7:
            r = np.clip(r * 3, -0.8, 0.8)  # clipped at both rails
        elif kind == 8:
            top = r.max()
            r[10:14] = top + 1.0  # a plateau one sample short of the run (clip_run 5): not clipped
        elif kind == 9:
            r[20:25] = r.min() - 1.0  # exactly clip_run at the minimum
        elif kind == 10:
            r[:] = 0.0
            r[3:9] = -0.0  # -0.0 == 0.0: one value
            r[30] = 0.5
        elif kind == 11:
            r = np.round(r * 20) / 20  # coarse ADC codes: repeated values, short plateaus
        elif kind == 12:
            r[::7] = r.max()  # many samples at the max, no run
        elif kind == 13:
            r = -np.abs(r) - 3.0  # all negative
        elif kind == 14:
            r[5] = 3.0  # a sample beyond the range check (max_abs_v 2.5)
        rows.append(r)
    x = np.array(rows, dtype=dtype)
    return x[rng.permutation(len(x))]


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("clip_run", [2, 3, 5])
@pytest.mark.parametrize("max_abs_v", [None, 2.5])
def test_screen_codes_equal_the_numpy_passes(dtype, clip_run, max_abs_v):
    x = _adversarial(dtype)
    want = screening._screen_codes_numpy(x, 1e-6, max_abs_v, clip_run)
    got = screening._screen_codes(x, 1e-6, max_abs_v, clip_run)
    np.testing.assert_array_equal(got, want)
    assert set(want.tolist()) >= ({0, 1, 3, 4} | ({2} if max_abs_v else set())), "every code occurs"
    # a strided view (every other row and sample) is read in place, with the same codes
    v = x[::2, ::2]
    np.testing.assert_array_equal(screening._screen_codes(v, 1e-6, max_abs_v, clip_run),
                                  screening._screen_codes_numpy(v, 1e-6, max_abs_v, clip_run))


def test_screen_traces_takes_the_kernel_for_floats_and_numpy_for_adc_counts(monkeypatch):
    numpy_calls = []

    def numpy_path(x, *args):
        numpy_calls.append(x.dtype)
        return screening_numpy(x, *args)

    screening_numpy = screening._screen_codes_numpy
    monkeypatch.setattr(screening, "_screen_codes_numpy", numpy_path)
    x = _adversarial(np.float32)
    valid, reasons = screening.screen_traces(x, max_abs_v=2.5)
    assert numpy_calls == [], "float rows take the kernel"
    assert reasons.tolist() == [screening._REASONS[c] for c in screening_numpy(x, 1e-6, 2.5, 5)]
    assert (valid == (reasons == "")).all()
    counts = np.tile(np.array([0, 900, 2047, 2047, 2047, 2047, 2047, 10, -2048], np.int16), (3, 1))
    counts[1] = 7  # flat
    counts[2, 2:] = np.arange(7)  # valid
    _, why = screening.screen_traces(counts, flat_tol=0.5)
    assert numpy_calls == [np.int16], "ADC counts take the numpy passes"
    assert why.tolist() == ["clipped", "flat", ""]


def test_row_sums_are_the_float64_sums_and_propagate_non_finite_samples():
    rng = np.random.default_rng(1)
    for dtype in (np.float32, np.float64):
        x = rng.standard_normal((50, 300)).astype(dtype) + 0.3
        ref = rng.standard_normal((80, 300)).astype(np.float32)  # the gate's table: float32, more rows than x
        pos = rng.permutation(80)[:50]  # each row's own reference, out of order
        x1, xx, xr = _kernels.row_sums(x, ref, pos)
        X, R = x.astype(np.float64), ref[pos].astype(np.float64)
        np.testing.assert_allclose(x1, X.sum(axis=1), rtol=1e-12)
        np.testing.assert_allclose(xx, (X * X).sum(axis=1), rtol=1e-12)
        np.testing.assert_allclose(xr, (X * R).sum(axis=1), rtol=1e-10, atol=1e-10)
        x[3, 4], x[7, 0] = np.nan, np.inf
        x1, xx, xr = _kernels.row_sums(x, ref, pos)
        assert np.isnan(x1[3]) and np.isnan(xx[3]) and np.isinf(xx[7]) and np.isfinite(np.delete(xx, [3, 7])).all()
    with pytest.raises(ValueError, match="int64 positions"):
        _kernels.row_sums(np.zeros((2, 3), np.float32), np.zeros((2, 4), np.float32), np.zeros(2, np.int64))
    with pytest.raises(ValueError, match="int64 positions"):
        _kernels.row_sums(np.zeros((2, 3), np.float32), np.zeros((2, 3), np.float32), np.zeros(3, np.int64))
    with pytest.raises(ValueError, match=r"positions must be in \[0, 2\)"):
        _kernels.row_sums(np.zeros((2, 3), np.float32), np.zeros((2, 3), np.float32), np.array([0, 2]))
    # the labeller's call: -1 is a row without a reference (NaN sums), anything below is an error
    x = np.ones((2, 3), np.float32)
    _, x1, xx, xr = _kernels.screen_and_row_sums(x, None, None, None, np.ones((2, 3), np.float32), np.array([-1, 1]))
    assert np.isnan([x1[0], xx[0], xr[0]]).all() and (x1[1], xx[1], xr[1]) == (3.0, 3.0, 3.0)
    with pytest.raises(ValueError, match=r"positions must be in \[-1, 2\)"):
        _kernels.screen_and_row_sums(x, None, None, None, np.ones((2, 3), np.float32), np.array([-2, 0]))


def test_gate_clears_the_same_rows_with_the_kernel_as_with_numpy_passes(monkeypatch):
    from inkdiag_core import BaselineRecorder, FaultClass, HealthyGate, simulate_nozzles

    rec = BaselineRecorder(n_frames=4)
    for f in range(4):
        rec.add(0, simulate_nozzles(["healthy_nozzle"] * 300, seed=5, frame_seed=[5, f]).traces)
    classes = np.array([c.value for c in FaultClass], dtype=object)[np.arange(300) % len(FaultClass)]
    frame = simulate_nozzles(classes, seed=5, frame_seed=[5, 99]).traces.astype(np.float32)
    g = HealthyGate(rec.baselines())
    got = g.screen(frame, 0)
    monkeypatch.setattr(gate, "_row_sums", gate._row_sums_numpy)
    want = g.screen(frame, 0)
    assert got.cleared.any() and not got.cleared.all()
    np.testing.assert_array_equal(got.cleared, want.cleared)
    np.testing.assert_array_equal(got.classes, want.classes)
    np.testing.assert_allclose(got.gain, want.gain, rtol=1e-5, atol=1e-5)  # numpy: float32 accumulation
    np.testing.assert_allclose(got.residual_fraction, want.residual_fraction, rtol=1e-3, atol=1e-6)


def test_after_warm_up_a_decoded_frame_and_a_batch_need_no_new_kernel_build():
    """In a fresh process (what a node does): warm_up, then screen, gate and fit the KPIs of a read-only
    frame decoded from a message and of a writable batch, float32 and float64, label them with a detector
    of both branches (its compiled tail), and walk a forest; no kernel gains a signature."""
    import subprocess
    import sys
    import textwrap

    code = textwrap.dedent("""
        import numpy as np
        from inkdiag_core import (BaselineRecorder, HealthyGate, _kernels, extract_kpis, screen_traces,
                                  simulate_nozzles)
        from msg_defs import decode_traces, encode_traces
        rec = BaselineRecorder(n_frames=2)
        for f in range(2):
            rec.add(0, simulate_nozzles(["healthy_nozzle"] * 8, seed=1, frame_seed=[1, f]).traces)
        gate = HealthyGate(rec.baselines())
        _kernels.warm_up()
        from inkdiag_core.openset import unexplained_fraction
        kernels = (_kernels._screen_sums, _kernels._fit_windows, _kernels._forest_sums, _kernels._kpis_of_spectra,
                   _kernels._unexplained, _kernels._gate_codes, _kernels._detector_tail, _kernels._screen_gate_rows)
        from inkdiag_core import FrameLabeller
        from inkdiag_core import FaultDetector
        y = np.array(["ok_signal", "blocked"] * 8)
        t = simulate_nozzles(["healthy_nozzle"] * 16, seed=2).traces
        det = FaultDetector(n_estimators=3, unknown_rate=0.5).fit(t, y, baseline_kpis=extract_kpis(t, 10e6))
        before = [len(k.signatures) for k in kernels]
        x = simulate_nozzles(["healthy_nozzle"] * 8, seed=1, frame_seed=[1, 9]).traces.astype(np.float32)
        frame = decode_traces(encode_traces(x, first_nozzle=0, frame_id=1, stamp=0.0)).traces
        assert not frame.flags.writeable
        for rows in (frame, np.concatenate([frame, frame]), x.astype(np.float64)):
            screen_traces(rows)
            gate.screen(rows[:8], 0)
            pos = gate.positions(np.arange(8))
            gate.codes(*_kernels.screen_frames_and_row_sums([rows[:8]], 1e-6, 10.0, 5, gate.references, pos)[1:], pos)
            unexplained_fraction(rows, extract_kpis(rows, 10e6), 10e6)
            base = extract_kpis(rows, 10e6)
            base[::2] = np.nan  # both branches
            det.label(rows, baseline_kpis=base)
            labeller = FrameLabeller(det, rec.baselines(), sample_rate_hz=10e6, n_samples=512, max_abs_v=10.0)
            labeller.label([rows[:8], rows[:8]], [0, 100])  # the gate's nozzles, then none with a reference
            FrameLabeller(det, max_abs_v=10.0).label([rows[:8]], [0])  # no gate
            labeller.label([rows[:8]], [0], nozzles=[np.arange(8)[::-1]])  # each row's own id
        from sklearn.ensemble import RandomForestClassifier
        from inkdiag_core.fdi import forest_predict_proba
        rf = RandomForestClassifier(n_estimators=3, random_state=0).fit(extract_kpis(x, 10e6), [0, 1] * 4)
        forest_predict_proba(rf, extract_kpis(frame, 10e6))
        assert [len(k.signatures) for k in kernels] == before, ([k.signatures for k in kernels], before)
        print("ok")
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr[-3000:]


def test_the_compiled_window_fit_is_numpys_within_float64_rounding():
    """Every class (noisy), float32 and float64, short traces (3 and 2 window bins), noise-free sinusoids."""
    from inkdiag_core import FaultClass, simulate, spectral_fit
    from inkdiag_core.kpis import _peak_spectrum, _fit_window_inputs

    sim = simulate({c: 40 for c in FaultClass}, seed=7)
    for y in (sim.traces, sim.traces.astype(np.float32), sim.traces[:, :7], sim.traces[:, :5],
              np.exp(-0.01 * np.arange(512)) * np.cos(np.outer(np.linspace(0.1, 2.5, 30), np.arange(512)) + 0.3)):
        spec, m_peak, peak_power, _ = _peak_spectrum(np.ascontiguousarray(y))
        n_samples = y.shape[1]
        Yw, start, _ = _fit_window_inputs(spec, m_peak, peak_power, n_samples)
        want = spectral_fit.fit_windows(Yw, start, m_peak, n_samples)
        got = _kernels.fit_windows(Yw, start, m_peak, n_samples)
        for g, w, name in zip(got, want, ("omega", "sigma", "C")):
            np.testing.assert_allclose(g, w, rtol=1e-8, atol=1e-12 * np.abs(w).max(), err_msg=f"{name}, {y.shape}")
    assert all(a.shape == (0,) for a in _kernels.fit_windows(np.empty((0, 16), complex), [], [], 512))
    # a read-only window and a scalar first bin, as the numpy fit takes them
    Yw.flags.writeable = False
    np.testing.assert_allclose(_kernels.fit_windows(Yw[:3], 5, m_peak[:3], n_samples)[0],
                               spectral_fit.fit_windows(Yw[:3], 5, m_peak[:3], n_samples)[0], rtol=1e-8)


def test_the_compiled_kpis_are_numpys_within_float64_rounding(monkeypatch):
    """extract_kpis with the compiled spectrum steps and with their numpy form: every class, float32 and
    float64, odd and very short traces, flat rows, amplitudes that take the rescaled path, one row."""
    from inkdiag_core import FaultClass, extract_kpis, kpis, simulate

    sim = simulate({c: 30 for c in FaultClass}, seed=8)
    t = np.arange(512)
    ring = np.exp(-0.01 * t) * np.cos(0.7 * t)
    cases = [sim.traces, sim.traces.astype(np.float64), sim.traces[:, :511], sim.traces[:, :7], sim.traces[:, :5],
             np.vstack([np.full((2, 512), 0.3), ring, np.zeros((1, 512))]),  # flat, a clean ring, all zero
             (ring * np.array([[1e-14], [1e20], [1.0]])).astype(np.float32),  # underflowing / overflowing |Y|**2
             ring[None] * 1e200, sim.traces[:1]]
    got = [extract_kpis(y, 10e6) for y in cases]
    monkeypatch.setattr(kpis, "_fit_spectra", kpis._fit_spectra_numpy)
    for y, g in zip(cases, got):
        want = extract_kpis(y, 10e6)
        np.testing.assert_array_equal(np.isfinite(g), np.isfinite(want))
        for j in range(want.shape[1]):
            # dc: a difference of bin 0 and the mode's share of it, within rounding of the amplitude
            scale = np.abs(want[:, [j, 3] if j == 0 else j]).max()
            np.testing.assert_allclose(g[:, j], want[:, j], rtol=1e-9, atol=1e-12 * scale,
                                       err_msg=f"{y.dtype} {y.shape}, KPI {j}")


def test_a_batch_of_frames_is_screened_and_summed_as_each_frame_alone():
    """screen_frames_and_row_sums (the labeller's per-batch call) against screen_and_row_sums frame by frame:
    the same codes and bit-identical sums, float32 and float64 frames, an empty frame, rows without a reference;
    bad positions or widths refused for the batch."""
    ref = _adversarial(np.float32, seed=3)[:10]
    frames = [_adversarial(np.float32, seed=1)[:17], np.zeros((0, 64), np.float32), _adversarial(np.float64, seed=2)]
    n = sum(len(a) for a in frames)
    pos = np.arange(n, dtype=np.int64) % 11 - 1  # -1 .. 9
    got = _kernels.screen_frames_and_row_sums(frames, 1e-6, 2.5, 5, ref, pos)
    want, i = [], 0
    for a in frames:
        want.append(_kernels.screen_and_row_sums(a, 1e-6, 2.5, 5, ref, pos[i:i + len(a)]))
        i += len(a)
    for g, w in zip(got, zip(*want)):
        np.testing.assert_array_equal(g, np.concatenate(w))
    with pytest.raises(ValueError, match="positions"):
        _kernels.screen_frames_and_row_sums(frames, 1e-6, 2.5, 5, ref, pos + 2)
    with pytest.raises(ValueError, match="one width"):
        _kernels.screen_frames_and_row_sums([frames[0], frames[2][:, :32]], 1e-6, 2.5, 5, ref, pos[:17 + 40])


def test_gate_codes_refuses_positions_outside_its_table_and_mismatched_shapes():
    x = np.ones(3)
    rr = np.ones(2)
    with pytest.raises(ValueError, match=r"positions must be in \[-1, 2\)"):
        _kernels.gate_codes(x, x, x, np.array([0, 1, 2]), rr, 4, 0.5, (0.9, 1.1), (0.7, 0.8))
    with pytest.raises(ValueError, match="one shape"):
        _kernels.gate_codes(x, x[:2], x, np.array([0, 1, -1]), rr, 4, 0.5, (0.9, 1.1), (0.7, 0.8))
    assert _kernels.gate_codes(x, x, x, np.array([0, 1, -1]), rr, 4, 0.5, (0.9, 1.1), (0.7, 0.8)).shape == (3,)


def _gated_frames(dtype):
    """Frames of a recorded head (every class, screening's invalid kinds) and the gate of its references."""
    from inkdiag_core import BaselineRecorder, FaultClass, HealthyGate, simulate_nozzles

    rec = BaselineRecorder(n_frames=4)
    for k in range(4):
        rec.add(0, simulate_nozzles(["healthy_nozzle"] * 90, seed=5, frame_seed=k).traces)
    g = HealthyGate(rec.baselines(), max_residual_fraction=0.005)  # leaves some healthy rows of 4-frame references
    classes = np.array(["healthy_nozzle", "ok_signal"] * 45, dtype=object)
    values = [c.value for c in FaultClass]
    classes[::6] = [values[i % len(values)] for i in range(15)]
    x = simulate_nozzles(classes, seed=5, frame_seed=11).traces.astype(dtype)
    x[4, 9], x[13], x[22, 40:50], x[31, 2] = np.nan, 0.0, x[22].max(), 99.0  # non_finite, flat, clipped, out_of_range
    return g, x


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_screen_gate_frames_is_screening_then_the_gate(dtype):
    """screen_gate_frames (the labeller's first stage) against screen_frames_and_row_sums then gate_codes on the
    valid rows: the same codes; the rows left listed with their nozzle ids and handed back in order (copies
    of the few, a frame all of whose rows are left as itself); explicit ids; no gate; bad input refused."""
    g, x = _gated_frames(dtype)
    cuts = [0, 25, 25, 60, 90]
    frames = [x[a:b] for a, b in zip(cuts, cuts[1:])]
    frames.append(x[[12, 18, 42]])  # empty channels and a blocked nozzle: every row left, the frame whole
    firsts = [0, 25, 25, 60, 12]
    ids = np.concatenate([np.arange(f, f + len(a)) for f, a in zip(firsts[:4], frames[:4])] + [np.array([12, 18, 42])])
    pos = g.positions(ids)
    code, x1, xx, xr = _kernels.screen_frames_and_row_sums(frames, 1e-6, 10.0, 5, g.references, pos)
    want = code.copy()
    gate_code = g.codes(x1, xx, xr, np.where(code == 0, pos, -1))
    want[gate_code > 0] = gate.CLEARED_HEALTHY - 1 + gate_code[gate_code > 0]
    rows = np.concatenate(frames)
    for nozzles in (None, [ids[a:b] for a, b in zip([0, 25, 25, 60, 90], [25, 25, 60, 90, 93])]):
        positions = [g.range_positions(f, len(a)) for f, a in zip(firsts, frames)]
        positions[-1] = g.positions(ids[-3:])
        firsts_ = list(firsts)
        if nozzles is None:  # the last frame's ids are not consecutive: given as a frame of its own ids below
            got = _kernels.screen_gate_frames(frames[:-1], 1e-6, 10.0, 5, positions[:-1], g.verdict_params, firsts_[:-1])
            got_all = _kernels.screen_gate_frames(frames, 1e-6, 10.0, 5, positions, g.verdict_params, firsts_,
                                                  [np.empty(0, np.int64)] * 5)  # empty ids: consecutive from firsts
            np.testing.assert_array_equal(got_all[0], want)
            code_, at, nz, parts = got
            np.testing.assert_array_equal(code_, want[:90])
        else:
            code_, at, nz, parts = _kernels.screen_gate_frames(frames, 1e-6, 10.0, 5, positions, g.verdict_params,
                                                               firsts_, nozzles)
            np.testing.assert_array_equal(code_, want)
            assert parts[-1] is frames[-1]  # left whole: not copied
        np.testing.assert_array_equal(at, np.flatnonzero(code_ == 0))
        np.testing.assert_array_equal(nz, ids[at])
        np.testing.assert_array_equal(np.concatenate(parts), rows[at])
        assert all(p.dtype == dtype for p in parts)
    assert (want == gate.CLEARED_HEALTHY).sum() > 20 and (want == gate.CLEARED_OK).sum() > 20
    assert set(want[[4, 13, 22, 31]]) == {1, 3, 4, 2} and (want == 0).sum() > 15
    # no gate: every valid row left, nothing copied when all of a frame's rows are valid
    code_, at, nz, parts = _kernels.screen_gate_frames(frames[3:4], 1e-6, 10.0, 5, None, None, [60])
    np.testing.assert_array_equal(code_, want[60:90].clip(max=4) * (want[60:90] < 5))
    assert parts[0] is frames[3] and (nz == np.arange(60, 90)).all()
    with pytest.raises(ValueError, match="one float dtype"):
        _kernels.screen_gate_frames([frames[0], frames[2].astype(np.float16)], 1e-6, 10.0, 5, None, None, [0, 25])
    with pytest.raises(ValueError, match=r"positions must be in \[-1"):
        bad = positions[0].copy()
        bad[3] = len(g.references)
        _kernels.screen_gate_frames(frames[:1], 1e-6, 10.0, 5, [bad], g.verdict_params, firsts[:1])
    with pytest.raises(ValueError, match="positions and nozzle ids"):
        _kernels.screen_gate_frames(frames[:1], 1e-6, 10.0, 5, [positions[0][:3]], g.verdict_params, [0])
    with pytest.raises(ValueError, match="positions and nozzle ids"):  # ids of another dtype
        _kernels.screen_gate_frames(frames[:1], 1e-6, 10.0, 5, positions[:1], g.verdict_params, [0],
                                    [ids[:25].astype(float)])
    with pytest.raises(ValueError, match=r"r.r \(n_ref,\)"):
        ref, rr, *rest = g.verdict_params
        _kernels.screen_gate_frames(frames[:1], 1e-6, 10.0, 5, positions[:1], (ref, rr[:-1], *rest), [0])
