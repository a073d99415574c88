"""What both simulators share: the drive, the spreads and the channel draw.

:class:`DriveWaveform` (the actuation pulse), :class:`Spreads` (per-trace
physical variation), :data:`PHYSICAL_CONSTANTS`, and :func:`draw_channels`,
which draws every trace's physical parameters in one fixed order (whatever
its class) and builds its model coefficients, returned as a
:class:`ChannelDraw`. The linear simulator (:mod:`.linear`) and the nonlinear
one (:mod:`.nonlinear`) both start from it, so that for one ``seed`` they
draw the same channels.

Spreads (all from physics, none from the label; see :class:`Spreads`)
---------------------------------------------------------------------
Every trace draws, independently of its class:

==============================  ========================  =====================================
quantity                        default spread            why
==============================  ========================  =====================================
ink temperature                 30 C, std 1.5 K (normal)  head heater regulation; viscosity of
                                                          all the ink follows by Andrade's law,
                                                          -3 %/K at 30 C (typical inkjet ink):
                                                          +-4.5 % R_n, R_r (1 sigma). Widened
                                                          from 1.0 K so that the RF baseline
                                                          lands near the thesis's (94-96 %):
                                                          a head's ink temperature varies with
                                                          print load and position.
nozzle radius r_n               1 % (log-normal)          electroformed/laser-drilled nozzle
                                                          plate, +-0.15 um on 15 um
nozzle length L_n               2 %                       nozzle-plate thickness tolerance
restrictor radius r_r           1 %                       etching tolerance
actuator compliance B_act       3 %                       piezo thickness / d31 spread
actuator coupling b             3 %                       idem
drive amplitude                 1 %                       driver-IC output tolerance
sense gain                      5 %                       per-channel sense amplifier
sense offset                    10 mV std                 amplifier offset
white noise                     SNR 30 dB                 of the nominal healthy trace; the
                                                          noise in volts is the same for every
                                                          trace, so weak traces have lower SNR
ADC                             12 bit over +-2 V         quantisation, clipping at the rails
==============================  ========================  =====================================

Severity within each class's range (:data:`inkdiag_core.faults.MECHANISMS`) is drawn
uniformly. What makes the 12 classes hard to separate, as in the thesis (RF on the 7 KPIs
about 94 %, Table 2), is physics: (i) the severity ranges are wide and neighbouring drying
classes touch or nearly touch, without overlapping (drying is continuous; slight drying
starts at a nozzle viscosity 2.4 times the ink's, where Table 3's slightly dried frequency
puts it), (ii) a particle in the bore adds resistance much
like dried ink (partially blocked overlaps the drying classes), (iii) a nozzle bubble's
position is continuous (mature and intermediate bubbles touch), (iv) ok_signal and
healthy_nozzle differ only by the drive amplitude, which the per-channel coupling, gain
and drive tolerances blur, and (v) temperature moves every class's damping by a few %.
No spread depends on the label, and the noise level, offset and gain distributions are
the same for every class. ``scripts/reports/sim.py`` prints the resulting accuracy.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, field, fields

import numpy as np

from ..faults import MECHANISMS, PARTICLE_LENGTH_FRACTION
from ..model import InkChannelParams

__all__ = [
    "PHYSICAL_CONSTANTS",
    "DriveWaveform",
    "Spreads",
    "ChannelDraw",
    "draw_channels",
    "andrade_viscosity",
    "bubble_compliance",
    "observable_A",
]

PHYSICAL_CONSTANTS = {
    "T_ref_k": 303.15,  # nominal ink temperature (30 C)
    "andrade_b_k": 0.03 * 303.15**2,  # ln mu = A + B/T; -3 %/K at 30 C
    "p0_pa": 1.0e5,  # static chamber pressure (about atmospheric)
    "sigma_n_per_m": 0.030,  # ink surface tension
    "kappa_gas": 1.2,  # polytropic exponent of a micro-bubble at 200 kHz
    "f_act_hz": 2.175e6,  # structural resonance of the unloaded actuator (default head)
    # ... at this nominal actuator compliance (the default head's B_act, m^3/Pa). A head of
    # another B_act keeps the actuator's modal inertance, so its empty-channel resonance is
    # f_act_hz * sqrt(f_act_ref_b_act / B_act) (healthy traces do not show the actuator alone).
    "f_act_ref_b_act": 5.198e-21,
    "zeta_act": 0.03,  # its damping ratio (piezo loss + air)
    "film_loss_factor": 1.5,  # extra actuator resistance per unit ink-film mass ratio
    "sensor_gain_v_per_m3s": 1.0e10,  # nominal sense gain, V per (m^3/s)
}
"""Constants of the simulator's physics (SI units; see the module docstring)."""


