"""Compiled per-row kernels of the labeller's hot path (numba, cached on disk).

Every row of every frame is screened (:func:`inkdiag_core.screen_traces`: its extremes
and how many samples sit at them) and, where its nozzle has a healthy reference, fitted
to it (:class:`inkdiag_core.HealthyGate`: three row sums). In numpy these are seven
passes over the samples, each a separate reduction; here they are two loops per row,
which LLVM vectorises. ``scripts/bench fdi`` measures both against the numpy passes in
the same run (issue 17: a compiled kernel goes in only where it wins >= 2x on its stage).

- :func:`screen_codes`: each row's screening verdict (valid, non-finite, out of range,
  flat, clipped), exact: the same as numpy's ``max``/``min`` passes and the comparisons
  with them. Float comparisons with NaN semantics do not vectorise without assuming no
  NaN, so the extremes are taken over the samples' bit patterns mapped to integers of
  the same order (``b ^ ((b >> 31) & 0x7fffffff)`` for float32): exact for every finite
  and infinite value, and a NaN maps beyond +-Inf, so a row holding one comes out
  non-finite, as numpy's NaN-propagating max and min say.
- :func:`row_sums`: ``sum(x)``, ``sum(x * x)`` and ``sum(x * r)`` per row, accumulated
  in float64 whatever the input precision. Only these sums may be reassociated
  (``fastmath={"reassoc", "contract"}``): no flag assumes finite values, so a NaN or Inf
  sample still propagates.

The kernels compile on first use and are cached next to this file (numba's
``cache=True``; a read-only install falls back to numba's user-wide cache directory).
:func:`warm_up` compiles or loads them for the rows a labeller sees (C-contiguous float32
and float64, writable and read-only): the labeller calls it when it is built or
unpickled (the labelling process's child), ``scripts/_bootstrap.sh`` at install, so no
node stalls on its first frame. Importing this module imports numba (~0.35 s): the core imports it only
when a kernel is first needed.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["row_sums", "screen_codes", "warm_up"]

_SUMS_FASTMATH = {"reassoc", "contract"}  # reorder and fuse the sums only: no finite-math assumption


@numba.njit(cache=True, nogil=True)
def _ordered_extremes(bits, hi, lo):
    """Per row the largest and smallest of ``bits`` (a float array viewed as signed integers of its
    width) in the floats' order, written back as the floats' bit patterns into ``hi, lo``."""
    n, m = bits.shape
    top = np.iinfo(bits.dtype).max  # all bits but the sign: flips a negative float's order
    sign = 8 * bits.itemsize - 1
    for i in range(n):
        h = bits[i, 0] ^ ((bits[i, 0] >> sign) & top)
        lw = h
        for k in range(1, m):
            q = bits[i, k]
            q = q ^ ((q >> sign) & top)
            h = max(h, q)
            lw = min(lw, q)
        hi[i] = h ^ ((h >> sign) & top)
        lo[i] = lw ^ ((lw >> sign) & top)


@numba.njit(cache=True, nogil=True)
def _codes(x, hi, lo, flat_tol, max_abs_v, clip_run, code):
    """Per row its screening code from its extremes ``hi, lo`` (see :func:`screen_codes`)."""
    n, m = x.shape
    for i in range(n):
        a = hi[i]
        b = lo[i]
        if not (np.isfinite(a) and np.isfinite(b)):
            code[i] = 1  # non_finite
            continue
        if np.float64(a) > max_abs_v or np.float64(b) < -max_abs_v:
            code[i] = 2  # out_of_range
            continue
        if np.float64(a) - np.float64(b) <= flat_tol:
            code[i] = 3  # flat
            continue
        ch = 0
        cl = 0
        for k in range(m):
            v = x[i, k]
            ch += v == a
            cl += v == b
        code[i] = 0
        if ch < clip_run and cl < clip_run:  # nearly every row: no run that long can exist
            continue
        run_h = 0
        run_l = 0
        for k in range(m):  # clip_run consecutive samples at an extreme (float equality: -0.0 == 0.0)
            v = x[i, k]
            run_h = run_h + 1 if v == a else 0
            run_l = run_l + 1 if v == b else 0
            if run_h >= clip_run or run_l >= clip_run:
                code[i] = 4  # clipped
                break


@numba.njit(cache=True, nogil=True, fastmath=_SUMS_FASTMATH)
def _sums(x, r, s1, s2, sr):
    n, m = x.shape
    for i in range(n):
        a = 0.0
        b = 0.0
        c = 0.0
        for k in range(m):
            v = np.float64(x[i, k])
            a += v
            b += v * v
            c += v * np.float64(r[i, k])
        s1[i] = a
        s2[i] = b
        sr[i] = c


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
    if x.dtype not in (np.float32, np.float64) or x.ndim != 2 or x.shape[1] == 0:
        raise ValueError(f"screen_codes takes (n, m >= 1) float32 or float64 rows, got {x.dtype} {x.shape}")
    n = x.shape[0]
    code = np.empty(n, np.uint8)
    if n:
        as_int = np.int32 if x.dtype == np.float32 else np.int64
        hi, lo = np.empty(n, x.dtype), np.empty(n, x.dtype)
        _ordered_extremes(x.view(as_int), hi.view(as_int), lo.view(as_int))
        _codes(x, hi, lo, float(flat_tol), float(max_abs_v), int(clip_run), code)
    return code


def row_sums(x, r):
    """``sum(x)``, ``sum(x * x)`` and ``sum(x * r)`` of each row, in float64.

    Parameters
    ----------
    x : ndarray of float32 or float64, shape (n, m)
    r : ndarray of x's dtype, shape (n, m)
        Each row's reference.

    Returns
    -------
    x1, xx, xr : ndarray of float64, shape (n,)
        Summed in float64, in an order the compiler chooses (vectorised): within a few
        float64 roundings of the exact sums. NaN or Inf where a row holds one.
    """
    if x.dtype not in (np.float32, np.float64) or r.dtype != x.dtype or x.ndim != 2 or r.shape != x.shape:
        raise ValueError(f"row_sums takes float rows and references of one dtype and shape, got "
                         f"{x.dtype} {x.shape} and {r.dtype} {r.shape}")
    n = x.shape[0]
    x1, xx, xr = np.empty(n), np.empty(n), np.empty(n)
    if n:
        _sums(x, r, x1, xx, xr)
    return x1, xx, xr


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
            screen_codes(x, 1e-6, np.inf, 5)
            row_sums(x, np.zeros((1, 4), dtype))  # the gate's references: its own writable array


if __name__ == "__main__":  # scripts/_bootstrap.sh: compile at install
    warm_up()
