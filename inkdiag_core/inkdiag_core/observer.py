"""Unknown-input observer of the thesis (section 4.3.3, eq. 13-20) and its existence test.

For ``x' = A x + B_f f``, ``y = C x`` the full-order UIO is ::

    z' = F z + T y,        x_hat = z + H y                       (eq. 14)

with ``H = B_f (C B_f)^+`` so that ``(I - H C) B_f = 0`` (eq. 17), ``F = A - H C A``
(eq. 18) and ``T = A H - H C A H`` (eq. 19; the thesis's approximation eq. 20 is
``T = A H``). Its error obeys ``e' = F e``. The same algebra holds in discrete
time with ``A_d`` in place of ``A`` (then "stable" means ``|lambda| < 1``).

Existence (Chen & Patton, *Robust model-based fault diagnosis*, 1999, Thm 3.1):
a UIO with asymptotically stable error exists iff

1. ``rank(C B_f) = rank(B_f)``, and
2. ``(C, A1)`` with ``A1 = (I - H C) A`` is detectable.

Chen-Patton's full-order form then takes ``F = A1 - K1 C`` with ``K1`` placing
the observable eigenvalues of ``A1``, ``T = K1 + F H`` (no known input here).
Everything below is computed, not assumed: for the ink channel (eq. 12) the
continuous-time ``A1`` has eigenvalues ``{0, 0, -R_r/I_r}`` and ``(C, A1)`` has
observability rank 1 (indeed ``C (I - H C) = 0`` whenever ``C H = 1``), so one
zero eigenvalue is unobservable and no stabilising gain exists; the
discrete-time design of eq. 25 is a different matter and is reported as found.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.linalg as sla
import scipy.signal

from . import checks

__all__ = ["UIODesign", "design_uio"]


@dataclass(frozen=True)
class UIODesign:
    """A UIO design and the checks behind it (all matrices in the caller's units).

    Attributes
    ----------
    H, F, T, T_approx : ndarray
        ``H`` (n, p), ``F = (I - H C) A`` (n, n), exact ``T = F H`` (eq. 19) and the
        thesis's ``T_approx = A H`` (eq. 20), (n, p).
    rank_CBf, rank_Bf : int
        Ranks in condition 1.
    rank_condition : bool
        ``rank(C B_f) == rank(B_f)``.
    eig_F : ndarray
        Eigenvalues of ``F`` (1/s in continuous time, per-sample multipliers in discrete time).
    obs_rank : int
        Rank of the observability matrix of ``(C, F)``.
    unobservable_eigs : ndarray
        Eigenvalues of ``F`` that fail the PBH test (unobservable modes).
    stable : bool
        ``F`` itself (no gain) is asymptotically stable.
    detectable : bool
        Every unstable or marginal eigenvalue of ``F`` is observable.
    K1 : ndarray or None
        A stabilising gain when one exists and is needed (Chen-Patton form), else None.
    F_cp, T_cp : ndarray or None
        ``F - K1 C`` and ``K1 + (F - K1 C) H`` of the Chen-Patton form, or None.
    discrete : bool
        True for a discrete-time design (``dt`` was given).
    """

    H: np.ndarray
    F: np.ndarray
    T: np.ndarray
    T_approx: np.ndarray
    rank_CBf: int
    rank_Bf: int
    rank_condition: bool
    eig_F: np.ndarray
    obs_rank: int
    unobservable_eigs: np.ndarray
    stable: bool
    detectable: bool
    K1: np.ndarray | None = None
    F_cp: np.ndarray | None = None
    T_cp: np.ndarray | None = None
    discrete: bool = False
    notes: list = field(default_factory=list)

    @property
    def exists(self) -> bool:
        """A UIO with asymptotically stable error exists (conditions 1 and 2)."""
        return bool(self.rank_condition and self.detectable)

    def summary(self) -> str:
        """Human-readable report of the checks, one fact per line."""
        dom = "discrete" if self.discrete else "continuous"
        eig = ", ".join(_fmt_eig(v) for v in self.eig_F)
        une = ", ".join(_fmt_eig(v) for v in self.unobservable_eigs) or "none"
        lines = [
            f"{dom}-time UIO, H = B_f (C B_f)^+",
            f"rank(C B_f) = {self.rank_CBf}, rank(B_f) = {self.rank_Bf}: "
            f"condition 1 {'holds' if self.rank_condition else 'FAILS'}",
            f"eig(F = (I-HC)A) = {{{eig}}}",
            f"observability rank of (C, F) = {self.obs_rank} of {self.F.shape[0]}; "
            f"unobservable eigenvalues: {une}",
            f"F stable without gain: {self.stable}; (C, F) detectable: {self.detectable}",
        ]
        if self.K1 is not None:
            lines.append(f"Chen-Patton gain K1 = {np.array2string(self.K1.ravel(), precision=4)}")
        elif not self.exists:
            lines.append("no UIO with asymptotically stable error exists for this pair")
        lines.extend(self.notes)
        return "\n".join(lines)


def _fmt_eig(v: complex) -> str:
    v = complex(v)
    if abs(v.imag) <= 1e-12 * max(1.0, abs(v)):
        return f"{v.real:.4g}"
    return f"{v.real:.4g}{v.imag:+.4g}j"


def _check_matrices(A, C, B_f):
    A = np.asarray(A, dtype=float)
    C = np.asarray(C, dtype=float)
    B_f = np.asarray(B_f, dtype=float)
    if A.ndim != 2 or A.shape[0] != A.shape[1]:
        raise checks.InputError(f"A must be square (n, n), got shape {A.shape}")
    n = A.shape[0]
    if C.ndim != 2 or C.shape[1] != n:
        raise checks.InputError(f"C must have shape (p, {n}), got {C.shape}")
    if B_f.ndim != 2 or B_f.shape[0] != n:
        raise checks.InputError(f"B_f must have shape ({n}, q), got {B_f.shape}")
    return tuple(checks.finite_array(name, M) for name, M in (("A", A), ("C", C), ("B_f", B_f)))


def design_uio(A, C, B_f, *, dt: float | None = None, poles=None, rtol: float = 1e-9):
    """Design the thesis's UIO and check the existence conditions.

    Parameters
    ----------
    A : array_like, shape (n, n)
        Continuous-time system matrix (1/s), or the discrete-time ``A_d`` if ``dt`` is given.
    C : array_like, shape (p, n)
    B_f : array_like, shape (n, q)
        Unknown-input (fault) matrix.
    dt : float, optional
        Sample period in s; marks ``A`` as discrete-time (stability is ``|lambda| < 1``).
    poles : array_like, optional
        Where to place the observable eigenvalues of ``F`` in the Chen-Patton form
        (default: mirror unstable/marginal observable ones to a stable location).
    rtol : float
        Relative tolerance of the rank decisions (on a balanced, scaled copy).

    Returns
    -------
    UIODesign
    """
    A, C, B_f = _check_matrices(A, C, B_f)
    n = A.shape[0]
    discrete = dt is not None
    # Conditioning: balance A (diagonal similarity, powers of 2) and, in continuous
    # time, measure time in units of 1/||A|| so that ranks are decided on O(1) numbers.
    if discrete:
        As = A.copy()
        t_unit = 1.0
    else:
        t_unit = 1.0 / max(np.abs(np.linalg.eigvals(A)).max(), 1e-300)
        As = A * t_unit
    _, (scale, _) = sla.matrix_balance(As, permute=False, separate=True)
    D = np.diag(scale)
    Di = np.diag(1.0 / scale)
    As = Di @ As @ D
    Cs = C @ D
    Bs = Di @ B_f

    def rank(M):
        s = np.linalg.svd(M, compute_uv=False)
        return int(np.sum(s > rtol * max(s.max(initial=0.0), 1e-300))) if s.size else 0

    CB = Cs @ Bs
    rank_CBf, rank_Bf = rank(CB), rank(Bs)
    Hs = Bs @ np.linalg.pinv(CB)
    Es = np.eye(n) - Hs @ Cs
    Fs = Es @ As
    eig_s = np.linalg.eigvals(Fs)
    O = np.vstack([Cs @ np.linalg.matrix_power(Fs, k) for k in range(n)])
    obs_rank = rank(O)

    def is_stable(lam):
        return (abs(lam) < 1.0 - 1e-12) if discrete else (lam.real < -1e-9)

    unobs = []
    for lam in eig_s:
        if any(abs(lam - u) <= 1e-9 * max(1.0, abs(lam)) for u in unobs):
            continue  # repeated eigenvalue: test once
        M = np.vstack([lam * np.eye(n) - Fs, Cs])
        if rank(M) < n:
            unobs.append(lam)
    unobs = np.array(unobs, dtype=complex)
    stable = bool(all(is_stable(l) for l in eig_s))
    detectable = bool(all(is_stable(l) for l in unobs))

    notes = []
    K1s = None
    if rank_CBf == rank_Bf and detectable and not stable:
        # place the observable part: observer gain via pole placement on (F^T, C^T)
        bad = [l for l in eig_s if not is_stable(l)]
        if poles is None:
            if discrete:
                target = [0.5 * l / max(abs(l), 1e-12) if abs(l) > 0 else 0.5 for l in bad]
            else:
                target = [complex(-abs(l.real) - 1.0, l.imag) if l.real >= 0 else l for l in bad]
            keep = [l for l in eig_s if is_stable(l)]
            poles_s = np.array(keep + target)
        else:
            poles_s = np.asarray(poles, dtype=complex) * (1.0 if discrete else t_unit)
        try:
            res = scipy.signal.place_poles(Fs.T, Cs.T, poles_s)
            K1s = res.gain_matrix.T
        except (ValueError, np.linalg.LinAlgError) as exc:  # pragma: no cover - defensive
            notes.append(f"pole placement failed: {exc}")

    # back to the caller's coordinates (and time unit)
    H = D @ Hs
    F = (np.eye(n) - H @ C) @ A
    T = F @ H
    T_approx = A @ H
    eig_F = eig_s / (1.0 if discrete else t_unit)
    unobs_F = unobs / (1.0 if discrete else t_unit)
    K1 = F_cp = T_cp = None
    if K1s is not None:
        K1 = D @ K1s / (1.0 if discrete else t_unit)
        F_cp = F - K1 @ C
        T_cp = K1 + F_cp @ H
    return UIODesign(
        H=H, F=F, T=T, T_approx=T_approx, rank_CBf=rank_CBf, rank_Bf=rank_Bf,
        rank_condition=rank_CBf == rank_Bf, eig_F=eig_F, obs_rank=obs_rank,
        unobservable_eigs=unobs_F, stable=stable, detectable=detectable, K1=K1,
        F_cp=F_cp, T_cp=T_cp, discrete=discrete, notes=notes,
    )
