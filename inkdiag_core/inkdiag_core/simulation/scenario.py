"""The simulated printhead's fault scenario (pure Python, no ROS).

:class:`HeadScenario` says, for a time ``t`` since the start, which class each
nozzle has and, for drying nozzles, their nozzle ink viscosity. The physics
call that turns that into traces is :func:`simulate_head`, the one place
where the simulator is called.

Both take the head as a :class:`inkdiag_core.HeadProfile` (keyword
``profile``; default: the shipped default head, whose frames are
bit-identical to those of the scenario before profiles): its channel, drive,
sampling, sensor gain and offset, noise, ADC and spreads. The one keyword
stands for the six the simulator would otherwise need threaded through.
"""

from __future__ import annotations

import math

import numpy as np

from ..faults import DRIED_CLASSES, FAULT_CLASSES, MECHANISMS, FaultClass, as_fault_class
from .linear import simulate_nozzles

__all__ = ["HeadScenario", "simulate_head", "dried_class_of", "defaults_on_head", "RANDOM_FAULT_CLASSES"]

#: Classes a random fault is drawn from (drying is the progression's job).
RANDOM_FAULT_CLASSES = tuple(c for c in FAULT_CLASSES if c not in DRIED_CLASSES)


def _complete_profile(profile, what):
    """``profile``, or the shipped default head; refuse a nominal one (a clear ProfileError)."""
    from ..head_profile import HeadProfile, ProfileError  # the profile module imports the simulators

    if profile is None:
        return HeadProfile.default()
    if not isinstance(profile, HeadProfile):
        raise TypeError(f"profile must be a HeadProfile (or None: the default head), got {type(profile).__name__}")
    if not profile.is_complete:
        raise ProfileError(f"profile {profile.name!r} is nominal ({', '.join(profile.missing)} missing): {what} "
                           "needs a complete profile (run `inkdiag calibrate` on recorded healthy traces)")
    return profile


def dried_class_of(k: np.ndarray) -> np.ndarray:
    """Drying class of nozzle viscosity factors ``k`` (object array of FaultClass).

    Boundaries are the midpoints where the class ranges of ``MECHANISMS`` touch.
    """
    s, i, d = DRIED_CLASSES
    lo_i = 0.5 * (MECHANISMS[s].high + MECHANISMS[i].low)
    lo_d = 0.5 * (MECHANISMS[i].high + MECHANISMS[d].low)
    k = np.asarray(k, dtype=float)
    return np.where(k < lo_i, s, np.where(k < lo_d, i, d)).astype(object)


#: Samples one simulated frame holds at most (``n_nozzles x n_samples``): 512 MiB of float32, about three times
#: that at its peak while it is simulated (20,000 nozzles x 512 samples: 41 MB, 125 MB more at the peak).
MAX_FRAME_SAMPLES = 2**27


