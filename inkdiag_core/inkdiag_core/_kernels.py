"""Compiled per-row kernels of the labeller's hot path and of the KPIs (numba, cached on disk).

Every row of every frame is screened (:func:`inkdiag_core.screen_traces`: its extremes
and how many samples sit at them) and, where its nozzle has a healthy reference, fitted
to it (:class:`inkdiag_core.HealthyGate`: three row sums). In numpy these are seven
passes over the samples, each a separate reduction; here they are one kernel, three
short loops per row back to back (extremes, samples at them, sums), which LLVM vectorises.
``scripts/bench fdi`` measures both against the numpy passes in the same run (issue 17: a
compiled kernel goes in only where it wins >= 2x on its stage).

- :func:`screen_codes`: each row's screening verdict (valid, non-finite, out of range,
  flat, clipped), exact: the same as numpy's ``max``/``min`` passes and the comparisons
  with them. Float comparisons with NaN semantics do not vectorise without assuming no
  NaN, so the extremes are taken over the samples' bit patterns mapped to integers of
  the same order (``b ^ ((b >> 31) & 0x7fffffff)`` for float32): exact for every finite
  and infinite value, and a NaN maps beyond +-Inf, so a row holding one comes out
  non-finite, as numpy's NaN-propagating max and min say.
- :func:`row_sums`: ``sum(x)``, ``sum(x * x)`` and ``sum(x * r)`` per row, accumulated
  in float64 whatever the input precision, each row's ``r`` read in place from the
  reference table. The kernel is compiled with ``fastmath={"reassoc", "contract"}`` for
  these sums: no flag assumes finite values, so a NaN or Inf sample still propagates; the
  screening is integer and comparison work plus one ``max - min <= flat_tol`` per row,
  which neither flag changes.
- :func:`screen_and_row_sums`: both for the same rows from one kernel (both functions above
  are it), each row's loops back to back, so a row comes from memory once and its later
  loops read it from cache (:meth:`inkdiag_core.HealthyGate.screen`; :func:`screen_frames_and_row_sums`
  of a batch of frames, not concatenated, is the reference the tests hold the labeller's kernel to).
- :func:`gate_codes`: the healthy gate's verdict per row from those sums (its gain, residual
  fraction and bands), one loop for what :meth:`inkdiag_core.HealthyGate.decide` does in about a
  dozen numpy passes: the same verdicts.
- :func:`screen_gate_frames`: the labeller's first stage, per frame one call of both kernels above
  (the same compiled screening, sums and verdicts) that also lists the rows left for the detector
  with their nozzle ids and copies those few out: one code per row (left, invalid and why, cleared
  and as what) instead of about thirty numpy calls per batch around :func:`screen_and_row_sums`.
- :func:`fit_windows`: the KPIs' damped-sinusoid fit on each trace's spectral window
  (:func:`inkdiag_core.spectral_fit.fit_windows`, its numpy reference, has the method),
  one trace at a time: in numpy about a hundred small array operations per call, a fixed
  cost that dominates on the few rows the gate leaves to the detector. Same arithmetic,
  sums in another order: within ~1e-11 relative of the numpy fit on the simulator's traces
  (12,000 rows, 5 seeds); where the fit is ill-conditioned (a step, a window of noise, a
  2-sample trace) both versions move as much under a 1e-15 change of their input. Every
  KPI (``extract_kpis``: training and labelling alike) comes from this fit.
- :func:`kpis_of_spectra`: the rest of the KPIs from each trace's rfft (peak bin, Parseval's
  AC energy, the scaled window, :func:`fit_windows`'s fit, dc, phase, the flat and fallback
  rows) per row, instead of about sixty numpy calls per chunk: within float64 rounding of
  :func:`inkdiag_core.kpis._fit_spectra_numpy` (the peak found in the spectrum's precision,
  as numpy finds it; tests compare both).
- :func:`unexplained`: the open-set layer's unexplained fraction per row, in float64 by blocks of
  32 samples (its numpy form sums in float32, within 0.3 % of the direct formula; this is
  within 1e-11 of it on 512-sample traces). A block is sliced out of the row so that its loop vectorises.
- :func:`p_values`: the open-set layer's conformal p-values, a binary search per row and class
  in one call instead of a ``searchsorted`` call per class: the same counts, exactly.
- :func:`forest_proba`: a Random Forest's class probabilities, every tree walked per row in
  one call (:func:`inkdiag_core.fdi.forest_predict_proba` flattens the forest once). In
  numpy each tree is a call of its own (``tree_.predict``, a few us each, 50 per forest) and
  an ``(n, k)`` sum: the forest's fixed cost on a few rows (:func:`detector_tail` walks the
  trees the same way for the default detector). The same
  comparisons (the float32 feature against the float64 threshold) and the same sums in
  the same order per row: bit-identical to scikit-learn's ``predict_proba``.
- :func:`mahalanobis_scores`: the open-set layer's float32 squared Mahalanobis distances, one
  row at a time (a BLAS matrix-vector product, then each class's sum of squares in index order),
  so a row's scores are the same bits whatever rows are scored with it (numpy's matrix product
  of a batch summed one row in another order than of that row alone, gemv against gemm, and
  differently again in a batch of another size).
- :func:`detector_tail`: one branch of :meth:`inkdiag_core.FaultDetector.label` from the KPIs on
  (features, forest, decision, open-set features, :func:`mahalanobis_scores`' arithmetic, p-values,
  unknown score) in one call instead of about eighty numpy calls: ``scripts/bench fdi`` times it
  against that loop, and the tests check the same labels, confidences and unknown scores.

The kernels compile on first use and are cached next to this file (numba's
``cache=True``; a read-only install falls back to numba's user-wide cache directory).
:func:`warm_up` compiles or loads them for the rows a labeller sees (C-contiguous float32
and float64, writable and read-only): the labeller calls it when it is built or
unpickled (the labelling process's child), ``scripts/_bootstrap.sh`` at install, so no
node stalls on its first frame (a first compile takes a few seconds, a cache load ~0.2 s).
Importing this module imports numba (~0.35 s): the core imports it only when a kernel is
first needed.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from llvmlite import ir
from numba.core import types
from numba.core.extending import intrinsic

from .gate import CLEARED_HEALTHY

__all__ = ["detector_tail", "fit_windows", "forest_proba", "gate_codes", "kpis_of_spectra", "mahalanobis_scores",
           "p_values", "row_sums",
           "screen_and_row_sums", "screen_codes", "screen_frames_and_row_sums", "screen_gate_frames", "unexplained",
           "warm_up"]

_SUMS_FASTMATH = {"reassoc", "contract"}  # reorder and fuse the sums only: no finite-math assumption


@intrinsic
def _float_of_bits(typingctx, bits, like):
    """The float of ``like``'s type whose bit pattern is the low 32 or 64 bits of the integer ``bits``
    (numba widens int32 arithmetic to int64; the low bits are the pattern): a bit cast."""
    if not isinstance(bits, types.Integer) or like not in (types.float32, types.float64):
        return None

    def codegen(context, builder, sig, args):
        width = 32 if like == types.float32 else 64
        v = args[0]
        if bits.bitwidth > width:
            v = builder.trunc(v, ir.IntType(width))
        elif bits.bitwidth < width:
            v = builder.sext(v, ir.IntType(width))
        return builder.bitcast(v, context.get_value_type(like))

    return like(bits, like), codegen


@numba.njit(cache=True, nogil=True, fastmath=_SUMS_FASTMATH)
def _screen_sums(x, bits, screen, flat_tol, max_abs_v, clip_run, ref, scale, mean, pos, code, s1, s2, sr):
    """Per row: its screening code (if ``screen``) and, where ``pos[i] >= 0``, its three sums against
    ``ref[pos[i]]`` (NaN elsewhere); where ``scale`` is not empty (int16 references,
    :func:`inkdiag_core.gate.quantize_references`), against ``ref[p] * scale[p] - mean[p]`` (``p = pos[i]``:
    ``sum(x) * mean[p]`` off ``scale[p] * sum(x * ref[p])``). Each row's loops run back to back, so the row
    is read from memory once. ``bits`` is ``x`` viewed as signed integers of its width."""
    n, m = x.shape
    top = np.iinfo(bits.dtype).max  # all bits but the sign: flips a negative float's order
    sign = 8 * bits.itemsize - 1
    for i in range(n):
        if screen:
            # the extremes over the bit patterns mapped to integers of the floats' order: vectorises
            # (a float max with NaN semantics does not), exact, a NaN maps beyond +-Inf
            if bits.itemsize == 4:
                # float32: kept in int32 lanes. Numba widens int32 arithmetic to int64, which halves the
                # lanes per vector: this loop took 2.2x as long, the whole kernel 1.3-1.4x (2026-11-26)
                h = np.int32(bits[i, 0])
                h = np.int32(h ^ ((h >> np.int32(31)) & np.int32(0x7FFFFFFF)))
                lw = h
                for k in range(m):
                    q = bits[i, k]
                    q = np.int32(q ^ ((q >> np.int32(31)) & np.int32(0x7FFFFFFF)))
                    h = max(h, q)
                    lw = min(lw, q)
            else:
                h = bits[i, 0] ^ ((bits[i, 0] >> sign) & top)
                lw = h
                for k in range(1, m):
                    q = bits[i, k]
                    q = q ^ ((q >> sign) & top)
                    h = max(h, q)
                    lw = min(lw, q)
            a = _float_of_bits(h ^ ((h >> sign) & top), x[i, 0])
            b = _float_of_bits(lw ^ ((lw >> sign) & top), x[i, 0])
            if not (np.isfinite(a) and np.isfinite(b)):
                code[i] = 1  # non_finite
            elif np.float64(a) > max_abs_v or np.float64(b) < -max_abs_v:
                code[i] = 2  # out_of_range
            elif np.float64(a) - np.float64(b) <= flat_tol:
                code[i] = 3  # flat
            else:
                code[i] = 0
                ch = np.int32(0)  # int32 counts: twice the lanes of numba's default int64 (m < 2**31)
                cl = np.int32(0)
                for k in range(m):
                    v = x[i, k]
                    ch = np.int32(ch + np.int32(v == a))
                    cl = np.int32(cl + np.int32(v == b))
                if ch >= clip_run or cl >= clip_run:  # few rows: only then can such a run exist
                    run_h = 0
                    run_l = 0
                    for k in range(m):  # clip_run consecutive samples at an extreme (-0.0 == 0.0)
                        v = x[i, k]
                        run_h = run_h + 1 if v == a else 0
                        run_l = run_l + 1 if v == b else 0
                        if run_h >= clip_run or run_l >= clip_run:
                            code[i] = 4  # clipped
                            break
        p = pos[i]
        if p < 0:
            s1[i] = np.nan
            s2[i] = np.nan
            sr[i] = np.nan
            continue
        c1 = 0.0
        c2 = 0.0
        c3 = 0.0
        for k in range(m):
            v = np.float64(x[i, k])
            c1 += v
            c2 += v * v
            c3 += v * np.float64(ref[p, k])
        s1[i] = c1
        s2[i] = c2
        sr[i] = c3 * scale[p] - c1 * mean[p] if scale.shape[0] else c3


@numba.njit(cache=True, nogil=True)
def _gate_codes(x1, xx, xr, pos, rr, n_samples, max_f, jet_lo, jet_hi, ok_lo, ok_hi, out):
    for i in range(x1.shape[0]):
        c = 0
        p = pos[i]
        if p >= 0:
            g = xr[i] / rr[p]
            var = xx[i] - x1[i] * x1[i] / n_samples
            if var > 0:
                f = (var - g * xr[i]) / var
                if f < 0.0:  # clipped to [0, 1]; a NaN stays NaN and clears nothing
                    f = 0.0
                elif f > 1.0:
                    f = 1.0
                if f <= max_f:
                    if g >= jet_lo and g <= jet_hi:
                        c = 1
                    elif g >= ok_lo and g <= ok_hi:
                        c = 2
        out[i] = c



@numba.njit(cache=True, nogil=True)
def _screen_gate_rows(x, bits, flat_tol, max_abs_v, clip_run, ref, scale, mean, pos, rr, n_samples, max_f, jet_lo,
                      jet_hi, ok_lo, ok_hi, first, ids, row0, code, at, nozzle, left, k):
    """One frame of :func:`screen_gate_frames`: each row screened, then gated where it is valid and has a
    reference (``pos`` empty: none has), its code written at ``code[row0 + i]``; the rows left (code 0)
    listed from ``at[k]`` on with their nozzle ids (``ids[i]``, or ``first + i`` where ``ids`` is empty) and,
    unless every row of the frame is left, copied to ``left[k]`` on. The sums and verdicts are
    :func:`_screen_sums`' and :func:`_gate_codes`' own (called here). Returns the next ``k``, whether every row
    was left (then none is copied: the frame is its own rows), and -1 or the first position outside
    ``[-1, len(ref))``."""
    n, m = x.shape
    p = pos if pos.shape[0] else np.full(n, -1, np.int64)  # empty: no row has a reference
    for i in range(n):
        if p[i] < -1 or p[i] >= ref.shape[0]:
            return k, False, p[i]
    frame_code = code[row0:row0 + n]
    s1, s2, sr = np.empty(n), np.empty(n), np.empty(n)
    _screen_sums(x, bits, True, flat_tol, max_abs_v, clip_run, ref, scale, mean, p, frame_code, s1, s2, sr)
    gate = np.zeros(n, np.uint8)
    _gate_codes(s1, s2, sr, p, rr, n_samples, max_f, jet_lo, jet_hi, ok_lo, ok_hi, gate)
    k0 = k
    for i in range(n):
        if frame_code[i] == 0:
            if gate[i] != 0:
                frame_code[i] = CLEARED_HEALTHY - 1 + gate[i]  # the gate's 1, 2: CLEARED_HEALTHY, CLEARED_OK
            else:
                at[k] = row0 + i
                nozzle[k] = ids[i] if ids.shape[0] else first + i
                k += 1
    whole = k - k0 == n
    if not whole:
        for j in range(k0, k):
            r = at[j] - row0
            for s in range(m):
                left[j, s] = x[r, s]
    return k, whole, -1

@numba.njit(cache=True, nogil=True)
def _solve2(a11, a12, a22, b1, b2):
    """:func:`inkdiag_core.spectral_fit.solve2` of one system."""
    det = a11 * a22 - a12 * a12
    inv = 1.0 / det if det > 1e-14 * abs(a11 * a22) else 0.0
    return (a22 * b1 - a12 * b2) * inv, (a11 * b2 - a12 * b1) * inv


@numba.njit(cache=True, nogil=True)
def _clip(v, lo, hi):
    """``np.clip`` of one value (NaN stays NaN)."""
    if v < lo:
        return lo
    if v > hi:
        return hi
    return v


@numba.njit(cache=True, nogil=True)
def _fit_windows(Yw, start, m_peak, n_samples, w, M, n_iter, sigma_min, sigma_max, omega_out, sigma_out, c_out):
    """:func:`inkdiag_core.spectral_fit.fit_windows`, one row at a time (its docstring has the method)."""
    n, n_bins = Yw.shape
    bin_w = 2.0 * np.pi / n_samples
    omega_lo, omega_hi = 0.5 * bin_w, np.pi - 0.5 * bin_w
    V = np.empty((5, n_bins), dtype=np.complex128)
    H = np.empty((5, 5), dtype=np.complex128)
    t = np.empty(4, dtype=np.complex128)
    s = np.empty(3, dtype=np.complex128)
    m00, m01, m10, m11 = M[0, 0], M[0, 1], M[1, 0], M[1, 1]
    w_inv, w2 = w ** -1, w ** 2
    hv = np.empty(5, dtype=np.complex128)  # h(1,1), h(1,2), h(2,2), h(1,0), h(2,0)
    pairs = ((1, 1), (1, 2), (2, 2), (1, 0), (2, 0))
    for i in range(n):
        e_s = np.exp((-2j * np.pi / n_samples) * start[i])
        ok = False
        omega = 0.0
        sigma = 0.0
        if n_bins >= 3:  # frequency-domain Prony (prony_init)
            for p in range(4):
                t[p] = 0.0
            for p in range(3):
                s[p] = 0.0
            for j in range(n_bins):
                y = Yw[i, j]
                yy = y.real * y.real + y.imag * y.imag
                t[0] += w_inv[j] * y
                t[1] += y
                t[2] += w[j] * y
                t[3] += w2[j] * y
                s[0] += yy
                s[1] += w[j] * yy
                s[2] += w2[j] * yy
            for idx in range(5):
                pp_, qq_ = pairs[idx]
                k = qq_ - pp_
                raw = s[k] if k >= 0 else np.conj(s[-k])
                bp0, bp1 = np.conj(t[pp_ + 1]), np.conj(t[pp_])
                bq0, bq1 = t[qq_ + 1], t[qq_]
                hv[idx] = raw - (bp0 * (m00 * bq0 + m01 * bq1) + bp1 * (m10 * bq0 + m11 * bq1))
            a1, a2 = _solve2(hv[0].real, (e_s * hv[1]).real, hv[2].real,
                             -(np.conj(e_s) * hv[3]).real, -(np.conj(e_s) ** 2 * hv[4]).real)
            re_z = -0.5 * a1
            im2 = a2 - re_z * re_z
            ok = a2 > 0.0 and im2 > 0.0
            omega = np.arctan2(np.sqrt(im2 if ok else 1.0), re_z)
            sigma = -0.5 * np.log(a2 if ok else 1.0)
        iters = n_iter if n_bins >= 3 else 0
        if not ok:
            omega = bin_w * m_peak[i]
            sigma = bin_w
        omega = _clip(omega, omega_lo, omega_hi)
        sigma = _clip(sigma, sigma_min, sigma_max)
        for j in range(n_bins):
            V[2, j] = Yw[i, j]
        have_best = False
        b_omega = b_sigma = b_rss = 0.0
        b_c = 0j
        for it in range(iters + 1):
            lam = complex(-sigma, omega)
            z = np.exp(lam)
            zn = np.exp(n_samples * lam)
            last = it == iters
            kk = 3 if last else 5
            for row in range(2):
                zeta = (z if row == 0 else np.conj(z)) * e_s
                for j in range(n_bins):
                    q = 1.0 - zeta * w[j]  # |q| is O(1) here: 1 / q as conj(q) / |q|^2, no scaling needed
                    r = 1.0 / (q.real * q.real + q.imag * q.imag)
                    d = complex(q.real * r, -q.imag * r)
                    V[row, j] = d
                    if not last:
                        V[row + 3, j] = d * d
            for a in range(kk):  # Hermitian: the upper triangle, mirrored (conj(x) y = conj(conj(y) x) exactly)
                for b in range(a, kk):
                    acc = 0j
                    for j in range(n_bins):
                        acc += np.conj(V[a, j]) * V[b, j]
                    H[a, b] = acc
                    H[b, a] = np.conj(acc)
            h00, h11, h22 = H[0, 0].real, H[1, 1].real, H[2, 2].real
            h01, h02, h12 = H[0, 1], H[0, 2], H[1, 2]
            alpha = 1.0 - zn
            ca = np.conj(alpha)
            aa = alpha.real ** 2 + alpha.imag ** 2
            gg = aa * h00
            hh = aa * h11
            gh = ca * ca * h01
            gy = ca * h02
            hy = alpha * h12
            pp = 0.25 * (gg + hh + 2.0 * gh.real)
            qq = 0.25 * (gg + hh - 2.0 * gh.real)
            pq_ = 0.5 * gh.imag
            c1, c2 = _solve2(pp, pq_, qq, 0.5 * (gy + hy).real, 0.5 * (gy - hy).imag)
            C = complex(c1, c2)
            rss = h22 - (c1 * 0.5 * (gy + hy).real + c2 * 0.5 * (gy - hy).imag)
            if not have_best or rss < b_rss:
                have_best = True
                b_omega, b_sigma, b_c, b_rss = omega, sigma, C, rss
            if last:
                break
            h03, h04, h13, h14, h34 = H[0, 3], H[0, 4], H[1, 3], H[1, 4], H[3, 4]
            h32, h42 = H[3, 2], H[4, 2]
            h33, h44 = H[3, 3].real, H[4, 4].real
            gamma = n_samples * zn
            cC = np.conj(C)
            u1 = -0.5j * C * (alpha + gamma)
            u2 = 0.5j * C * alpha
            v1 = 0.5j * cC * (ca + np.conj(gamma))
            v2 = -0.5j * cC * ca
            cu1, cu2, cv1, cv2 = np.conj(u1), np.conj(u2), np.conj(v1), np.conj(v2)
            na = (u1.real ** 2 + u1.imag ** 2) * h00 + (u2.real ** 2 + u2.imag ** 2) * h33 \
                + 2.0 * (cu1 * u2 * h03).real
            nb = (v1.real ** 2 + v1.imag ** 2) * h11 + (v2.real ** 2 + v2.imag ** 2) * h44 \
                + 2.0 * (cv1 * v2 * h14).real
            nab = cu1 * (v1 * h01 + v2 * h04) + cu2 * (v1 * np.conj(h13) + v2 * h34)
            g_a = ca * (u1 * h00 + u2 * h03)
            h_a = alpha * (u1 * np.conj(h01) + u2 * h13)
            g_b = ca * (v1 * h01 + v2 * h04)
            h_b = alpha * (v1 * h11 + v2 * h14)
            a_r = cu1 * h02 + cu2 * h32 - 0.5 * (C * np.conj(g_a) + cC * np.conj(h_a))
            b_r = cv1 * h12 + cv2 * h42 - 0.5 * (C * np.conj(g_b) + cC * np.conj(h_b))
            gj, hj = g_a + g_b, h_a + h_b
            gw0, gw1 = 0.5 * (gj + hj).real, 0.5 * (gj - hj).imag
            gj, hj = 1j * (g_a - g_b), 1j * (h_a - h_b)
            gs0, gs1 = 0.5 * (gj + hj).real, 0.5 * (gj - hj).imag
            iw0, iw1 = _solve2(pp, pq_, qq, gw0, gw1)
            is0, is1 = _solve2(pp, pq_, qq, gs0, gs1)
            nww = na + nb + 2.0 * nab.real - (gw0 * iw0 + gw1 * iw1)
            nws = 2.0 * nab.imag - (gw0 * is0 + gw1 * is1)
            nss = na + nb - 2.0 * nab.real - (gs0 * is0 + gs1 * is1)
            d_omega, d_sigma = _solve2(nww, nws, nss, (a_r + b_r).real, (a_r - b_r).imag)
            d_omega = _clip(d_omega, -2 * bin_w, 2 * bin_w)
            d_sigma = _clip(d_sigma, -2 * bin_w - 0.5 * sigma, 2 * bin_w + sigma)
            if rss > b_rss:  # a step from a point worse than the best one restarts halfway from the best
                omega = 0.5 * (omega + b_omega)
                sigma = 0.5 * (sigma + b_sigma)
            else:
                omega = omega + d_omega
                sigma = sigma + d_sigma
            omega = _clip(omega, omega_lo, omega_hi)
            sigma = _clip(sigma, sigma_min, sigma_max)
        omega_out[i] = b_omega
        sigma_out[i] = b_sigma
        c_out[i] = b_c


@numba.njit(cache=True, nogil=True)
def _leaf(x, root, nodes, threshold):
    """The leaf the feature row ``x`` reaches in the tree at ``root``: left where ``x[feature] <= threshold``."""
    node = root
    left = nodes[node, 0]
    while left >= 0:
        if x[nodes[node, 2]] <= threshold[node]:
            node = left
        else:
            node = nodes[node, 1]
        left = nodes[node, 0]
    return node


@numba.njit(cache=True, nogil=True)
def _forest_sums(X, roots, nodes, threshold, value, out):
    n_classes = value.shape[1]
    for t in range(roots.shape[0]):  # tree by tree (its nodes stay in cache); each row's sum in tree order
        for i in range(X.shape[0]):
            node = _leaf(X[i], roots[t], nodes, threshold)
            for c in range(n_classes):
                out[i, c] += value[node, c]


@numba.njit(cache=True, nogil=True, fastmath=_SUMS_FASTMATH)
def _unexplained(x, kpis, fs, tiny, out):
    n, m = x.shape
    B = 32  # samples per block: k = B a + b
    pr, pi = np.empty(B), np.empty(B)  # z**b
    for i in range(n):
        ok = True
        for j in range(kpis.shape[1]):
            if not np.isfinite(kpis[i, j]):
                ok = False
        zeta = kpis[i, 2]
        if not ok or not (zeta >= 0.0 and zeta < 1.0):
            out[i] = np.nan
            continue
        dc = kpis[i, 0]
        w = 2.0 * np.pi * kpis[i, 1] / fs  # rad per sample
        decay = np.exp(-(zeta * w / np.sqrt(1.0 - zeta * zeta)))  # |z|
        zr, zi = decay * np.cos(w), decay * np.sin(w)  # z, the per-sample pole
        pr[0], pi[0] = 1.0, 0.0
        s1 = 1.0  # sum_b |z**b|**2
        s2r, s2i = 1.0, 0.0  # sum_b z**(2 b)
        for b in range(1, B):
            pr[b] = pr[b - 1] * zr - pi[b - 1] * zi
            pi[b] = pr[b - 1] * zi + pi[b - 1] * zr
            s1 += pr[b] * pr[b] + pi[b] * pi[b]
            s2r += pr[b] * pr[b] - pi[b] * pi[b]
            s2i += 2.0 * pr[b] * pi[b]
        zBr = pr[B - 1] * zr - pi[B - 1] * zi  # z**B
        zBi = pr[B - 1] * zi + pi[B - 1] * zr
        cr, ci = kpis[i, 3] * np.cos(kpis[i, 4]), kpis[i, 3] * np.sin(kpis[i, 4])  # C z**(B a)
        row = x[i]
        total = cross = model2 = 0.0
        for a0 in range(0, m - B + 1, B):  # whole blocks
            blk = row[a0:a0 + B]  # a slice: its loop vectorises (indexing row[a0 + b] does not)
            t = qr = qi = 0.0
            for b in range(B):  # sum (y - dc)**2 and sum (y - dc) z**b over the block
                v = blk[b] - dc
                t += v * v
                qr += v * pr[b]
                qi += v * pi[b]
            total += t
            cross += cr * qr - ci * qi  # Re(C z**(B a) sum_b (y - dc) z**b)
            # |model|**2 of the block: |c|**2 s1 / 2 + Re(c**2 s2) / 2, c = C z**(B a)
            model2 += 0.5 * (cr * cr + ci * ci) * s1 + 0.5 * ((cr * cr - ci * ci) * s2r - 2.0 * cr * ci * s2i)
            cr, ci = cr * zBr - ci * zBi, cr * zBi + ci * zBr
        for b in range(m - m % B, m) if m % B else range(0):  # the last, partial block
            v = row[b] - dc
            k = b % B
            mr = cr * pr[k] - ci * pi[k]
            total += v * v
            cross += v * mr
            model2 += mr * mr
        u = max(total - 2.0 * cross + model2, 0.0) / max(total, tiny)
        out[i] = u if np.isfinite(u) else np.nan


@numba.njit(cache=True, nogil=True)
def _power(y, out):
    """``|y|**2`` in ``y``'s precision, as numpy's ``y.real**2 + y.imag**2`` rounds it (no fused multiply-add)."""
    for m in range(y.shape[0]):
        out[m] = y[m].real * y[m].real + y[m].imag * y[m].imag


@numba.njit(cache=True, nogil=True, fastmath={"reassoc"})
def _sum64(p):
    """``sum(p)`` in float64, in the order the compiler vectorises."""
    total = 0.0
    for m in range(p.shape[0]):
        total += np.float64(p[m])
    return total


@numba.njit(cache=True, nogil=True)
def _kpis_of_spectra(spec, n_samples, fs, n_bins, w, M, n_iter, sigma_min, sigma_max, flat_rtol, out):
    """KPIs (n, 7) of traces from their rfft ``spec``: :func:`inkdiag_core.kpis._fit_chunk`'s steps per row."""
    n = spec.shape[0]
    half = n_samples // 2
    m_peak = np.empty(n, np.int64)
    start = np.empty(n, np.int64)
    peak_power = np.empty(n)
    ac_sumsq = np.empty(n)
    expo = np.empty(n, np.int64)
    Yw = np.empty((n, n_bins), np.complex128)
    power = np.empty(half, spec.real.dtype)
    for i in range(n):
        # power |Y[m]|**2 in the spectrum's precision (as numpy's ac.real**2 + ac.imag**2), m = 1 .. N/2;
        # the first largest is the peak; Parseval's sum in float64
        _power(spec[i, 1:half + 1], power)  # vectorised
        best = -1.0
        at = 1
        for m in range(half):
            if power[m] > best:
                best = power[m]
                at = m + 1
        m_peak[i] = at
        peak_power[i] = best
        sumsq = 2.0 * _sum64(power)
        if n_samples % 2 == 0:
            sumsq -= power[half - 1]
        ac_sumsq[i] = sumsq / n_samples
        # the window: n_bins bins around the peak inside 1 .. N/2, scaled by 2**-e near its peak
        st = min(max(at - n_bins // 2, 1), half - n_bins + 1)
        start[i] = st
        _, e = math.frexp(math.sqrt(peak_power[i]))
        expo[i] = e
        if -1000 < e < 1000:  # 2**-e a normal float64: multiplying by it is ldexp, exactly
            scale = math.ldexp(1.0, -e)
            for b in range(n_bins):
                v = spec[i, st + b]
                Yw[i, b] = complex(np.float64(v.real) * scale, np.float64(v.imag) * scale)
        else:
            for b in range(n_bins):
                v = spec[i, st + b]
                Yw[i, b] = complex(math.ldexp(np.float64(v.real), -e), math.ldexp(np.float64(v.imag), -e))
    omega = np.empty(n)
    sigma = np.empty(n)
    C = np.empty(n, np.complex128)
    _fit_windows(Yw, start, m_peak, n_samples, w, M, n_iter, sigma_min, sigma_max, omega, sigma, C)
    for i in range(n):
        c = complex(math.ldexp(C[i].real, expo[i]), math.ldexp(C[i].imag, expo[i]))
        om, sg = omega[i], sigma[i]
        lam = complex(-sg, om)
        g0 = (1.0 - np.exp(n_samples * lam)) / (1.0 - np.exp(lam))  # DC from bin 0: Y_0 = N dc + Re(C G_0)
        s0 = np.float64(spec[i, 0].real)
        mean = s0 / n_samples
        phase = np.arctan2(c.imag, c.real)
        if phase <= -np.pi:
            phase += 2.0 * np.pi
        nyq = 1.0 if (n_samples % 2 == 0 and m_peak[i] == half) else 2.0
        out[i, 0] = (s0 - (c * g0).real) / n_samples
        out[i, 1] = om * fs / (2.0 * np.pi)
        out[i, 2] = sg / np.hypot(om, sg)
        out[i, 3] = abs(c)
        out[i, 4] = phase
        out[i, 5] = ac_sumsq[i] / fs
        out[i, 6] = nyq * np.sqrt(peak_power[i]) / n_samples
        finite = True
        for j in range(7):
            if not np.isfinite(out[i, j]):
                finite = False
        if ac_sumsq[i] <= flat_rtol * (ac_sumsq[i] + n_samples * mean * mean):  # flat: its mean, nothing else
            out[i, 0] = mean
            for j in range(1, 7):
                out[i, j] = 0.0
        elif not finite:  # should not happen; if it does, the FFT peak rather than NaN
            out[i, 0] = mean
            out[i, 1] = m_peak[i] * fs / n_samples
            out[i, 2] = 0.0
            out[i, 3] = out[i, 6]
            out[i, 4] = 0.0


@numba.njit(cache=True, nogil=True)
def _p_values(S, cal, starts, modelled, out):
    n, k = S.shape
    for i in range(n):
        finite = True
        for c in range(k):
            if not np.isfinite(S[i, c]):
                finite = False
        for c in range(k):
            if not finite:
                out[i, c] = np.nan
            elif not modelled[c]:
                out[i, c] = 1.0
            else:
                out[i, c] = _p_value(cal, starts[c], starts[c + 1], S[i, c])


@numba.njit(cache=True, nogil=True)
def _p_value(cal, lo, hi, s):
    """``(1 + #{cal[lo:hi] >= s}) / (hi - lo + 1)``: the conformal p-value of score ``s`` against one
    class's sorted calibration scores."""
    n_ge = (hi - lo) - np.searchsorted(cal[lo:hi], s)  # scores >= this row's (side left)
    return (1.0 + n_ge) / (hi - lo + 1.0)


@numba.njit(cache=True, nogil=True)
def _floor(v, tiny):
    """``np.maximum(v, tiny)``: NaN stays NaN."""
    return tiny if v < tiny else v


@numba.njit(cache=True, nogil=True)
def _row_scores(z, w_all, mu_w, out):
    """Squared Mahalanobis distances of one standardized float32 row ``z`` (d,) to every class, in float32
    into ``out`` (k,): ``z [W_1 ... W_k]`` by one BLAS matrix-vector product (the row alone: the same bits
    whatever rows are scored with it and whichever kernel calls this), then per class
    ``sum_e2 ((z W_c)[e2] - (mu_c W_c)[e2])**2`` in index order."""
    d = z.shape[0]
    W = np.dot(z, w_all)
    for c in range(out.shape[0]):
        s = np.float32(0.0)
        for e2 in range(d):
            v = W[c * d + e2] - mu_w[c * d + e2]
            s += v * v
        out[c] = s


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _scores(Z, w_all, mu_w, out):
    for i in range(Z.shape[0]):
        _row_scores(Z[i], w_all, mu_w, out[i])


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _detector_tail(kpis, base, x, fs, tiny, eps, roots, nodes, threshold, value, healthy, fd_threshold,
                   has_layer, center, scale, w_all, mu_w, cal, starts, modelled, levels, rate, rate_bound,
                   log_min_amp, weak_q, ok, idx, conf, pf, uscore):
    n = kpis.shape[0]
    has_base = base.shape[0] == n and base.shape[1] == 7
    p = 13 if has_base else 7
    k = value.shape[1]
    d = center.shape[0]
    n_trees = roots.shape[0]
    feats = np.empty(p)
    xf = np.empty(p, np.float32)
    proba = np.empty(k)
    F = np.empty(d)
    z = np.empty(d, np.float32)  # standardized open-set features, float32 (ConformalOpenSet.scores)
    S = np.empty(k, np.float32)
    u = np.empty(n)
    if has_layer and n:
        _unexplained(x, kpis, fs, tiny, u)
    for i in range(n):
        # the branch's features (BaselineKpis._features_of / the KPIs alone), in float64
        for j in range(7):
            feats[j] = kpis[i, j]
        if has_base:
            feats[7] = kpis[i, 1] / (base[i, 1] + eps)
            feats[8] = kpis[i, 2] - base[i, 2]
            feats[9] = kpis[i, 2] / (base[i, 2] + eps)
            feats[10] = kpis[i, 3] / (base[i, 3] + eps)
            feats[11] = kpis[i, 5] / (base[i, 5] + eps)
            dphi = kpis[i, 4] - base[i, 4]
            feats[12] = math.atan2(math.sin(dphi), math.cos(dphi))  # np.angle(np.exp(1j * dphi))
        finite = True
        for j in range(p):
            xf[j] = np.float32(feats[j])
            if not np.isfinite(xf[j]):
                finite = False
        ok[i] = finite
        if not finite:  # not classified (finite_rows_proba)
            continue
        # the forest (_forest_sums: each row's sum in tree order, then the mean)
        for c in range(k):
            proba[c] = 0.0
        for t in range(n_trees):
            node = _leaf(xf, roots[t], nodes, threshold)
            for c in range(k):
                proba[c] += value[node, c]
        for c in range(k):
            proba[c] /= n_trees
        # P(faulty) and the class at the threshold (fdi.decide_classes)
        h = 0.0
        for c in range(k):
            if healthy[c]:
                h += proba[c]
        pf[i] = 1.0 - h
        faulty = pf[i] >= fd_threshold
        best_c = 0
        best = -1.0 if healthy[0] == faulty else proba[0]
        for c in range(1, k):
            v = -1.0 if healthy[c] == faulty else proba[c]
            if v > best:
                best, best_c = v, c
        idx[i] = best_c
        conf[i] = proba[best_c]
        uscore[i] = np.nan
        if not has_layer:
            continue
        # the open-set features (openset.openset_features, baseline_openset_features), standardized
        F[0] = math.log(_floor(feats[1], tiny))
        F[1] = math.log(_floor(feats[2], tiny))
        F[2] = math.log(_floor(feats[3], tiny))
        F[3] = math.log(_floor(feats[5], tiny))
        F[4] = math.log(_floor(feats[6], tiny))
        F[5] = math.cos(feats[4])
        F[6] = math.sin(feats[4])
        F[7] = math.log10(_floor(u[i], 1e-12))
        if has_base:
            F[8] = math.log(_floor(feats[7], tiny))
            F[9] = feats[8]
            F[10] = math.log(_floor(feats[10], tiny))
            F[11] = math.log(_floor(feats[11], tiny))
            F[12] = math.cos(feats[12])
        for e in range(d):
            z[e] = np.float32((F[e] - center[e]) / scale[e])
        # per class the squared Mahalanobis distance (ConformalOpenSet.scores), its p-value (_p_values)
        # and the row's unknown score 1 - max_c min(1, p_c rate / a_c) (ConformalOpenSet.unknown_score)
        _row_scores(z, w_all, mu_w, S)
        if F[2] < log_min_amp:  # a weak row (ConformalOpenSet._judged) of finite scores: against the chosen class's
            finite_s = True  # weak rows alone
            for c in range(k):
                if not np.isfinite(S[c]):
                    finite_s = False
            if finite_s:
                uscore[i] = 1.0 - weak_q[best_c]
                if 1.0 - uscore[i] <= rate_bound:
                    conf[i] = uscore[i]
                    pf[i] = 1.0
                    idx[i] = -1
                continue
        q_max = 0.0
        for c in range(k):
            s = S[c]
            if not np.isfinite(s):
                q_max = np.nan
                break
            pv = _p_value(cal, starts[c], starts[c + 1], s) if modelled[c] else 1.0
            q = min(1.0, pv * (rate / levels[c])) if levels[c] > 0 else 1.0
            if q > q_max:
                q_max = q
        uscore[i] = 1.0 - q_max
        if 1.0 - uscore[i] <= rate_bound:  # unknown (ConformalOpenSet.is_unknown)
            conf[i] = uscore[i]
            pf[i] = 1.0
            idx[i] = -1


def forest_proba(X, roots, nodes, threshold, value):
    """Mean over the trees of each row's leaf values: a flattened forest's ``predict_proba``.

    Parameters
    ----------
    X : ndarray of float32, shape (n, n_features)
        Finite feature rows (C-contiguous; another layout is copied).
    roots : ndarray of int64, shape (n_trees,)
        Each tree's root node.
    nodes : ndarray of int32, shape (n_nodes, 4)
        Per node: left child, right child, feature, 0 (one row of 16 bytes); the left child
        is -1 at a leaf. Go left where ``X[i, feature] <= threshold``.
    threshold : ndarray of float64, shape (n_nodes,)
    value : ndarray of float64, shape (n_nodes, n_classes)
        Each leaf's class probabilities.

    Returns
    -------
    ndarray of float64, shape (n, n_classes)
    """
    X = np.require(X, np.float32, ["C", "W"])  # the one signature warm_up compiles
    out = np.zeros((X.shape[0], value.shape[1]))
    if X.shape[0]:
        _forest_sums(X, roots, nodes, threshold, value, out)
    out /= roots.shape[0]
    return out


def mahalanobis_scores(Z, w_all, mu_w):
    """Squared Mahalanobis distances of standardized rows to every class, in float32, row by row.

    :meth:`inkdiag_core.openset.ConformalOpenSet.scores` (calibration and test rows alike) and
    :func:`detector_tail` both compute them one row at a time (a BLAS matrix-vector product, then
    each class's sum of squares in index order): a row's scores do not depend on the rows scored
    with it, nor on which of the two computes them.

    Parameters
    ----------
    Z : ndarray of float32, shape (n, d)
        Standardized feature rows.
    w_all : ndarray of float32, shape (d, k * d)
        The classes' whitening matrices side by side (``[W_1 ... W_k]``).
    mu_w : ndarray of float32, shape (k * d,)
        The classes' centres, whitened (``mu_c W_c``).

    Returns
    -------
    ndarray of float32, shape (n, k)
        ``sum_e ((z W_c)[e] - (mu_c W_c)[e])**2``; non-finite where the row is.
    """
    Z = np.require(Z, np.float32, ["C", "W"])
    w_all = np.require(w_all, np.float32, ["C", "W"])
    mu_w = np.require(mu_w, np.float32, ["C", "W"])
    d = w_all.shape[0]
    if Z.ndim != 2 or Z.shape[1] != d or w_all.ndim != 2 or d == 0 or w_all.shape[1] % d or mu_w.shape != (
            w_all.shape[1],):
        raise ValueError(f"mahalanobis_scores: rows (n, d), whitening (d, k * d) and centres (k * d,) are needed, "
                         f"got {Z.shape}, {w_all.shape} and {mu_w.shape}")
    out = np.empty((Z.shape[0], w_all.shape[1] // d), np.float32)
    if Z.shape[0]:
        _scores(Z, w_all, mu_w, out)
    return out


def detector_tail(kpis, base, x, sample_rate_hz, forest, healthy, fd_threshold, layer, *, eps):
    """One branch of :meth:`inkdiag_core.FaultDetector.label` from the KPIs on, one row at a time in one call.

    Per row: the branch's features (the KPIs, and with ``base`` the six relative to the nozzle's
    baseline, :class:`inkdiag_core.baselines.BaselineKpis`), the forest's class probabilities
    (:func:`forest_proba`), P(faulty) and the class at the threshold
    (:func:`inkdiag_core.fdi.decide_classes`), then with a layer its open-set features
    (:func:`inkdiag_core.openset.openset_features`, :func:`inkdiag_core.openset.baseline_openset_features`),
    their float32 Mahalanobis scores, p-values and unknown score
    (:meth:`inkdiag_core.openset.ConformalOpenSet.unknown_score`): in numpy about eighty calls
    (most of the detector's fixed cost on the few rows the gate leaves). The same arithmetic, the
    scores :func:`mahalanobis_scores`' own: the same labels, confidences and unknown scores.

    Parameters
    ----------
    kpis : ndarray of float64, shape (n, 7)
        The traces' KPIs (:func:`inkdiag_core.kpis.kpis_of_checked`).
    base : ndarray of float64, shape (n, 7) or None
        The baseline branch: each row's nozzle baseline KPIs; None: the plain branch (KPI_Y).
    x : ndarray of float32 or float64, shape (n, n_samples)
        The traces, V (the open-set layer's unexplained fraction).
    sample_rate_hz : float
    forest : tuple
        ``(roots, nodes, threshold, value)`` of :func:`inkdiag_core.fdi.flat_forest`.
    healthy : ndarray of bool, shape (n_classes,)
    fd_threshold : float
    layer : tuple or None
        :meth:`inkdiag_core.openset.ConformalOpenSet._tail_params` (the open-set features' floor, the log of
        the smallest amplitude its Mahalanobis scores judge and the weak rows' per-class ``q`` last); None: no
        open-set layer.
    eps : float
        The relative features' denominator offset (:data:`inkdiag_core.baselines.features.RELATIVE_EPS`).

    Returns
    -------
    ok : ndarray of bool, shape (n,)
        The row's features are finite in float32 (the others are not classified).
    idx : ndarray of int64, shape (n,)
        Class column; -1 where the open-set layer calls the row unknown.
    conf, pf, uscore : ndarray of float64, shape (n,)
        Confidence, P(faulty), unknown score (NaN without a layer or for non-finite open-set
        features), as :meth:`inkdiag_core.FaultDetector.label` reports them; meaningless where not ``ok``.
    """
    roots, nodes, threshold, value = forest
    n = kpis.shape[0]
    kpis = np.require(kpis, np.float64, ["C", "W"])
    base = np.empty((0, 7)) if base is None else np.require(base, np.float64, ["C", "W"])
    x = np.require(x, np.float32 if x.dtype == np.float32 else np.float64, ["C", "W"])  # the signatures warm_up compiles
    if kpis.shape != (n, 7) or base.shape not in ((0, 7), (n, 7)) or x.ndim != 2 or x.shape[0] != n:
        raise ValueError(f"detector_tail: KPIs (n, 7), baselines (n, 7) or none and traces (n, m) are needed, got "
                         f"{kpis.shape}, {base.shape} and {x.shape}")
    if layer is None:
        f32, f64 = np.zeros((1, 1), np.float32), np.zeros(1)
        layer = (f64, f64, f32, f32[0], f32[0], np.zeros(2, np.int64), np.zeros(1, bool), f64, 0.0, 0.0, 1e-30,
                 -np.inf, f64)
        has_layer = False
    else:
        has_layer = True
    center, scale, w_all, mu_w, cal, starts, modelled, levels, rate, rate_bound, tiny, log_min_amp, weak_q = layer
    ok, idx = np.empty(n, bool), np.empty(n, np.int64)
    conf, pf, uscore = np.empty(n), np.empty(n), np.full(n, np.nan)
    if n:
        _detector_tail(kpis, base, x, float(sample_rate_hz), float(tiny), float(eps), roots, nodes, threshold, value,
                       np.require(healthy, bool, ["C", "W"]), float(fd_threshold), has_layer, center, scale, w_all,
                       mu_w, cal, starts, modelled, levels, float(rate), float(rate_bound), float(log_min_amp), weak_q,
                       ok, idx, conf, pf, uscore)
    return ok, idx, conf, pf, uscore


def fit_windows(Yw, start, m_peak, n_samples):
    """:func:`inkdiag_core.spectral_fit.fit_windows` compiled, one row at a time: the same fit, the
    same returns (within float64 rounding: sums in another order; tests compare both).

    Parameters
    ----------
    Yw : ndarray of complex128, shape (n, K)
        Each trace's ``K`` window bins.
    start, m_peak : ndarray of int, shape (n,)
        First window bin and peak bin.
    n_samples : int

    Returns
    -------
    omega : ndarray, shape (n,)
        rad/sample.
    sigma : ndarray, shape (n,)
        1/sample.
    C : ndarray of complex128, shape (n,)
    """
    from .spectral_fit import N_ITER, SIGMA_MAX, SIGMA_MIN, window_projector

    # the one signature warm_up compiles: writable C-contiguous arrays (a copy only where they are not)
    Yw = np.require(Yw, np.complex128, ["C", "W"])
    n, n_bins = Yw.shape
    start = np.require(np.broadcast_to(np.asarray(start), (n,)), np.int64, ["C", "W"])
    m_peak = np.require(np.broadcast_to(np.asarray(m_peak), (n,)), np.int64, ["C", "W"])
    w, M, _, _ = window_projector(n_bins, n_samples)
    omega, sigma, C = np.empty(n), np.empty(n), np.empty(n, np.complex128)
    if n:
        _fit_windows(Yw, start, m_peak, int(n_samples), w, M, N_ITER, SIGMA_MIN, SIGMA_MAX, omega, sigma, C)
    return omega, sigma, C


def unexplained(x, kpis, sample_rate_hz, tiny):
    """:func:`inkdiag_core.openset.unexplained_fraction` compiled, one row at a time:
    ``sum((y - dc - model)**2) / sum((y - dc)**2)`` with the model ``Re(C z**k)``, in float64,
    by the numpy version's blocks of 32 samples: ``z**b`` (``b < 32``) once per row, then per
    block the sums of ``(y - dc)**2`` and ``(y - dc) z**b`` (vectorised) and ``|model|**2``
    in closed form.

    Parameters
    ----------
    x : ndarray of float32 or float64, shape (n, m)
        Traces, V (C-contiguous; another layout is copied).
    kpis : ndarray of float64, shape (n, 7)
        Their KPIs.
    sample_rate_hz : float
        Hz.
    tiny : float
        Floor of the denominator.

    Returns
    -------
    ndarray of float64, shape (n,)
        NaN where a row's KPIs are not finite, its damping ratio is outside [0, 1), or the
        fraction is not finite.
    """
    x = np.asarray(x)
    kpis = np.asarray(kpis)
    if x.ndim != 2 or kpis.ndim != 2 or kpis.shape[0] != x.shape[0] or kpis.shape[1] < 5:
        raise ValueError(f"unexplained: traces (n, m) and their KPIs (n, >= 5) are needed, got shapes {x.shape} "
                         f"and {kpis.shape}")
    x = np.require(x, np.float32 if x.dtype == np.float32 else np.float64, ["C"])
    kpis = np.require(kpis, np.float64, ["C", "W"])  # small: a copy costs less than a compile
    out = np.empty(x.shape[0])
    if x.shape[0]:
        _unexplained(x, kpis, float(sample_rate_hz), float(tiny), out)
    return out


def kpis_of_spectra(spec, n_samples, sample_rate_hz, flat_rtol, out):
    """The KPIs of traces from their spectra, compiled: :func:`inkdiag_core.kpis._fit_chunk`'s
    steps (peak bin, Parseval's AC energy, the scaled window, :func:`fit_windows`, dc, phase,
    the flat and fallback rows) one row at a time, instead of ~60 numpy calls per chunk.

    Parameters
    ----------
    spec : ndarray of complex64 or complex128, shape (n, n_samples // 2 + 1)
        ``scipy.fft.rfft`` of the traces (complex64 for float32 traces: the peak is found in that
        precision, as numpy's).
    n_samples : int
    sample_rate_hz : float
    flat_rtol : float
        A row whose AC energy is at most this fraction of its total is flat.
    out : ndarray of float64, shape (n, 7)
        Written.
    """
    from .spectral_fit import N_ITER, SIGMA_MAX, SIGMA_MIN, WINDOW_BINS, window_projector

    spec = np.require(spec, np.complex64 if spec.dtype == np.complex64 else np.complex128, ["C", "W"])
    if spec.ndim != 2 or spec.shape[1] != int(n_samples) // 2 + 1 or int(n_samples) < 2 or out.shape != (
            spec.shape[0], 7) or out.dtype != np.float64:
        raise ValueError(f"kpis_of_spectra: spectra (n, {int(n_samples) // 2 + 1}) of {int(n_samples)} >= 2 samples "
                         f"and a float64 out (n, 7) are needed, got {spec.shape} and {out.dtype} {out.shape}")
    n_bins = min(WINDOW_BINS, int(n_samples) // 2)
    w, M, _, _ = window_projector(n_bins, int(n_samples))
    if spec.shape[0]:
        _kpis_of_spectra(spec, int(n_samples), float(sample_rate_hz), n_bins, w, M, N_ITER, SIGMA_MIN, SIGMA_MAX,
                         float(flat_rtol), out)
    return out


def p_values(S, cal, starts, modelled):
    """Conformal p-values ``(1 + #{calibration scores of c >= score}) / (n_c + 1)`` per row and class:
    :meth:`inkdiag_core.openset.ConformalOpenSet.p_values`'s loop of one ``searchsorted`` per class, per row.

    Parameters
    ----------
    S : ndarray of float32, shape (n, k)
        Nonconformity scores.
    cal : ndarray of float32, shape (m,)
        Every class's sorted calibration scores, one after the other.
    starts : ndarray of int64, shape (k + 1,)
        Class ``c``'s scores are ``cal[starts[c]:starts[c + 1]]``.
    modelled : ndarray of bool, shape (k,)
        A class without a model has p-value 1.

    Returns
    -------
    ndarray of float64, shape (n, k)
        NaN on every column of a row with a non-finite score.
    """
    S, cal, starts, modelled = np.asarray(S), np.asarray(cal), np.asarray(starts), np.asarray(modelled)
    if (S.ndim != 2 or S.dtype != np.float32 or cal.ndim != 1 or cal.dtype != np.float32
            or starts.shape != (S.shape[1] + 1,) or starts.dtype.kind not in "iu"
            or modelled.shape != (S.shape[1],) or modelled.dtype != bool
            or (starts.size and (starts[0] != 0 or starts[-1] != cal.size or np.any(np.diff(starts) < 0)))):
        raise ValueError(f"p_values: float32 scores (n, k), float32 calibration scores (m,), starts (k + 1,) from 0 "
                         f"to m and a bool mask (k,) are needed, got {S.dtype} {S.shape}, {cal.dtype} {cal.shape}, "
                         f"{starts.shape} and {modelled.dtype} {modelled.shape}")
    S = np.require(S, np.float32, ["C", "W"])
    starts = np.require(starts, np.int64, ["C", "W"])
    cal = np.require(cal, np.float32, ["C", "W"])
    modelled = np.require(modelled, bool, ["C", "W"])
    out = np.empty(S.shape)
    if S.shape[0]:
        _p_values(S, cal, starts, modelled, out)
    return out


def screen_codes(x, flat_tol, max_abs_v, clip_run):
    """Each row's screening code: 0 valid, then the first that applies of 1 non-finite (a NaN or
    Inf sample), 2 out of range (a sample beyond ``+-max_abs_v``), 3 flat (``max - min <=
    flat_tol``), 4 clipped (``clip_run`` consecutive samples at the row's max or min).

    The same codes as :func:`inkdiag_core.screening._screen_codes_numpy`, from one pass over
    the samples for the extremes and one more for the samples at them (tests compare both).

    Parameters
    ----------
    x : ndarray of float32 or float64, shape (n, m), m >= 1
        Rows, V (any memory layout; C-contiguous is the one :func:`warm_up` compiles).
    flat_tol : float
        V.
    max_abs_v : float
        V; ``inf``: no range check.
    clip_run : int
        Samples, >= 2.

    Returns
    -------
    ndarray of uint8, shape (n,)
    """
    return screen_and_row_sums(x, flat_tol, max_abs_v, clip_run, None, None)[0]


def row_sums(x, ref, pos, ref_scale=None, ref_mean=None):
    """``sum(x)``, ``sum(x * x)`` and ``sum(x * r)`` of each row, in float64, ``r`` its row of ``ref``
    (with ``ref_scale``: ``ref * ref_scale - ref_mean``, that row's).

    Each row's reference is read where it lies in ``ref`` (row ``pos[i]``): no gathered copy
    of the references (a batch that wraps around the head, or any out-of-order ids, would
    otherwise copy every row's reference first).

    Parameters
    ----------
    x : ndarray of float32 or float64, shape (n, m)
    ref : ndarray of float32, float64 or int16, shape (n_ref, m)
        The references, one per row of the table (int16: :func:`inkdiag_core.gate.quantize_references`).
    pos : ndarray of int64, shape (n,)
        Each row's reference row, in ``[0, n_ref)``.
    ref_scale, ref_mean : ndarray of float64, shape (n_ref,), optional
        Each reference row's scale and mean: its samples are ``ref * ref_scale - ref_mean`` (the gate's
        quantized references re-centred); ``ref_scale`` is needed with int16 references, ``ref_mean``
        None: 0.

    Returns
    -------
    x1, xx, xr : ndarray of float64, shape (n,)
        Summed in float64, in an order the compiler chooses (vectorised): within a few
        float64 roundings of the exact sums. NaN or Inf where a row holds one.

    Raises
    ------
    ValueError
        Other dtypes or shapes, or a ``pos`` outside ``ref``.
    """
    p = np.asarray(pos)
    if p.size and (p.min() < 0 or p.max() >= len(ref)):
        raise ValueError(f"row_sums: positions must be in [0, {len(ref)}), got {p.min()}..{p.max()}")
    return screen_and_row_sums(x, None, None, None, ref, pos, ref_scale=ref_scale, ref_mean=ref_mean)[1:]


def screen_and_row_sums(x, flat_tol, max_abs_v, clip_run, ref, pos, out=None, ref_scale=None, ref_mean=None):
    """:func:`screen_codes` and :func:`row_sums` of the same rows, each row read from memory once.

    Parameters
    ----------
    x : ndarray of float32 or float64, shape (n, m), m >= 1
    flat_tol, max_abs_v, clip_run
        As for :func:`screen_codes`; ``clip_run`` None: no screening (the codes are not written).
    ref : ndarray of float32, float64 or int16, shape (n_ref, m), or None
        Reference rows; None: no sums (they are NaN).
    pos : ndarray of int64, shape (n,), or None
        Each row's reference row in ``[0, n_ref)``, or -1 for a row without one (its sums NaN).
    out : tuple of 4 ndarray, optional
        ``(code uint8, x1, xx, xr float64)``, each of shape (n,), to write into (e.g. one
        frame's slices of a batch's arrays).
    ref_scale, ref_mean : ndarray of float64, shape (n_ref,), optional
        As for :func:`row_sums`.

    Returns
    -------
    code : ndarray of uint8, shape (n,)
    x1, xx, xr : ndarray of float64, shape (n,)

    Raises
    ------
    ValueError
        Other dtypes or shapes, or a position outside ``[-1, n_ref)``.
    """
    return _screen_and_sum([x], flat_tol, max_abs_v, clip_run, ref, pos, out, ref_scale, ref_mean)


def screen_frames_and_row_sums(frames, flat_tol, max_abs_v, clip_run, ref, pos, ref_scale=None, ref_mean=None):
    """:func:`screen_and_row_sums` of a batch of frames, each frame's rows in turn into the batch's arrays
    (the frames not concatenated), the arguments checked once for the batch instead of once per frame.

    Parameters
    ----------
    frames : sequence of ndarray of float32 or float64, each of shape (n_i, m), m >= 1
    flat_tol, max_abs_v, clip_run
        As for :func:`screen_codes`.
    ref : ndarray of float32, float64 or int16, shape (n_ref, m), or None
    pos : ndarray of int64, shape (sum n_i,), or None
        Each row's reference row in ``[0, n_ref)``, or -1.
    ref_scale, ref_mean : ndarray of float64, shape (n_ref,), optional
        As for :func:`row_sums`.

    Returns
    -------
    code : ndarray of uint8, shape (sum n_i,)
    x1, xx, xr : ndarray of float64, shape (sum n_i,)
    """
    return _screen_and_sum(frames, flat_tol, max_abs_v, clip_run, ref, pos, None, ref_scale, ref_mean)


def _screen_and_sum(frames, flat_tol, max_abs_v, clip_run, ref, pos, out, ref_scale, ref_mean):
    """Both functions above: the arguments checked once, then the kernel frame by frame into one set of arrays."""
    m = frames[0].shape[1] if frames and frames[0].ndim == 2 else 0
    for a in frames:
        if a.dtype not in (np.float32, np.float64) or a.ndim != 2 or a.shape[1] != m or m == 0:
            raise ValueError(f"the screening and gate kernels take (n, m >= 1) float32 or float64 rows of one "
                             f"width, got {a.dtype} {a.shape}")
    n = sum(a.shape[0] for a in frames)
    if ref is None:
        ref, pos, ref_scale, ref_mean = np.zeros((1, m), np.float32), np.full(n, -1, np.int64), None, None
    pos = np.asarray(pos)
    if ref.ndim != 2 or ref.shape[1] != m or pos.shape != (n,) or pos.dtype != np.int64:
        raise ValueError(f"the gate's row sums take float rows (n, m), references (n_ref, m) and int64 positions "
                         f"(n,), got {n} rows of {m}, {ref.dtype} {ref.shape} and {pos.dtype} {pos.shape}")
    scale, mean = _reference_scale(ref, ref_scale, ref_mean)
    if n and (pos.min() < -1 or pos.max() >= ref.shape[0]):
        raise ValueError(f"the gate's row sums: positions must be in [-1, {ref.shape[0]}) (-1: no reference), "
                         f"got {pos.min()}..{pos.max()}")
    code, x1, xx, xr = out if out is not None else (np.empty(n, np.uint8), np.empty(n), np.empty(n), np.empty(n))
    screen = clip_run is not None
    i = 0
    for a in frames:
        j = i + a.shape[0]
        if j > i:
            _screen_sums(a, a.view(np.int32 if a.dtype == np.float32 else np.int64), screen,
                         float(flat_tol) if screen else 0.0, float(max_abs_v) if screen else 0.0,
                         int(clip_run) if screen else 0, ref, scale, mean, pos[i:j], code[i:j], x1[i:j], xx[i:j],
                         xr[i:j])
        i = j
    return code, x1, xx, xr


def _reference_scale(ref, ref_scale, ref_mean) -> tuple:
    """The kernels' ``scale`` and ``mean`` of a reference table: ``ref_scale`` and ``ref_mean`` checked (float64
    (n_ref,); a scale is needed with int16 references, a mean None is 0), or both empty (float references
    without a scale: neither scaled nor shifted)."""
    if ref.dtype not in (np.float32, np.float64, np.int16):
        raise ValueError(f"references must be float32, float64 or int16 (quantized), got {ref.dtype}")
    if ref_scale is None:
        if ref.dtype == np.int16:
            raise ValueError("int16 references need their ref_scale (inkdiag_core.gate.quantize_references)")
        if ref_mean is not None:
            raise ValueError("a ref_mean goes with a ref_scale")
        return np.empty(0), np.empty(0)
    out = []
    for name, v in (("ref_scale", ref_scale), ("ref_mean", np.zeros(ref.shape[0]) if ref_mean is None else ref_mean)):
        v = np.asarray(v)
        if v.shape != (ref.shape[0],) or v.dtype != np.float64:
            raise ValueError(f"{name} must be float64 of shape ({ref.shape[0]},), one per reference row, got "
                             f"{v.dtype} {v.shape}")
        out.append(np.require(v, np.float64, ["C"]))
    return tuple(out)


def screen_gate_frames(frames, flat_tol, max_abs_v, clip_run, positions, verdict, firsts, nozzles=None):
    """Screening, the healthy gate and the gathering of the rows left for the detector, frame by frame
    (:class:`inkdiag_core.FrameLabeller`'s first stage): one compiled call per frame, each row read from
    memory once for its screening and its sums (:func:`screen_and_row_sums`), its verdict
    :func:`gate_codes`' own. Only the few rows the gate leaves are copied; a frame all of whose rows are
    left is handed back as it is.

    Parameters
    ----------
    frames : sequence of ndarray, each of shape (n_i, m), m >= 1, all float32 or all float64
    flat_tol, max_abs_v, clip_run
        As for :func:`screen_codes`.
    positions : sequence of ndarray of int64, each of shape (n_i,), or None
        Each row's reference row (:meth:`inkdiag_core.HealthyGate.positions`, -1: none); None: no gate.
    verdict : tuple or None
        :attr:`inkdiag_core.HealthyGate.verdict_params` (with ``positions``): ``(ref, rr, n_samples,
        max_residual_fraction, jetting_gain, ok_gain[, ref_scale[, ref_mean]])``, the last two as for
        :func:`row_sums`.
    firsts : sequence of int
        Each frame's first nozzle id (its rows consecutive ids), where ``nozzles`` does not give them.
    nozzles : sequence of ndarray of int64, each of shape (n_i,), optional
        Each frame's nozzle id per row.

    Returns
    -------
    code : ndarray of uint8, shape (sum n_i,)
        0: left for the detector; 1-4: invalid (:func:`screen_codes`' codes); :data:`inkdiag_core.gate.CLEARED_HEALTHY`,
        :data:`inkdiag_core.gate.CLEARED_OK`: cleared by the gate.
    at : ndarray of int64, shape (k,)
        The rows left, ascending batch indices.
    nozzle : ndarray of int64, shape (k,)
        Their nozzle ids.
    rows : list of ndarray
        The rows left, in order: copies of the few, or a whole frame itself.

    Raises
    ------
    ValueError
        Frames of several dtypes or widths, other dtypes, or a position outside ``[-1, n_ref)``.
    """
    m = frames[0].shape[1] if frames and frames[0].ndim == 2 else 0
    dtype = frames[0].dtype if frames else None
    for a in frames:
        if a.dtype != dtype or dtype not in (np.float32, np.float64) or a.ndim != 2 or a.shape[1] != m or m == 0:
            raise ValueError(f"screen_gate_frames takes (n, m >= 1) rows of one width and one float dtype "
                             f"(float32 or float64), got {a.dtype} {a.shape}")
    n = sum(a.shape[0] for a in frames)
    if positions is None:
        ref, rr, n_samples, max_f, (jet_lo, jet_hi), (ok_lo, ok_hi) = (np.zeros((1, m), np.float32), np.ones(1), m,
                                                                      0.0, (0.0, 0.0), (0.0, 0.0))
        scale = mean = np.empty(0)
    else:
        ref, rr, n_samples, max_f, (jet_lo, jet_hi), (ok_lo, ok_hi), *ref_scale = verdict
        if ref.ndim != 2 or ref.shape[1] != m or rr.shape != (ref.shape[0],) or rr.dtype != np.float64:
            raise ValueError(f"screen_gate_frames: references (n_ref, {m}) of float32, float64 or int16 and r.r "
                             f"(n_ref,) float64, got {ref.dtype} {ref.shape} and {rr.dtype} {rr.shape}")
        scale, mean = _reference_scale(ref, *(ref_scale + [None, None])[:2])
    no_pos, no_ids = np.empty(0, np.int64), np.empty(0, np.int64)
    code, at, nozzle = np.empty(n, np.uint8), np.empty(n, np.int64), np.empty(n, np.int64)
    left = np.empty((n, m), dtype)
    bits_type = np.int32 if dtype == np.float32 else np.int64
    rows, k, row0, run = [], 0, 0, None  # run: where the copies not yet handed out start in left
    for f, a in enumerate(frames):
        p = no_pos if positions is None else positions[f]
        ids = no_ids if nozzles is None else nozzles[f]
        if (p.shape not in ((0,), (a.shape[0],)) or p.dtype != np.int64 or ids.shape not in ((0,), (a.shape[0],))
                or ids.dtype != np.int64):
            raise ValueError(f"screen_gate_frames: frame {f} has {a.shape[0]} rows, its int64 positions and nozzle "
                             f"ids {p.dtype} {p.shape} and {ids.shape}")
        k0 = k
        k, whole, bad = _screen_gate_rows(a, a.view(bits_type), float(flat_tol), float(max_abs_v), int(clip_run), ref,
                                          scale, mean, p, rr, float(n_samples), float(max_f), float(jet_lo),
                                          float(jet_hi), float(ok_lo), float(ok_hi),
                                          int(firsts[f]) if nozzles is None else 0,
                                          ids, row0, code, at, nozzle, left, k)
        if bad != -1:
            raise ValueError(f"screen_gate_frames: positions must be in [-1, {ref.shape[0]}) (-1: no reference), "
                             f"got {bad}")
        if whole and k > k0:
            if run is not None:
                rows.append(left[run:k0])
                run = None
            rows.append(a)
        elif k > k0 and run is None:
            run = k0
        row0 += a.shape[0]
    if run is not None:
        rows.append(left[run:k])
    return code, at[:k], nozzle[:k], rows

def gate_codes(x1, xx, xr, pos, rr, n_samples, max_residual_fraction, jetting_gain, ok_gain):
    """The healthy gate's verdict per row from its three sums (:meth:`inkdiag_core.HealthyGate.decide`'s
    arithmetic, one loop instead of about a dozen numpy passes: the same verdicts, bit for bit).

    Parameters
    ----------
    x1, xx, xr : ndarray of float64, shape (n,)
        Each row's ``sum(x)``, ``sum(x * x)``, ``sum(x * r)``.
    pos : ndarray of int64, shape (n,)
        Each row's reference row, -1 for none (not cleared).
    rr : ndarray of float64, shape (n_ref,)
        ``r.r`` of each reference row (finite and positive where ``pos`` points).
    n_samples : int
    max_residual_fraction : float
    jetting_gain, ok_gain : (float, float)
        The gain bands (not overlapping).

    Returns
    -------
    ndarray of uint8, shape (n,)
        0: not cleared, 1: cleared ``healthy_nozzle``, 2: cleared ``ok_signal``.
    """
    n = np.shape(x1)[0]
    same = np.shape(x1) == np.shape(xx) == np.shape(xr) == np.shape(pos) == (n,)
    if not same or getattr(pos, "dtype", None) != np.int64:
        raise ValueError(f"gate_codes takes x1, xx, xr and int64 pos of one shape (n,), got {np.shape(x1)}, "
                         f"{np.shape(xx)}, {np.shape(xr)}, {np.shape(pos)} {getattr(pos, 'dtype', '')}")
    if n and (pos.min() < -1 or pos.max() >= len(rr)):
        raise ValueError(f"gate_codes: positions must be in [-1, {len(rr)}), got {pos.min()}..{pos.max()}")
    out = np.empty(n, np.uint8)
    _gate_codes(x1, xx, xr, pos, rr, float(n_samples), float(max_residual_fraction), float(jetting_gain[0]),
                float(jetting_gain[1]), float(ok_gain[0]), float(ok_gain[1]), out)
    return out


def warm_up() -> None:
    """Compile (first run) or load from the cache every kernel for the rows a labeller sees.

    C-contiguous float32 and float64 rows, writable (a batch of frames concatenated) and
    read-only (a frame decoded from a message is a read-only view of it): numba compiles
    each kind separately. Another layout (a strided view) compiles on its first call.
    """
    for dtype in (np.float32, np.float64):
        for writeable in (True, False):
            x = np.zeros((1, 4), dtype)
            x.flags.writeable = writeable
            screen_and_row_sums(x, 1e-6, np.inf, 5, np.zeros((1, 4), np.float32), np.zeros(1, np.int64))
            screen_and_row_sums(x, 1e-6, np.inf, 5, np.zeros((1, 4), np.int16), np.zeros(1, np.int64),
                                ref_scale=np.ones(1), ref_mean=np.zeros(1))  # the gate's quantized references
    fit_windows(np.ones((1, 16), np.complex128), np.ones(1, np.int64), np.ones(1, np.int64), 64)
    for ctype in (np.complex64, np.complex128):
        kpis_of_spectra(np.ones((1, 33), ctype), 64, 1.0, 1e-12, np.empty((1, 7)))
    forest_proba(np.zeros((1, 1), np.float32), np.zeros(1, np.int64), np.full((1, 4), -1, np.int32), np.zeros(1),
                 np.ones((1, 1)))
    for dtype in (np.float32, np.float64):
        for writeable in (True, False):
            x = np.zeros((1, 4), dtype)
            x.flags.writeable = writeable
            unexplained(x, np.zeros((1, 7)), 1.0, 1e-30)
    p_values(np.zeros((1, 2), np.float32), np.zeros(1, np.float32), np.array([0, 1, 1]), np.array([True, False]))
    mahalanobis_scores(np.zeros((1, 2), np.float32), np.ones((2, 4), np.float32), np.zeros(4, np.float32))
    forest = (np.zeros(1, np.int64), np.full((1, 4), -1, np.int32), np.zeros(1), np.ones((1, 2)))
    for dtype in (np.float32, np.float64):  # both branches' rows (one signature: base (0, 7) or (n, 7))
        detector_tail(np.ones((1, 7)), None, np.zeros((1, 4), dtype), 1.0, forest, np.array([True, False]), 0.5,
                      None, eps=1e-30)
    gate_codes(np.zeros(1), np.zeros(1), np.zeros(1), np.zeros(1, np.int64), np.ones(1), 4, 0.5, (0.9, 1.1), (0.7, 0.8))
    for dtype in (np.float32, np.float64):
        for writeable in (True, False):
            x = np.zeros((2, 4), dtype)
            x.flags.writeable = writeable
            screen_gate_frames([x], 1e-6, np.inf, 5, None, None, [0])
            screen_gate_frames([x], 1e-6, np.inf, 5, [np.zeros(2, np.int64)],  # the gate's quantized references
                               (np.ones((1, 4), np.int16), np.ones(1), 4, 0.5, (0.9, 1.1), (0.7, 0.8), np.ones(1),
                                np.zeros(1)), [0])


if __name__ == "__main__":  # scripts/_bootstrap.sh: compile at install
    warm_up()