@dataclass(frozen=True)
class DriveWaveform:
    """Trapezoidal actuation pulse and the sensing switch-over, SI units.

    Parameters
    ----------
    amplitude_v : float
        Jetting pulse amplitude, V (ok_signal uses a fraction of it).
    rise_s, dwell_s, fall_s : float
        Ramp-up, flat top and ramp-down durations, s.
    switch_delay_s : float
        Delay between the end of the pulse and the first sensed sample, s.
    """

    amplitude_v: float = 20.0
    rise_s: float = 0.6e-6
    dwell_s: float = 1.6e-6
    fall_s: float = 0.6e-6
    switch_delay_s: float = 1.0e-6

    def __post_init__(self):
        for f in fields(self):
            v = getattr(self, f.name)
            if not (isinstance(v, numbers.Real) and math.isfinite(v) and v > 0):
                raise ValueError(f"drive.{f.name} must be a positive finite number, got {v!r}")

    @property
    def end_s(self) -> float:
        """End of the pulse, s after its start."""
        return self.rise_s + self.dwell_s + self.fall_s

    @property
    def window_start_s(self) -> float:
        """Time of the first sensed sample, s after the pulse start."""
        return self.end_s + self.switch_delay_s

    def u(self, t):
        """Drive voltage at times ``t`` (s) for unit amplitude (array in, array out)."""
        t = np.asarray(t, dtype=float)
        t1, t2, t3 = self.rise_s, self.rise_s + self.dwell_s, self.end_s
        return np.interp(t, [0.0, t1, t2, t3], [0.0, 1.0, 1.0, 0.0], left=0.0, right=0.0)


@dataclass(frozen=True)
class Spreads:
    """Per-trace physical variation (relative values are standard deviations).

    The defaults are the calibrated ones (thesis-like 12-class accuracy of a
    Random Forest on the 7 KPIs, see ``scripts/reports/sim.py``).
    ``Spreads.none()`` switches everything off except the class severity.

    Parameters
    ----------
    temperature_std_k : float
        Ink temperature spread around 30 C, K (viscosity follows, -3 %/K).
    nozzle_radius_rel, nozzle_length_rel, restrictor_radius_rel : float
        Geometry tolerances, relative.
    actuator_compliance_rel, coupling_rel : float
        Piezo tolerances on ``B_act`` and ``b``, relative.
    drive_rel : float
        Drive amplitude tolerance, relative.
    gain_rel : float
        Sense-amplifier gain tolerance, relative.
    offset_std_v : float
        Sense-amplifier offset spread, V.
    snr_db : float
        SNR of the nominal healthy (jetting) trace: RMS of its window over the
        noise standard deviation, dB. ``inf`` = no noise.
    adc_bits : int or None
        ADC resolution; ``None`` = no quantisation.
    adc_range_v : float
        ADC input range is +-adc_range_v, V (values beyond are clipped).
    actuator_resonance_rel, actuator_damping_rel, film_loss_rel : float
        Spread (log-normal, relative) of the empty channel's physics: the unloaded
        actuator's resonance and damping ratio and the ink film's loss factor
        (:data:`PHYSICAL_CONSTANTS`). Healthy traces do not show them, so a head
        calibrated from healthy traces trains over a range of them instead of the
        default head's values (:mod:`inkdiag_core.calibration`). Default 0: the
        constants as they are, and no draws (the default head's results do not change).
    """

    temperature_std_k: float = 1.5
    nozzle_radius_rel: float = 0.01
    nozzle_length_rel: float = 0.02
    restrictor_radius_rel: float = 0.01
    actuator_compliance_rel: float = 0.03
    coupling_rel: float = 0.03
    drive_rel: float = 0.01
    gain_rel: float = 0.05
    offset_std_v: float = 0.01
    snr_db: float = 30.0
    adc_bits: int | None = 12
    adc_range_v: float = 2.0
    actuator_resonance_rel: float = 0.0
    actuator_damping_rel: float = 0.0
    film_loss_rel: float = 0.0

    @classmethod
    def none(cls) -> "Spreads":
        """No variation, no noise, no quantisation: nominal channels at each severity."""
        return cls(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, math.inf, None, 2.0)

    def __post_init__(self):
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name == "adc_bits":
                if v is not None and not (isinstance(v, numbers.Integral) and 1 <= v <= 32):
                    raise ValueError(f"spreads.adc_bits must be None or an int 1..32, got {v!r}")
                continue
            if not isinstance(v, numbers.Real) or math.isnan(v) or v < 0:
                raise ValueError(f"spreads.{f.name} must be a number >= 0, got {v!r}")
        if not self.adc_range_v > 0:
            raise ValueError(f"spreads.adc_range_v must be > 0, got {self.adc_range_v!r}")


