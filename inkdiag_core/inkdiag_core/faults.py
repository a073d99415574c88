"""The 12 nozzle conditions of the thesis (Appendix A, Table 9) and their physics.

Every class is one physical mechanism acting on the ink-channel model of
:mod:`inkdiag_core.model` (the faults are *multiplicative*: they change the
model's parameters, never add a signal). The frequencies of the classes come
out of the model, they are not looked up; :data:`MECHANISMS` holds, per class,
the severity variable and its range, which the simulator draws uniformly.
The ranges were calibrated so that every class's mean dominant frequency matches
Table 3 within 3 % under two measures (``scripts/reports/sim.py`` prints both): the
damped frequency of the trace's fit (``extract_kpis``) and the thesis's own, the
peak of the zero-padded FFT of the mean-removed trace. For a lightly damped class
the two agree; for a damped one (damping ratio 0.2-0.25: partially blocked and the
dried classes) the spectral peak reads 2-3 % above the damped frequency, so the
severity range of such a class is placed where Table 3 lies between the two.

Mechanisms (nominal channel: 237 kHz, zeta 0.074)
--------------------------------------------------
ok_signal, healthy_nozzle
    Both are healthy channels; they differ in the operating condition under
    which the trace was taken. ``healthy_nozzle`` is sensed after the normal
    jetting pulse; ``ok_signal`` after the printhead's reduced-amplitude
    "OK-check" pulse (a non-jetting pulse at :data:`OK_SIGNAL_DRIVE_FACTOR` of
    the jetting voltage), so its residual oscillation is smaller. With the
    per-channel drive, coupling and sense-gain tolerances the two amplitude
    distributions overlap partly, as in the thesis's confusion matrices.
empty_channel_1, empty_channel_2
    No ink in the chamber: nothing loads the actuator but its own structure,
    and the self-sensing signal is the actuator's structural resonance
    ``f_act = 1 / (2 pi sqrt(I_act B_act))`` (a separate, lightly damped
    second-order mode; ``I_act`` is the actuator's modal mass expressed as an
    acoustic inertance). ``empty_channel_1`` is fully empty (a trace of ink
    film, mass ratio 0-0.1). ``empty_channel_2`` is partially emptied: a
    residual ink film on the actuator adds mass (ratio ``m`` 1.1-1.6, so
    ``f = f_act / sqrt(1 + m)``) and viscous loss.
mature_air_bubble, intermediate_air_bubble
    A bubble sucked in through the nozzle sits in the nozzle bore, a fraction
    ``phi`` of the bore's length in from the outlet (``(1 - phi) L_n`` from the
    chamber). Its gas is far softer than the ink (``B_b = V_b / (kappa p_g)``
    is tens of times ``B_t``), so at the channel's resonance it is a pressure
    release: only the ink column between the chamber and the bubble, length
    ``(1 - phi) L_n``, still moves with the chamber. The nozzle branch's inertance and resistance shrink to
    that column (``I_n -> rho ((1 - phi) L_n + pi r_n / 4) / (pi r_n^2)``,
    ``R_n -> (1 - phi) R_n``) and the resonance rises (330-360 kHz). The
    ink beyond the bubble and the bubble's spring form a separate, slow
    (< 80 kHz), weakly driven mode that the 3-state model leaves out.
    A mature bubble has grown closer to the chamber (larger ``phi``: 0.82-0.91
    against 0.72-0.82).
small_air_bubble
    A small free bubble of radius ``r_b`` in the chamber adds the gas
    compliance ``B_b = V_b / (kappa p_g - 2 sigma / (3 r_b))`` with
    ``p_g = p0 + 2 sigma / r_b`` (polytropic gas with surface tension) to
    ``B_t``: the resonance drops (about 190 kHz) but the damping of the necks
    is unchanged, which is what separates it from a deeply dried nozzle at the
    same frequency.
fully_blocked
    The nozzle is closed (dried plug or particle): ``V_n' = 0`` and only the
    restrictor branch resonates with the chamber,
    ``f = sqrt(1 / (I_r B_t)) / 2 pi`` (about 167 kHz).
partially_blocked
    A particle (pigment agglomerate, dust) of radius ``a = beta r_n`` is
    lodged in the bore over a length ``PARTICLE_LENGTH_FRACTION * L_n``. That
    stretch becomes a concentric annulus: its inertance is
    ``rho l / (pi (r_n^2 - a^2))`` and its Poiseuille resistance
    ``8 mu l / (pi (r^4 - a^4 - (r^2 - a^2)^2 / ln(r / a)))`` grows much
    faster than the inertance as the gap closes (``beta`` 0.58-0.68: the
    particle leaves a gap of 32-42 % of the bore radius; as ``beta`` grows
    towards 1 the channel tends to ``fully_blocked``). The result is a lower
    frequency (about 198-199 kHz damped, 202-204 kHz as the zero-padded FFT
    peak) with a damping
    close to that of a dried nozzle, so the class overlaps the drying classes
    partly (the thesis's weakest class, Table 10).
slightly_dried, intermediately_dried, deeply_dried
    Evaporation at the meniscus thickens the ink in the nozzle: the nozzle
    viscosity is the channel's ink viscosity times a factor ``k`` (ranges
    2.4-4.2, 4.2-5.4, 6.0-9.6). Only ``R_n`` changes,
    ``f_m = -alpha (mu_nozzle - mu)`` (Appendix F). Slight drying starts at
    ``k = 2.4``, where the damped frequency has dropped about 3 % below a
    healthy nozzle's and the damping ratio has about doubled (0.14 against
    0.075); with the former lower bound 1.6 the class mean read 2.7 % above
    Table 3 as the zero-padded FFT peak, i.e. the thesis's slightly dried
    nozzles are drier than that. The three ranges are placed so that Table 3
    lies between the class's mean damped frequency and its mean FFT peak.

Severity ranges of neighbouring classes touch or leave a gap, but never overlap
(slightly / intermediately dried touch at k = 4.2, intermediately / deeply dried
leave 5.4-6.0; intermediate / mature bubble touch at phi = 0.82):
drying and bubble growth are continuous, but a class is a range of the
physical state, so a classifier that knew the true state could always name
the class. What makes classes hard to tell apart is the physical spread of
every trace (ink temperature, geometry and piezo tolerances, sensor gain and
offset, noise, quantisation; see ``simulator.Spreads``), never the labels.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np

__all__ = [
    "FaultClass",
    "Mechanism",
    "MECHANISMS",
    "HEALTHY_CLASSES",
    "HEALTHY_VALUES",
    "DRIED_CLASSES",
    "DRIED_VALUES",
    "FAULT_CLASSES",
    "FAULT_VALUES",
    "OK_SIGNAL_DRIVE_FACTOR",
    "PARTICLE_LENGTH_FRACTION",
    "is_healthy",
    "is_dried",
    "class_values",
    "healthy_mask",
    "dried_mask",
    "as_fault_class",
]


class FaultClass(enum.Enum):
    """The 12 classes of thesis Table 9; ``.value`` is a stable snake_case string."""

    OK_SIGNAL = "ok_signal"
    HEALTHY_NOZZLE = "healthy_nozzle"
    EMPTY_CHANNEL_1 = "empty_channel_1"
    EMPTY_CHANNEL_2 = "empty_channel_2"
    MATURE_AIR_BUBBLE = "mature_air_bubble"
    INTERMEDIATE_AIR_BUBBLE = "intermediate_air_bubble"
    SMALL_AIR_BUBBLE = "small_air_bubble"
    FULLY_BLOCKED = "fully_blocked"
    PARTIALLY_BLOCKED = "partially_blocked"
    SLIGHTLY_DRIED = "slightly_dried"
    INTERMEDIATELY_DRIED = "intermediately_dried"
    DEEPLY_DRIED = "deeply_dried"

    def __str__(self) -> str:
        return self.value


# Class groups: defined here once. The rest of the core, inkdiag_ros and scripts/ use these;
# msg_defs (which must not import the core) keeps a wire copy of the value tuples
# (msg_defs.HEALTHY_CLASSES, msg_defs.DRIED_CLASSES), pinned to these by tests/core/test_vocabulary.py.

HEALTHY_CLASSES = frozenset({FaultClass.OK_SIGNAL, FaultClass.HEALTHY_NOZZLE})
"""The two healthy operating conditions (negative class of fault detection)."""

HEALTHY_VALUES = tuple(c.value for c in FaultClass if c in HEALTHY_CLASSES)
"""``HEALTHY_CLASSES`` as value strings, in :class:`FaultClass` order: ``("ok_signal", "healthy_nozzle")``."""

DRIED_CLASSES = (
    FaultClass.SLIGHTLY_DRIED,
    FaultClass.INTERMEDIATELY_DRIED,
    FaultClass.DEEPLY_DRIED,
)
"""Drying classes, in increasing severity (the fault-estimation classes)."""

DRIED_VALUES = tuple(c.value for c in DRIED_CLASSES)
"""``DRIED_CLASSES`` as value strings, in increasing severity."""

FAULT_CLASSES = tuple(c for c in FaultClass if c not in HEALTHY_CLASSES)
"""The 10 fault classes (every class but the healthy ones), in :class:`FaultClass` order."""

FAULT_VALUES = tuple(c.value for c in FAULT_CLASSES)
"""``FAULT_CLASSES`` as value strings."""

PARTICLE_LENGTH_FRACTION = 0.3
"""Length of the bore occupied by a partially blocking particle, fraction of L_n."""

OK_SIGNAL_DRIVE_FACTOR = 0.8
"""Drive amplitude of the OK-check pulse relative to the jetting pulse (ok_signal)."""


def is_healthy(cls) -> bool:
    """True for ``ok_signal`` and ``healthy_nozzle`` (accepts a FaultClass or its value)."""
    return as_fault_class(cls) in HEALTHY_CLASSES


def is_dried(cls) -> bool:
    """True for the three drying classes (accepts a FaultClass or its value)."""
    return as_fault_class(cls) in DRIED_CLASSES


def class_values(labels) -> np.ndarray:
    """Labels as value strings: FaultClass members become ``.value``, anything else is kept.

    Parameters
    ----------
    labels : array_like, shape (n,)
        FaultClass members and/or strings (or any other objects).

    Returns
    -------
    ndarray of object, shape (n,)
    """
    arr = np.asarray(labels)
    if arr.dtype.kind in "US":  # already strings: no per-label Python step
        return arr.astype(object).reshape(-1)
    arr = arr.astype(object).reshape(-1)
    return np.array([getattr(c, "value", c) for c in arr.tolist()], dtype=object)


def healthy_mask(labels) -> np.ndarray:
    """Boolean mask (n,) of the labels in :data:`HEALTHY_CLASSES` (members or value strings).

    Anything else (fault classes, unknown strings, ``""``, numbers) is False.
    """
    return np.isin(class_values(labels), HEALTHY_VALUES)


def dried_mask(labels) -> np.ndarray:
    """Boolean mask (n,) of the labels in :data:`DRIED_CLASSES` (members or value strings)."""
    return np.isin(class_values(labels), DRIED_VALUES)


def as_fault_class(cls, name: str = "fault class") -> FaultClass:
    """Return ``cls`` as a :class:`FaultClass`; accepts members and their string values.

    Raises
    ------
    ValueError
        If ``cls`` is neither; the message names ``name`` and lists the valid values.
    """
    if isinstance(cls, FaultClass):
        return cls
    if isinstance(cls, str):
        try:
            return FaultClass(cls)
        except ValueError:
            pass
    valid = ", ".join(c.value for c in FaultClass)
    raise ValueError(f"{name}: unknown fault class {cls!r}; expected one of: {valid}")


@dataclass(frozen=True)
class Mechanism:
    """How one class changes the ink-channel model.

    Attributes
    ----------
    kind : str
        ``"healthy"``, ``"empty"``, ``"nozzle_bubble"``, ``"chamber_bubble"``,
        ``"blocked"``, ``"particle"`` or ``"dried"``.
    severity : str
        Name and unit of the severity variable (empty string if none).
    low, high : float
        Range of the severity variable, drawn uniformly per trace.
    drive_factor : float
        Drive amplitude relative to the jetting pulse.
    description : str
        One line of physics.
    """

    kind: str
    severity: str
    low: float
    high: float
    drive_factor: float
    description: str


MECHANISMS = {
    FaultClass.OK_SIGNAL: Mechanism(
        "healthy", "", 0.0, 0.0, OK_SIGNAL_DRIVE_FACTOR,
        "healthy channel sensed after the reduced-amplitude OK-check pulse"),
    FaultClass.HEALTHY_NOZZLE: Mechanism(
        "healthy", "", 0.0, 0.0, 1.0,
        "healthy channel sensed after the jetting pulse"),
    FaultClass.EMPTY_CHANNEL_1: Mechanism(
        "empty", "ink-film mass ratio m (-)", 0.0, 0.10, 1.0,
        "no ink: actuator structural resonance f_act / sqrt(1 + m)"),
    FaultClass.EMPTY_CHANNEL_2: Mechanism(
        "empty", "ink-film mass ratio m (-)", 1.1, 1.6, 1.0,
        "partially empty: residual ink film mass-loads the actuator"),
    FaultClass.MATURE_AIR_BUBBLE: Mechanism(
        "nozzle_bubble", "bubble position phi (fraction of L_n in from the outlet)", 0.82, 0.91, 1.0,
        "bubble in the nozzle bore decouples the outer ink column"),
    FaultClass.INTERMEDIATE_AIR_BUBBLE: Mechanism(
        "nozzle_bubble", "bubble position phi (fraction of L_n in from the outlet)", 0.72, 0.82, 1.0,
        "smaller/less advanced nozzle bubble"),
    FaultClass.SMALL_AIR_BUBBLE: Mechanism(
        "chamber_bubble", "bubble radius r_b (m)", 4.6e-6, 6.0e-6, 1.0,
        "free gas bubble in the chamber adds compliance to B_t"),
    FaultClass.FULLY_BLOCKED: Mechanism(
        "blocked", "", 0.0, 0.0, 1.0,
        "nozzle closed: restrictor-only resonance"),
    FaultClass.PARTIALLY_BLOCKED: Mechanism(
        "particle", "particle radius ratio beta = a / r_n (-)", 0.58, 0.68, 1.0,
        "particle lodged in the bore: annular gap adds resistance and inertance"),
    FaultClass.SLIGHTLY_DRIED: Mechanism(
        "dried", "nozzle viscosity factor k (-)", 2.4, 4.2, 1.0,
        "nozzle ink viscosity mu_nozzle = k mu"),
    FaultClass.INTERMEDIATELY_DRIED: Mechanism(
        "dried", "nozzle viscosity factor k (-)", 4.2, 5.4, 1.0,
        "nozzle ink viscosity mu_nozzle = k mu"),
    FaultClass.DEEPLY_DRIED: Mechanism(
        "dried", "nozzle viscosity factor k (-)", 6.0, 9.6, 1.0,
        "nozzle ink viscosity mu_nozzle = k mu"),
}
"""Per-class :class:`Mechanism` (severity ranges are calibrated against Table 3)."""
