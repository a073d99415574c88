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
  loops read it from cache. The labeller calls it once per frame into its batch's arrays:
  the frames of a batch are not concatenated first (a copy of every sample).
- :func:`fit_windows`: the KPIs' damped-sinusoid fit on each trace's spectral window
  (:func:`inkdiag_core.spectral_fit.fit_windows`, its numpy reference, has the method),
  one trace at a time: in numpy about a hundred small array operations per call, a fixed
  cost that dominates on the few rows the gate leaves to the detector. Same arithmetic,
  sums in another order: within ~1e-11 relative of the numpy fit on the simulator's traces
  (12,000 rows, 5 seeds); where the fit is ill-conditioned (a step, a window of noise, a
  2-sample trace) both versions move as much under a 1e-15 change of their input. Every
  KPI (``extract_kpis``: training and labelling alike) comes from this fit.
- :func:`forest_proba`: a Random Forest's class probabilities, every tree walked per row in
  one call (:func:`inkdiag_core.fdi.forest_predict_proba` flattens the forest once). In
  numpy each tree is a call of its own (``tree_.predict``, a few us each, 50 per forest) and
  an ``(n, k)`` sum: the forest's fixed cost on the few rows the gate leaves. The same
  comparisons (the float32 feature against the float64 threshold) and the same sums in
  the same order per row: bit-identical to scikit-learn's ``predict_proba``.

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

import numba
import numpy as np
from llvmlite import ir
from numba.core import types
from numba.core.extending import intrinsic

__all__ = ["fit_windows", "forest_proba", "row_sums", "screen_and_row_sums", "screen_codes", "warm_up"]

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
def _screen_sums(x, bits, screen, flat_tol, max_abs_v, clip_run, ref, pos, code, s1, s2, sr):
    """Per row: its screening code (if ``screen``) and, where ``pos[i] >= 0``, its three sums against
    ``ref[pos[i]]`` (NaN elsewhere). Each row's loops run back to back, so the row is read from
    memory once. ``bits`` is ``x`` viewed as signed integers of its width."""
    n, m = x.shape
    top = np.iinfo(bits.dtype).max  # all bits but the sign: flips a negative float's order
    sign = 8 * bits.itemsize - 1
    for i in range(n):
        if screen:
            # the extremes over the bit patterns mapped to integers of the floats' order: vectorises
            # (a float max with NaN semantics does not), exact, a NaN maps beyond +-Inf
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
                ch = 0
                cl = 0
                for k in range(m):
                    v = x[i, k]
                    ch += v == a
                    cl += v == b
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
        sr[i] = c3


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
def _forest_sums(X, roots, nodes, threshold, value, out):
    n_classes = value.shape[1]
    for t in range(roots.shape[0]):  # tree by tree (its nodes stay in cache); each row's sum in tree order
        root = roots[t]
        for i in range(X.shape[0]):
            node = root
            left = nodes[node, 0]
            while left >= 0:
                if X[i, nodes[node, 2]] <= threshold[node]:
                    node = left
                else:
                    node = nodes[node, 1]
                left = nodes[node, 0]
            for c in range(n_classes):
                out[i, c] += value[node, c]


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


def row_sums(x, ref, pos):
    """``sum(x)``, ``sum(x * x)`` and ``sum(x * r)`` of each row, in float64, ``r`` its row of ``ref``.

    Each row's reference is read where it lies in ``ref`` (row ``pos[i]``): no gathered copy
    of the references (a batch that wraps around the head, or any out-of-order ids, would
    otherwise copy every row's reference first).

    Parameters
    ----------
    x : ndarray of float32 or float64, shape (n, m)
    ref : ndarray of float32 or float64, shape (n_ref, m)
        The references, one per row of the table.
    pos : ndarray of int64, shape (n,)
        Each row's reference row, in ``[0, n_ref)``.

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
    return screen_and_row_sums(x, None, None, None, ref, pos)[1:]


def screen_and_row_sums(x, flat_tol, max_abs_v, clip_run, ref, pos, out=None):
    """:func:`screen_codes` and :func:`row_sums` of the same rows, each row read from memory once.

    Parameters
    ----------
    x : ndarray of float32 or float64, shape (n, m), m >= 1
    flat_tol, max_abs_v, clip_run
        As for :func:`screen_codes`; ``clip_run`` None: no screening (the codes are not written).
    ref : ndarray of float32 or float64, shape (n_ref, m), or None
        Reference rows; None: no sums (they are NaN).
    pos : ndarray of int64, shape (n,), or None
        Each row's reference row in ``[0, n_ref)``, or -1 for a row without one (its sums NaN).
    out : tuple of 4 ndarray, optional
        ``(code uint8, x1, xx, xr float64)``, each of shape (n,), to write into (e.g. one
        frame's slices of a batch's arrays).

    Returns
    -------
    code : ndarray of uint8, shape (n,)
    x1, xx, xr : ndarray of float64, shape (n,)

    Raises
    ------
    ValueError
        Other dtypes or shapes, or a position outside ``[-1, n_ref)``.
    """
    if x.dtype not in (np.float32, np.float64) or x.ndim != 2 or x.shape[1] == 0:
        raise ValueError(f"the screening and gate kernels take (n, m >= 1) float32 or float64 rows, "
                         f"got {x.dtype} {x.shape}")
    n, m = x.shape
    if ref is None:
        ref, pos = np.zeros((1, m), np.float32), np.full(n, -1, np.int64)
    pos = np.asarray(pos)
    if (ref.dtype not in (np.float32, np.float64) or ref.ndim != 2 or ref.shape[1] != m
            or pos.shape != (n,) or pos.dtype != np.int64):
        raise ValueError(f"the gate's row sums take float rows (n, m), references (n_ref, m) and int64 positions "
                         f"(n,), got {x.dtype} {x.shape}, {ref.dtype} {ref.shape} and {pos.dtype} {pos.shape}")
    if n and (pos.min() < -1 or pos.max() >= ref.shape[0]):
        raise ValueError(f"the gate's row sums: positions must be in [-1, {ref.shape[0]}) (-1: no reference), "
                         f"got {pos.min()}..{pos.max()}")
    code, x1, xx, xr = out if out is not None else (np.empty(n, np.uint8), np.empty(n), np.empty(n), np.empty(n))
    if n:
        screen = clip_run is not None
        _screen_sums(x, x.view(np.int32 if x.dtype == np.float32 else np.int64), screen,
                     float(flat_tol) if screen else 0.0, float(max_abs_v) if screen else 0.0,
                     int(clip_run) if screen else 0, ref, pos, code, x1, xx, xr)
    return code, x1, xx, xr


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
    fit_windows(np.ones((1, 16), np.complex128), np.ones(1, np.int64), np.ones(1, np.int64), 64)
    forest_proba(np.zeros((1, 1), np.float32), np.zeros(1, np.int64), np.full((1, 4), -1, np.int32), np.zeros(1),
                 np.ones((1, 1)))


if __name__ == "__main__":  # scripts/_bootstrap.sh: compile at install
    warm_up()