class HeadScenario:
    """Faults of a simulated head over time.

    Parameters
    ----------
    n_nozzles, first_nozzle : int
    fault_nozzles : sequence of int
        Nozzle ids with a fixed fault, and ``fault_classes`` their class values.
    random_fault_fraction : float
        Fraction of the other nozzles given a random (non-drying) fault, fixed for the run.
    drying_nozzles : sequence of int
        Nozzles that dry: their nozzle viscosity factor goes linearly from
        ``drying_start_factor`` to ``drying_end_factor`` over ``drying_duration_s``, then holds
        (factors of the profile's ink viscosity ``channel["mu"]``).
    faults_start_s : float
        Every nozzle is healthy before this time (a purged head, whose baselines
        can be recorded); the faults appear and the drying starts then.
    seed : int
    profile : HeadProfile, optional
        The simulated head (default: the shipped default head); a complete
        profile (a nominal one raises :class:`inkdiag_core.ProfileError`). Its
        ink viscosity scales the drying nozzles' factors; :meth:`frame` simulates on it.
    """

    def __init__(self, *, n_nozzles, first_nozzle=0, fault_nozzles=(), fault_classes=(),
                 random_fault_fraction=0.0, drying_nozzles=(), drying_start_factor=2.4,
                 drying_end_factor=9.0, drying_duration_s=20.0, faults_start_s=0.0, seed=0, profile=None):
        self.profile = _complete_profile(profile, "the simulated head")
        if n_nozzles * self.profile.n_samples > MAX_FRAME_SAMPLES:  # one frame's arrays would not fit in memory
            raise ValueError(f"a frame of {n_nozzles} nozzles x {self.profile.n_samples} samples is more than "
                             f"{MAX_FRAME_SAMPLES:,} samples ({4 * MAX_FRAME_SAMPLES / 2**30:g} GiB of float32): "
                             "simulate the head as several heads of fewer nozzles (first_nozzle)")
        ids = np.arange(first_nozzle, first_nozzle + n_nozzles)
        fault_nozzles = [int(x) for x in fault_nozzles]
        drying_nozzles = [int(x) for x in drying_nozzles]
        if len(fault_nozzles) != len(fault_classes):
            raise ValueError(f"fault_nozzles ({len(fault_nozzles)}) and fault_classes "
                             f"({len(fault_classes)}) must have the same length")
        for name, lst in (("fault_nozzles", fault_nozzles), ("drying_nozzles", drying_nozzles)):
            out = [x for x in lst if not first_nozzle <= x < first_nozzle + n_nozzles]
            if out:
                raise ValueError(f"{name} {out} outside this head's nozzles "
                                 f"{first_nozzle}..{first_nozzle + n_nozzles - 1}")
            twice = sorted({x for x in lst if lst.count(x) > 1})
            if twice:  # the later entry would silently win (a nozzle has one condition)
                raise ValueError(f"{name} lists {twice} more than once: give each nozzle once")
        if set(fault_nozzles) & set(drying_nozzles):
            raise ValueError(f"nozzles both faulty and drying: {sorted(set(fault_nozzles) & set(drying_nozzles))}")
        if not (math.isfinite(faults_start_s) and faults_start_s >= 0.0):
            raise ValueError(f"faults_start_s must be finite and >= 0, got {faults_start_s}")
        if not 0.0 <= random_fault_fraction <= 1.0:
            raise ValueError(f"random_fault_fraction must be in [0, 1], got {random_fault_fraction}")
        if not (1.0 <= drying_start_factor <= drying_end_factor and drying_duration_s > 0):
            raise ValueError("need 1 <= drying_start_factor <= drying_end_factor and drying_duration_s > 0")
        self.first_nozzle = int(first_nozzle)
        self.n_nozzles = int(n_nozzles)
        self.classes = np.full(n_nozzles, FaultClass.HEALTHY_NOZZLE, dtype=object)
        for nz, c in zip(fault_nozzles, fault_classes):
            self.classes[nz - first_nozzle] = as_fault_class(c, "fault_classes")
        rng = np.random.default_rng(seed)
        free = np.setdiff1d(ids, fault_nozzles + drying_nozzles) - first_nozzle
        k = int(round(random_fault_fraction * free.size))
        pick = rng.choice(free, size=k, replace=False)
        self.classes[pick] = np.asarray(RANDOM_FAULT_CLASSES, dtype=object)[
            rng.integers(len(RANDOM_FAULT_CLASSES), size=k)]
        self.drying_rows = np.asarray(drying_nozzles, dtype=np.int64) - first_nozzle
        self.k0, self.k1, self.duration_s = float(drying_start_factor), float(drying_end_factor), float(drying_duration_s)
        self.faults_start_s = float(faults_start_s)

    def viscosity_factor(self, t_s: float) -> float:
        """Nozzle viscosity factor of the drying nozzles at ``t_s`` (drying from ``faults_start_s``)."""
        return self.k0 + (self.k1 - self.k0) * min(max(t_s - self.faults_start_s, 0.0) / self.duration_s, 1.0)

    def at(self, t_s: float):
        """``(classes, mu_nozzle)`` at ``t_s``: FaultClass per row and (n,) Pa s (NaN = class spread)."""
        mu = np.full(self.n_nozzles, math.nan)
        if t_s < self.faults_start_s:
            return np.full(self.n_nozzles, FaultClass.HEALTHY_NOZZLE, dtype=object), mu
        classes = self.classes.copy()
        k = self.viscosity_factor(t_s)
        classes[self.drying_rows] = dried_class_of(np.full(self.drying_rows.size, k))
        mu[self.drying_rows] = k * self.profile.channel["mu"]
        return classes, mu

    def frame(self, t_s: float, *, head_seed, rng):
        """One frame of the head at ``t_s``: :meth:`at`, then :func:`simulate_head` on :attr:`profile`.

        Returns ``(traces float32 (n_nozzles, profile.n_samples) V, labels, fm 1/s, mu_nozzle Pa s)``.
        """
        classes, mu_nozzle = self.at(t_s)
        return simulate_head(classes, mu_nozzle, head_seed=head_seed, rng=rng, profile=self.profile)