@dataclass(frozen=True)
class ChannelDraw:
    """Every trace's drawn channel: model coefficients and physical values.

    All arrays have shape (n,), one entry per trace, in the rows' order.

    Attributes
    ----------
    k_r, k_n : ndarray
        ``1 / (I_r B_t)`` and ``1 / (I_n B_t)``, 1/s^2 (0 for a closed branch).
    d_r, d_n : ndarray
        ``R_r / I_r`` and ``R_n / I_n``, 1/s.
    b_r, b_n : ndarray
        Input coefficients ``b k_r`` and ``b k_n``, m^3/(V s^2).
    drive : ndarray
        Relative drive amplitude (tolerance times the class's drive factor), 1.
    fm : ndarray
        Appendix F fault ``-alpha (mu_nozzle - mu)`` (dried classes only), 1/s.
    mu, mu_nozzle : ndarray
        Ink viscosity in the channel and in the nozzle, Pa s.
    kinds : ndarray of str
        The class's mechanism kind (``MECHANISMS[cls].kind``).
    params : dict of str -> ndarray, shape (n,)
        Per-trace physical values (SI), as :attr:`SimulationResult.params`;
        ``drive_v`` is ``None`` here (the caller knows the amplitude).
    """

    k_r: np.ndarray
    k_n: np.ndarray
    d_r: np.ndarray
    d_n: np.ndarray
    b_r: np.ndarray
    b_n: np.ndarray
    drive: np.ndarray
    fm: np.ndarray
    mu: np.ndarray
    mu_nozzle: np.ndarray
    kinds: np.ndarray
    params: dict = field(default_factory=dict)


# ---------------------------------------------------------------------------
# physics: per-trace model coefficients


def andrade_viscosity(mu_ref, temperature_k):
    """Viscosity (Pa s) at ``temperature_k`` (K) of an ink of viscosity ``mu_ref`` at 30 C (Andrade)."""
    c = PHYSICAL_CONSTANTS
    return mu_ref * np.exp(c["andrade_b_k"] * (1.0 / temperature_k - 1.0 / c["T_ref_k"]))


def bubble_compliance(r_b):
    """Compliance (m^3/Pa) of a gas bubble of radius r_b (m) with surface tension."""
    c = PHYSICAL_CONSTANTS
    V = 4.0 / 3.0 * np.pi * r_b**3
    p_g = c["p0_pa"] + 2.0 * c["sigma_n_per_m"] / r_b
    return V / (c["kappa_gas"] * p_g - 2.0 * c["sigma_n_per_m"] / (3.0 * r_b))


