"""Lumped ink-channel model (thesis section 2.3, eq. 1-2 and 12; Appendix F).

The ink channel is a chamber of total compliance ``B_t`` fed by a restrictor
and emptied through a nozzle. The piezo actuator displaces the volume
``b * u`` into the chamber (``u`` in volts). With ``V_r`` and ``V_n`` the
volumes that have flowed *out of the chamber* through the restrictor and the
nozzle, the chamber's excess pressure is

    p = (b u - V_r - V_n) / B_t                                       [Pa]

and it drives both necks (inertance ``I``, Poiseuille resistance ``R``):

    I_r dV_r'/dt = p - R_r V_r'
    I_n dV_n'/dt = p - R_n V_n'

This is the consistent reading of the thesis's eq. (1)-(2), whose extracted
text is partly garbled (eq. 1 carries a stray factor 2 and eq. 2 has the sign
of the (3,1) entry flipped; eq. 12, 21 and 27 agree with the set above).

State spaces
------------
4-state (eq. 2), ``x = [V_r, V_n, V_r', V_n']`` (m^3, m^3, m^3/s, m^3/s)::

    A4 = [[ 0,          0,           1,         0        ],
          [ 0,          0,           0,         1        ],
          [-1/(I_r B_t), -1/(I_r B_t), -R_r/I_r,  0        ],
          [-1/(I_n B_t), -1/(I_n B_t),  0,        -R_n/I_n ]]
    B4 = [0, 0, b/(I_r B_t), b/(I_n B_t)]^T

3-state observable form (eq. 12), ``x = [V_r + V_n, V_r', V_n']``::

    A = [[ 0,           1,        1        ],
         [-1/(I_r B_t), -R_r/I_r,  0        ],
         [-1/(I_n B_t),  0,       -R_n/I_n ]],   C = [0, 1, 1],   B_f = [0, 0, 1]^T

The self-sensing output is proportional to the total outflow
``y = V_r' + V_n'`` (m^3/s). A drying nozzle changes only ``R_n``: the
multiplicative fault is ``A_faulty = A + f_m e3 e3^T`` with
``f_m = -dR_n / I_n = -alpha d_mu`` (Appendix F's sign: ``f_m < 0`` when the
ink in the nozzle thickens).

Units are SI throughout (m, kg, s, Pa); internal scaling is never exposed.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
from scipy.linalg import expm

from . import checks

__all__ = [
    "InkChannelParams",
    "InkChannelModel",
    "alpha",
    "fault_fm",
    "fm_to_viscosity",
    "viscosity_to_fm",
]


@dataclass(frozen=True)
class InkChannelParams:
    """Geometry and ink of one ink channel, in SI units.

    The defaults give a healthy dominant mode of 237 kHz (thesis Table 3) with
    a damping ratio of about 0.07, from a 15 um x 60 um nozzle, a
    23.6 um x 182 um restrictor (``I_r ~ 1.03 I_n``, ``R_r ~ R_n / 2``) and a
    10 mPa s ink.

    Parameters
    ----------
    rho : float
        Ink density, kg/m^3.
    mu : float
        Dynamic viscosity of the ink in the channel (restrictor and chamber), Pa s.
    mu_nozzle : float or None
        Viscosity of the ink in the nozzle, Pa s. ``None`` means ``mu``. A
        drying nozzle is ``mu_nozzle > mu``: evaporation at the meniscus
        thickens only the ink in the nozzle.
    r_n, L_n : float
        Nozzle radius and length, m.
    r_r, L_r : float
        Restrictor radius and length, m.
    V_ch : float
        Ink volume of the chamber, m^3.
    c : float
        Speed of sound in the ink, m/s.
    B_act : float
        Compliance of the actuator, m^3/Pa.
    b : float
        Actuator coupling: volume displaced per volt, m^3/V.
    B_extra : float
        Extra compliance in the chamber (for instance entrained gas), m^3/Pa.
    f_act : float or None
        Structural resonance of the actuator alone (an empty channel, no ink film), Hz.
        Only the empty-channel fault classes use it (healthy traces do not show it).
        ``None``: the default head's actuator (2.175 MHz at its ``B_act``) with this
        ``B_act``, ``2.175 MHz * sqrt(5.198e-21 / B_act)``.
    zeta_act : float or None
        Damping ratio of that resonance; ``None``: the default head's, 0.03.
    """

    rho: float = 1000.0
    mu: float = 10e-3
    mu_nozzle: float | None = None
    r_n: float = 15e-6
    L_n: float = 60e-6
    r_r: float = 23.56e-6
    L_r: float = 182.4e-6
    V_ch: float = 5.0e-12
    c: float = 1200.0
    B_act: float = 5.198e-21
    b: float = 2.0e-18
    B_extra: float = 0.0
    f_act: float | None = None
    zeta_act: float | None = None

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if f.name in ("mu_nozzle", "f_act", "zeta_act") and value is None:
                continue
            if f.name == "zeta_act" and not (isinstance(value, (int, float)) and 0 < value < 1):
                raise ValueError(f"zeta_act must be a damping ratio in (0, 1), got {value!r}")
            if f.name == "B_extra":
                checks.nonnegative_float(f.name, value)
                continue
            checks.positive_float(f.name, value)

    def replace(self, **changes) -> "InkChannelParams":
        """Return a copy with some fields changed (validated again)."""
        return dataclasses.replace(self, **changes)

    @property
    def mu_n(self) -> float:
        """Viscosity of the ink in the nozzle, Pa s."""
        return self.mu if self.mu_nozzle is None else float(self.mu_nozzle)

    @property
    def I_n(self) -> float:
        """Nozzle inertance with the end correction of eq. (35), kg/m^4."""
        return self.rho * (self.L_n + math.pi * self.r_n / 4.0) / (math.pi * self.r_n**2)

    @property
    def I_r(self) -> float:
        """Restrictor inertance rho L_r / A_r (Table 1), kg/m^4."""
        return self.rho * self.L_r / (math.pi * self.r_r**2)

    @property
    def R_n(self) -> float:
        """Nozzle Hagen-Poiseuille resistance 8 mu_n L_n / (pi r_n^4) (eq. 34), Pa s/m^3."""
        return 8.0 * self.mu_n * self.L_n / (math.pi * self.r_n**4)

    @property
    def R_r(self) -> float:
        """Restrictor resistance 8 mu L_r / (pi r_r^4), Pa s/m^3.

        Table 1 prints ``r_n`` here; the restrictor's own radius is meant.
        """
        return 8.0 * self.mu * self.L_r / (math.pi * self.r_r**4)

    @property
    def B_t(self) -> float:
        """Total compliance B_act + V_ch / (rho c^2) + B_extra, m^3/Pa."""
        return self.B_act + self.V_ch / (self.rho * self.c**2) + self.B_extra


def alpha(params: InkChannelParams) -> float:
    """Fault gain of Appendix F, eq. (36): ``f_m = -alpha * d_mu``.

    ``alpha = 8 L_n / (rho (L_n + pi r_n / 4) r_n^2)`` in 1/(Pa s^2)
    (so that ``alpha * d_mu`` is in 1/s).
    """
    p = params
    return 8.0 * p.L_n / (p.rho * (p.L_n + math.pi * p.r_n / 4.0) * p.r_n**2)


def fault_fm(params: InkChannelParams, mu_faulty: float) -> float:
    """Multiplicative fault f_m for a nozzle whose ink viscosity became ``mu_faulty``.

    Eq. (33)-(37): ``f_m = -(R_n(mu_faulty) - R_n(mu)) / I_n = -alpha (mu_faulty - mu)``,
    in 1/s; negative for a drying nozzle. ``mu`` is the healthy nozzle
    viscosity ``params.mu_n``.
    """
    mu_f = checks.positive_float("mu_faulty", mu_faulty)
    return -alpha(params) * (mu_f - params.mu_n)


def fm_to_viscosity(params: InkChannelParams, fm):
    """Invert eq. (37): from f_m (1/s) to ``(d_mu, mu)`` in Pa s.

    Works elementwise on arrays. ``d_mu = -f_m / alpha``; ``mu = mu_n + d_mu``.
    """
    fm = np.asarray(fm, dtype=float)
    d_mu = -fm / alpha(params)
    return d_mu, params.mu_n + d_mu


def viscosity_to_fm(params: InkChannelParams, mu):
    """Eq. (37) elementwise: nozzle viscosity ``mu`` (Pa s) to f_m (1/s)."""
    mu = np.asarray(mu, dtype=float)
    return -alpha(params) * (mu - params.mu_n)


class InkChannelModel:
    """Linear state-space model of one ink channel.

    Parameters
    ----------
    params : InkChannelParams, optional
        Physical parameters (SI). Defaults to the healthy 237 kHz channel.

    Notes
    -----
    ``full()`` is the 4-state model with input (eq. 2); ``observable()`` the
    3-state form of eq. (12) used by the estimators. ``discretize`` gives the
    exact zero-order-hold discretisation; ``discretize_appendix_e`` the
    thesis's approximation (healthy A discretised, fault added as f_m dt).
    """

    def __init__(self, params: InkChannelParams | None = None):
        self.params = InkChannelParams() if params is None else params
        if not isinstance(self.params, InkChannelParams):
            raise ValueError(
                f"params must be an InkChannelParams, got {type(self.params).__name__}"
            )

    def __repr__(self) -> str:
        f, z = self.dominant_mode()
        return f"InkChannelModel(f={f / 1e3:.1f} kHz, zeta={z:.3f})"

    # -- continuous time -------------------------------------------------
    def full(self):
        """4-state model with input, eq. (2).

        Returns
        -------
        A : ndarray, shape (4, 4)
            1/s and 1/s^2 entries for ``x = [V_r, V_n, V_r', V_n']``.
        B : ndarray, shape (4, 1)
            Input matrix for the actuator voltage u (V), (m^3/s^2)/V.
        C : ndarray, shape (1, 4)
            Output ``y = V_r' + V_n'`` (m^3/s).
        """
        p = self.params
        kr = 1.0 / (p.I_r * p.B_t)
        kn = 1.0 / (p.I_n * p.B_t)
        A = np.array(
            [
                [0.0, 0.0, 1.0, 0.0],
                [0.0, 0.0, 0.0, 1.0],
                [-kr, -kr, -p.R_r / p.I_r, 0.0],
                [-kn, -kn, 0.0, -p.R_n / p.I_n],
            ]
        )
        B = np.array([[0.0], [0.0], [p.b * kr], [p.b * kn]])
        C = np.array([[0.0, 0.0, 1.0, 1.0]])
        return A, B, C

    def observable(self, fm: float = 0.0):
        """3-state observable form of eq. (12).

        Parameters
        ----------
        fm : float
            Multiplicative fault added to entry (3, 3), 1/s (0 = healthy).

        Returns
        -------
        A : ndarray, shape (3, 3)
        C : ndarray, shape (1, 3)
        B_f : ndarray, shape (3, 1)
            ``[0, 0, 1]^T``: where ``f_m x_3`` enters.
        """
        p = self.params
        A = np.array(
            [
                [0.0, 1.0, 1.0],
                [-1.0 / (p.I_r * p.B_t), -p.R_r / p.I_r, 0.0],
                [-1.0 / (p.I_n * p.B_t), 0.0, -p.R_n / p.I_n + float(fm)],
            ]
        )
        C = np.array([[0.0, 1.0, 1.0]])
        B_f = np.array([[0.0], [0.0], [1.0]])
        return A, C, B_f

    def input_matrix(self):
        """Input matrix of the observable form for the actuator voltage, shape (3, 1)."""
        p = self.params
        return np.array([[0.0], [p.b / (p.I_r * p.B_t)], [p.b / (p.I_n * p.B_t)]])

    @staticmethod
    def reduce_state(x4):
        """Map 4-state vectors ``[V_r, V_n, V_r', V_n']`` (..., 4) to eq. (12)'s (..., 3)."""
        x4 = np.asarray(x4, dtype=float)
        return np.stack([x4[..., 0] + x4[..., 1], x4[..., 2], x4[..., 3]], axis=-1)

    def dominant_mode(self, fm: float = 0.0):
        """Frequency (Hz) and damping ratio of the oscillatory mode.

        Returns
        -------
        frequency_hz : float
            Damped natural frequency ``Im(lambda) / 2 pi``.
        damping_ratio : float
            ``-Re(lambda) / |lambda|``.
        """
        A, _, _ = self.observable(fm)
        lam = np.linalg.eigvals(A)
        osc = lam[np.abs(lam.imag) > 0]
        if osc.size == 0:  # overdamped: report the slowest-decaying pole
            k = int(np.argmax(lam.real))
            return 0.0, 1.0 if lam[k].real < 0 else 0.0
        k = int(np.argmax(osc.imag))
        lam_k = osc[k]
        return float(lam_k.imag / (2.0 * math.pi)), float(-lam_k.real / abs(lam_k))

    # -- discrete time ---------------------------------------------------
    def discretize(self, sample_rate_hz: float, fm: float = 0.0):
        """Exact discretisation of the autonomous observable form.

        Returns ``A_d = expm((A + fm e3 e3^T) dt)`` (3, 3) for ``dt = 1 / sample_rate_hz`` s.
        """
        fs = checks.sample_rate(sample_rate_hz)
        A, _, _ = self.observable(fm)
        return expm(A / fs)

    def discretize_appendix_e(self, sample_rate_hz: float, fm: float = 0.0):
        """Appendix E approximation (eq. 24): ``expm(A_H dt) + fm dt e3 e3^T``."""
        fs = checks.sample_rate(sample_rate_hz)
        A, _, _ = self.observable(0.0)
        Ad = expm(A / fs)
        Ad[2, 2] += float(fm) / fs
        return Ad

    def free_response(self, x0, n_samples: int, sample_rate_hz: float, fm: float = 0.0):
        """Output of the autonomous observable model from ``x0``.

        Parameters
        ----------
        x0 : array_like, shape (3,)
            Initial state ``[V_r + V_n (m^3), V_r' (m^3/s), V_n' (m^3/s)]`` at t = 0.
        n_samples : int
        sample_rate_hz : float

        Returns
        -------
        y : ndarray, shape (n_samples,)
            ``y[k] = C x(k / fs)`` in m^3/s (exact, by powers of ``A_d``).
        """
        Ad = self.discretize(sample_rate_hz, fm)
        x = np.asarray(x0, dtype=float).reshape(3)
        y = np.empty(int(n_samples))
        for k in range(int(n_samples)):  # O(n_samples) 3x3 products: reference path only
            y[k] = x[1] + x[2]
            x = Ad @ x
        return y