def defaults_on_head(p: dict, given) -> list:
    """Leave out of ``p`` (:class:`HeadScenario`'s keyword arguments) the default fault and drying nozzles (of the
    lists whose names are not in ``given``) that are not on its head: a smaller one's, or one from another
    ``first_nozzle`` (``printhead_sim``'s defaults). Returns those left out. A list given is the scenario's own,
    checked by :class:`HeadScenario` (an id off the head: ValueError)."""
    on_head, off = range(p["first_nozzle"], p["first_nozzle"] + p["n_nozzles"]), []
    if not {"fault_nozzles", "fault_classes"} & given:
        off = [z for z in p["fault_nozzles"] if z not in on_head]
        kept = [(z, c) for z, c in zip(p["fault_nozzles"], p["fault_classes"]) if z in on_head]
        p["fault_nozzles"], p["fault_classes"] = [z for z, _ in kept], [c for _, c in kept]
    if "drying_nozzles" not in given:
        off += [z for z in p["drying_nozzles"] if z not in on_head]
        p["drying_nozzles"] = [z for z in p["drying_nozzles"] if z in on_head]
    return off


def simulate_head(classes, mu_nozzle, *, head_seed, rng, profile=None, sample_rate_hz=None, n_samples=None):
    """The one physics call of the simulated head: one frame.

    ``head_seed`` fixes the head's nozzles (each keeps its tolerances, sensor and
    fault severity from frame to frame); ``rng`` draws the frame's ink temperature
    and sensor noise.

    Parameters
    ----------
    classes : sequence of FaultClass (or their values), length n
        Each nozzle's condition.
    mu_nozzle : array_like, shape (n,)
        Nozzle ink viscosity of the dried nozzles, Pa s (NaN: the class's spread).
    head_seed : int, sequence of int or numpy.random.Generator
        The head's nozzles.
    rng : numpy.random.Generator
        The frame's ink temperature and sensor noise.
    profile : HeadProfile, optional
        The head: channel, drive, sampling, sensor gain and offset, noise, ADC
        and spreads (default: the shipped default head). A complete profile.
    sample_rate_hz : float, optional
        Instead of the profile's sample rate, Hz (the same head sampled otherwise).
    n_samples : int, optional
        Instead of the profile's samples per trace.

    Returns
    -------
    traces : ndarray of float32, shape (n, n_samples)
        V.
    labels : ndarray of str, shape (n,)
    fm : ndarray, shape (n,)
        True f_m, 1/s.
    mu_nozzle : ndarray, shape (n,)
        True nozzle ink viscosity, Pa s.

    Raises
    ------
    ProfileError
        A nominal profile, or sampling overrides the head cannot be sampled at.
    """
    profile = _complete_profile(profile, "the simulated head")
    if (sample_rate_hz is not None and sample_rate_hz != profile.sample_rate_hz) or \
            (n_samples is not None and n_samples != profile.n_samples):
        profile = profile.replace(**{k: v for k, v in (("sample_rate_hz", sample_rate_hz), ("n_samples", n_samples))
                                     if v is not None})
    r = simulate_nozzles(classes, mu_nozzle=mu_nozzle, sample_rate_hz=profile.sample_rate_hz,
                         n_samples=profile.n_samples, seed=head_seed, frame_seed=rng, spreads=profile.spreads(),
                         drive=profile.drive, base_params=profile.channel_params(),
                         sensor_gain_v_per_m3s=profile.sensor_gain_v_per_m3s,
                         sensor_offset_v=profile.sensor_offset_v)
    return r.traces, r.labels, r.fm, r.mu_nozzle