def draw_channels(classes, base: InkChannelParams, spreads: Spreads, rng, severity_override=None,
                   frame_rng=None, perm=None):
    """Draw every trace's physical parameters and build its model coefficients.

    Parameters
    ----------
    classes : list of (FaultClass, int)
        Classes and their trace counts, rows grouped in this order (n rows in all).
    base : InkChannelParams
        Nominal channel.
    spreads : Spreads
    rng : numpy.random.Generator
        Stream of the per-trace draws.
    severity_override : dict of FaultClass -> ndarray, optional
        Fixed severities (checked by the caller), one per trace of that class.
    frame_rng : numpy.random.Generator, optional
        Draws the ink temperature (default ``rng``).
    perm : ndarray of int, shape (n,), optional
        Maps rows to the positions of ``rng``'s draws: row ``r`` gets draw
        ``perm[r]`` of every per-trace quantity (default identity).

    Returns
    -------
    ChannelDraw
        Coefficients and physical values, (n,) arrays.
    """
    n = sum(k for _, k in classes)
    kind_idx = np.concatenate([np.full(k, i) for i, (_, k) in enumerate(classes)])
    mech = [MECHANISMS[c] for c, _ in classes]

    def per_row(a):
        return a if perm is None else a[perm]

    def lognormal(rel):
        return per_row(np.exp(rel * rng.standard_normal(n))) if rel > 0 else np.ones(n)

    # one fixed order of draws, independent of the classes
    temperature = PHYSICAL_CONSTANTS["T_ref_k"] + spreads.temperature_std_k * rng.standard_normal(n)
    if frame_rng is not None and frame_rng is not rng:
        temperature = PHYSICAL_CONSTANTS["T_ref_k"] + spreads.temperature_std_k * frame_rng.standard_normal(n)
    else:
        temperature = per_row(temperature)
    r_n = base.r_n * lognormal(spreads.nozzle_radius_rel)
    L_n = base.L_n * lognormal(spreads.nozzle_length_rel)
    r_r = base.r_r * lognormal(spreads.restrictor_radius_rel)
    B_act = base.B_act * lognormal(spreads.actuator_compliance_rel)
    b = base.b * lognormal(spreads.coupling_rel)
    drive = lognormal(spreads.drive_rel)
    u01 = per_row(rng.random(n))
    # the empty channel's actuator physics, drawn only when its spreads are set
    f_act_factor = lognormal(spreads.actuator_resonance_rel)
    zeta_act_factor = lognormal(spreads.actuator_damping_rel)
    film_factor = lognormal(spreads.film_loss_rel)

    lo = np.array([m.low for m in mech])[kind_idx]
    hi = np.array([m.high for m in mech])[kind_idx]
    severity = lo + (hi - lo) * u01
    if severity_override:
        start = 0
        for cls, k in classes:
            if cls in severity_override:
                severity[start:start + k] = severity_override[cls]
            start += k
    drive = drive * np.array([m.drive_factor for m in mech])[kind_idx]
    kinds = np.array([m.kind for m in mech])[kind_idx]
    has_sev = np.array([bool(m.severity) for m in mech])[kind_idx]

    rho = np.full(n, base.rho)
    mu = andrade_viscosity(base.mu, temperature)
    mu_nozzle = mu.copy()
    L_r = np.full(n, base.L_r)
    B_extra = np.full(n, base.B_extra)

    dried = kinds == "dried"
    mu_nozzle[dried] *= severity[dried]
    bubble = kinds == "chamber_bubble"
    B_extra[bubble] += bubble_compliance(severity[bubble])

    # ink column in the nozzle bore (a nozzle bubble cuts it short)
    col = np.where(kinds == "nozzle_bubble", (1.0 - severity) * L_n, L_n)
    I_n = rho * (col + np.pi * r_n / 4.0) / (np.pi * r_n**2)
    R_n = 8.0 * mu_nozzle * col / (np.pi * r_n**4)

    # particle of radius a = severity * r_n over a length PARTICLE_LENGTH_FRACTION * L_n:
    # that stretch of the bore is a concentric annulus (Poiseuille flow in an annulus)
    part = kinds == "particle"
    if part.any():
        ell = PARTICLE_LENGTH_FRACTION * L_n[part]
        r, a = r_n[part], severity[part] * r_n[part]
        area = np.pi * (r**2 - a**2)
        r_ann = 8.0 * mu_nozzle[part] * ell / (
            np.pi * (r**4 - a**4 - (r**2 - a**2) ** 2 / np.log(r / a))
        )
        free = L_n[part] - ell
        I_n[part] = rho[part] * ((free + np.pi * r / 4.0) / (np.pi * r**2) + ell / area)
        R_n[part] = 8.0 * mu_nozzle[part] * free / (np.pi * r**4) + r_ann
    I_r = rho * L_r / (np.pi * r_r**2)
    R_r = 8.0 * mu * L_r / (np.pi * r_r**4)
    B_t = B_act + base.V_ch / (rho * base.c**2) + B_extra

    k_r = 1.0 / (I_r * B_t)
    k_n = 1.0 / (I_n * B_t)
    d_r = R_r / I_r
    d_n = R_n / I_n
    b_r = b * k_r
    b_n = b * k_n

    # fully blocked: nozzle branch carries no flow (its row keeps its own decay
    # rate so that A stays non-singular; x3 stays 0)
    blocked = kinds == "blocked"
    k_n[blocked] = 0.0
    b_n[blocked] = 0.0
    I_n = np.where(blocked, np.inf, I_n)

    # empty channel: no ink in restrictor/chamber/nozzle; the actuator's own
    # structural resonance, mass-loaded by an ink film of mass ratio m
    empty = kinds == "empty"
    if empty.any():
        c = PHYSICAL_CONSTANTS
        # the actuator's modal inertance: the head's own resonance at its B_act, else the default head's
        f_act, b_ref = ((base.f_act, base.B_act) if base.f_act is not None else (c["f_act_hz"], c["f_act_ref_b_act"]))
        zeta_act = c["zeta_act"] if base.zeta_act is None else base.zeta_act
        I_act = 1.0 / ((2 * np.pi * f_act * f_act_factor[empty]) ** 2 * b_ref)
        R_act0 = 2.0 * zeta_act * zeta_act_factor[empty] * np.sqrt(I_act / base.B_act)
        m = severity[empty]
        I_e = I_act * (1.0 + m)
        R_e = R_act0 * (1.0 + c["film_loss_factor"] * film_factor[empty] * m * mu[empty] / base.mu)
        k_r[empty] = 0.0
        b_r[empty] = 0.0
        k_n[empty] = 1.0 / (I_e * B_act[empty])
        d_n[empty] = R_e / I_e
        b_n[empty] = b[empty] * k_n[empty]
        B_t = np.where(empty, B_act, B_t)
        I_n[empty] = I_e
        R_n[empty] = R_e
        I_r = np.where(empty, np.inf, I_r)
        R_r = np.where(empty, np.nan, R_r)

    alpha = 8.0 * L_n / (rho * (L_n + np.pi * r_n / 4.0) * r_n**2)
    fm = np.where(dried, -alpha * (mu_nozzle - mu), 0.0)

    return ChannelDraw(
        k_r=k_r, k_n=k_n, d_r=d_r, d_n=d_n, b_r=b_r, b_n=b_n,
        drive=drive, fm=fm, mu=mu, mu_nozzle=mu_nozzle, kinds=kinds,
        params={
            "temperature_k": temperature, "drive_v": None, "rho": rho, "r_n": r_n,
            "L_n": L_n, "r_r": r_r, "L_r": L_r, "B_act": B_act, "b": b, "B_t": B_t,
            "I_n": I_n, "I_r": I_r, "R_n": R_n, "R_r": R_r,
            "severity": np.where(has_sev, severity, np.nan),
        },
    )


def observable_A(k_r, k_n, d_r, d_n):
    """Observable-form matrices (n, 3, 3) of eq. 12 from (n,) coefficients (1/s^2, 1/s)."""
    n = k_r.shape[0]
    A = np.zeros((n, 3, 3))
    A[:, 0, 1] = 1.0
    A[:, 0, 2] = 1.0
    A[:, 1, 0] = -k_r
    A[:, 1, 1] = -d_r
    A[:, 2, 0] = -k_n
    A[:, 2, 2] = -d_n
    return A
