"""An independent "foreign head" simulator: test data for issue 14 (any printhead).

Issue 14's evidence is checked on traces of a head *simulated independently of our
simulator's code*. This module is that independent source. It imports numpy, scipy and
PyYAML only: nothing from ``inkdiag_core`` (not even ``inkdiag_core.faults``, because
importing any ``inkdiag_core`` submodule runs the package ``__init__``, which loads
``inkdiag_core.simulation``). The 12 class names are the stable ``FaultClass`` value
strings; a ``FaultClass`` member is accepted wherever a class is (by its ``.value``);
``tests/core/test_foreign_head.py`` pins the names to ``FaultClass``.

Physics (the lumped model of ``inkdiag_core.model``'s docstring, written here anew)
---------------------------------------------------------------------------------------
One ink channel: a chamber of compliance ``B_t = B_act + V_ch / (rho c^2) + B_extra``
(m^3/Pa) between a restrictor and a nozzle, each an inertance ``I`` (kg/m^4) in series
with a Poiseuille resistance ``R`` (Pa s/m^3)::

    I_n = rho (L_n + pi r_n / 4) / (pi r_n^2)      R_n = 8 mu_n L_n / (pi r_n^4)
    I_r = rho L_r / (pi r_r^2)                     R_r = 8 mu L_r / (pi r_r^4)

The piezo (coupling ``b``, m^3/V) displaces ``b u`` into the chamber; with ``V_r``,
``V_n`` the volumes that left through the restrictor and the nozzle the chamber pressure
is ``p = (b u - V_r - V_n) / B_t`` and ``I dV'/dt = p - R V'`` in each branch. The state
is ``x = [V_r, V_n, V_r', V_n']`` and the sensed quantity ``y = V_r' + V_n'`` (m^3/s).

Numerical route (deliberately not our simulator's exact modal solution): the model is
made dimensionless (time in microseconds, volume in units of ``b`` x 1 V) and
propagated by matrix exponentials (batched scaling and squaring of a Taylor
polynomial), batched over the traces. The trapezoidal drive is
exact on each of its three linear segments through the augmented system
``d/dt [x, u, u'] = [[A, B, 0], [0, 0, 1], [0, 0, 0]] [x, u, u']``; the channel then
rings freely for ``switch_delay_s`` (the state the pulse left), and the sensing window is
stepped with the one-sample transition ``expm(A / fs)`` (in blocks of 32 samples). Sensed volts are
``gain * y + offset + white noise``, quantised and clipped by the ADC.

Faults (each a change of that one model; severity ranges are those of
``inkdiag_core.faults.MECHANISMS``, copied as numbers)
-------------------------------------------------------------------------------------
ok_signal / healthy_nozzle
    healthy channel, drive amplitude x 0.8 (the OK-check pulse) / x 1.
slightly / intermediately / deeply dried
    nozzle ink viscosity ``mu_n = k mu``, ``k`` in 2.4-4.2 / 4.2-5.4 / 6.0-9.6.
fully_blocked
    nozzle closed: ``V_n' = 0``, only the restrictor branch rings with the chamber.
partially_blocked
    a particle of radius ``a = beta r_n`` (``beta`` 0.58-0.68) fills 0.3 ``L_n`` of the
    bore; that stretch is a concentric annulus of inertance ``rho l / (pi (r^2 - a^2))``
    and resistance ``8 mu l / (pi (r^4 - a^4 - (r^2 - a^2)^2 / ln(r / a)))``.
small_air_bubble
    a gas bubble of radius ``r_b`` (4.6-6.0 um) in the chamber adds the compliance
    ``V_b / (kappa p_g - 2 sigma / (3 r_b))``, ``p_g = p0 + 2 sigma / r_b``.
intermediate / mature air bubble
    a bubble in the bore at the fraction ``phi`` (0.72-0.82 / 0.82-0.91) of ``L_n`` in from
    the outlet is a pressure release at the channel's resonance: only the inner ink
    column ``(1 - phi) L_n`` still moves with the chamber (``I_n``, ``R_n`` of that column).
empty_channel_1 / empty_channel_2
    no ink: the actuator's own structural resonance (``f_act``, damping ``zeta_act``, the
    head's own values in :data:`FOREIGN_PHYSICS`) mass-loaded by an ink film of mass
    ratio ``m`` (0-0.1 / 1.1-1.6): inertance ``I_act (1 + m)``, resistance
    ``R_act (1 + film_loss m mu / mu_ref)``, compliance ``B_act``.

Per-trace spreads (:data:`FOREIGN_SPREADS`): ink temperature (viscosity by Andrade's law),
nozzle radius and length, restrictor radius, actuator compliance and coupling, drive
amplitude, sense gain and offset; then white noise of the head's ``noise_std_v`` and the
ADC. None depends on the class. By default each row is its own nozzle; with ``nozzle_seed``
the spreads of :data:`NOZZLE_SPREADS` belong to the row's nozzle id and stay with it from one
recording to the next (a head's commissioning frames and its later faults).

Heads (:data:`FOREIGN_HEADS`; modes measured as the peak of the zero-padded FFT of a
noise-free healthy trace, see the test)
------------------------------------------------------------------------------------
``h20``
    1100 kg/m^3, 6 mPa s ink, 11 um x 45 um nozzle, 24 um x 200 um restrictor
    (``I_r ~ 0.78 I_n``), 20 MHz x 1024 samples, 28 V pulse; healthy mode about 169 kHz,
    damping ratio 0.08; fully blocked about 128 kHz, empty channels 0.99-1.6 MHz.
``h16``
    1060 kg/m^3, 7 mPa s ink, 12 um x 40 um nozzle, 26 um x 210 um restrictor
    (``I_r ~ 0.91 I_n``), 16 MHz x 768 samples, 25 V pulse; healthy mode about 174 kHz,
    damping ratio 0.08; fully blocked about 127 kHz, empty channels 1.0-1.6 MHz.
``h12``
    1080 kg/m^3, 5 mPa s ink, 10.5 um x 38 um nozzle, 22 um x 170 um restrictor
    (``I_r ~ 0.84 I_n``), 12.5 MHz x 640 samples, 24 V pulse; healthy mode about 191 kHz,
    damping ratio 0.07; fully blocked about 142 kHz, empty channels 1.0-1.6 MHz: its actuator
    rings 15 % below what inkdiag assumes for an actuator it was not told about (``inkdiag
    calibrate --empty``).
``h5``
    1040 kg/m^3, 8 mPa s ink, 13 um x 50 um nozzle, 36 um x 360 um restrictor
    (``I_r ~ 0.78 I_n``), 5 MHz x 256 samples, 22 V pulse; healthy mode about 135 kHz,
    damping ratio 0.09; fully blocked about 103 kHz, empty channels 0.65-1.05 MHz.
"""

from __future__ import annotations

import copy
import math
import numbers

import numpy as np
import yaml

__all__ = [
    "CLASS_VALUES",
    "FOREIGN_HEADS",
    "FOREIGN_PHYSICS",
    "FOREIGN_SPREADS",
    "NOZZLE_SPREADS",
    "nominal_profile",
    "true_profile",
    "simulate_foreign",
    "write_recording",
    "write_nominal_yaml",
    "write_true_yaml",
]

CLASS_VALUES = (
    "ok_signal", "healthy_nozzle", "empty_channel_1", "empty_channel_2",
    "mature_air_bubble", "intermediate_air_bubble", "small_air_bubble",
    "fully_blocked", "partially_blocked",
    "slightly_dried", "intermediately_dried", "deeply_dried",
)
"""The 12 class value strings, in ``FaultClass`` declaration order (rows come out in it)."""

# kind, severity low, severity high, drive factor (numbers of faults.MECHANISMS)
_MECH = {
    "ok_signal": ("healthy", 0.0, 0.0, 0.8),
    "healthy_nozzle": ("healthy", 0.0, 0.0, 1.0),
    "empty_channel_1": ("empty", 0.0, 0.10, 1.0),
    "empty_channel_2": ("empty", 1.1, 1.6, 1.0),
    "mature_air_bubble": ("nozzle_bubble", 0.82, 0.91, 1.0),
    "intermediate_air_bubble": ("nozzle_bubble", 0.72, 0.82, 1.0),
    "small_air_bubble": ("chamber_bubble", 4.6e-6, 6.0e-6, 1.0),
    "fully_blocked": ("blocked", 0.0, 0.0, 1.0),
    "partially_blocked": ("particle", 0.58, 0.68, 1.0),
    "slightly_dried": ("dried", 2.4, 4.2, 1.0),
    "intermediately_dried": ("dried", 4.2, 5.4, 1.0),
    "deeply_dried": ("dried", 6.0, 9.6, 1.0),
}
_PARTICLE_LENGTH_FRACTION = 0.3

FOREIGN_HEADS = {
    "h20": {
        "sampling": {"sample_rate_hz": 20.0e6, "n_samples": 1024},
        "channel": {
            "rho": 1100.0, "mu": 6.0e-3, "r_n": 11.0e-6, "L_n": 45.0e-6,
            "r_r": 24.0e-6, "L_r": 200.0e-6, "V_ch": 8.0e-12, "c": 1350.0,
            "B_act": 8.79e-21, "b": 3.0e-18,
        },
        "drive": {"amplitude_v": 28.0, "rise_s": 0.8e-6, "dwell_s": 2.4e-6,
                  "fall_s": 0.9e-6, "switch_delay_s": 1.5e-6},
        "sensor": {"gain_v_per_m3s": 1.0e10, "offset_v": 0.0, "noise_std_v": 0.012,
                   "adc_range_v": 2.5, "adc_bits": 12},
    },
    # chosen for an independent walkthrough of the documented workflow (2026-11-26), before any result
    "h16": {
        "sampling": {"sample_rate_hz": 16.0e6, "n_samples": 768},
        "channel": {
            "rho": 1060.0, "mu": 7.0e-3, "r_n": 12.0e-6, "L_n": 40.0e-6,
            "r_r": 26.0e-6, "L_r": 210.0e-6, "V_ch": 9.0e-12, "c": 1300.0,
            "B_act": 1.0e-20, "b": 2.5e-18,
        },
        "drive": {"amplitude_v": 25.0, "rise_s": 0.7e-6, "dwell_s": 2.8e-6,
                  "fall_s": 0.8e-6, "switch_delay_s": 1.2e-6},
        "sensor": {"gain_v_per_m3s": 1.2e10, "offset_v": 0.0, "noise_std_v": 0.010,
                   "adc_range_v": 2.5, "adc_bits": 12},
    },
    # chosen for a blind walkthrough of the documented workflow (2026-11-26), before any result; its
    # actuator (this module's default 1.6 MHz) rings 15 % below inkdiag's rule for an unknown actuator
    "h12": {
        "sampling": {"sample_rate_hz": 12.5e6, "n_samples": 640},
        "channel": {
            "rho": 1080.0, "mu": 5.0e-3, "r_n": 10.5e-6, "L_n": 38.0e-6,
            "r_r": 22.0e-6, "L_r": 170.0e-6, "V_ch": 6.5e-12, "c": 1320.0,
            "B_act": 7.0e-21, "b": 2.2e-18,
        },
        "drive": {"amplitude_v": 24.0, "rise_s": 0.7e-6, "dwell_s": 2.0e-6,
                  "fall_s": 0.7e-6, "switch_delay_s": 1.3e-6},
        "sensor": {"gain_v_per_m3s": 1.1e10, "offset_v": 0.02, "noise_std_v": 0.009,
                   "adc_range_v": 2.5, "adc_bits": 12},
    },
    "h5": {
        "sampling": {"sample_rate_hz": 5.0e6, "n_samples": 256},
        "channel": {
            "rho": 1040.0, "mu": 8.0e-3, "r_n": 13.0e-6, "L_n": 50.0e-6,
            "r_r": 36.0e-6, "L_r": 360.0e-6, "V_ch": 10.0e-12, "c": 1250.0,
            "B_act": 1.995e-20, "b": 2.5e-18,
        },
        "drive": {"amplitude_v": 22.0, "rise_s": 1.0e-6, "dwell_s": 3.2e-6,
                  "fall_s": 1.2e-6, "switch_delay_s": 2.0e-6},
        "sensor": {"gain_v_per_m3s": 1.6e10, "offset_v": 0.0, "noise_std_v": 0.01,
                   "adc_range_v": 2.0, "adc_bits": 10},
    },
    # inkdiag's own default head (the shipped profile's channel, drive, sampling and sensor),
    # simulated by this module's code: the reference row of reports/heads.md.
    "default": {
        "sampling": {"sample_rate_hz": 10.0e6, "n_samples": 512},
        "channel": {
            "rho": 1000.0, "mu": 10.0e-3, "r_n": 15.0e-6, "L_n": 60.0e-6,
            "r_r": 23.56e-6, "L_r": 182.4e-6, "V_ch": 5.0e-12, "c": 1200.0,
            "B_act": 5.198e-21, "b": 2.0e-18,
        },
        "drive": {"amplitude_v": 20.0, "rise_s": 0.6e-6, "dwell_s": 1.6e-6,
                  "fall_s": 0.6e-6, "switch_delay_s": 1.0e-6},
        "sensor": {"gain_v_per_m3s": 1.0e10, "offset_v": 0.0, "noise_std_v": 0.00585,
                   "adc_range_v": 2.0, "adc_bits": 12},
    },
}
"""The foreign heads: name -> ``{"sampling", "channel", "drive", "sensor"}`` (SI units).

``channel`` uses the ``InkChannelParams`` field names, ``drive`` the ``DriveWaveform``
ones; ``sensor``: nominal sense gain (V per m^3/s), nominal offset (V), white-noise
standard deviation (V), ADC range (+-V) and bits.
"""

_DEFAULT_PHYSICS = {
    "T_ref_k": 308.15,  # nominal ink temperature (35 C)
    "visc_temp_coeff_per_k": 0.025,  # Andrade: -2.5 %/K at T_ref
    "p0_pa": 1.0e5,  # static chamber pressure
    "sigma_n_per_m": 0.028,  # ink surface tension
    "kappa_gas": 1.3,  # polytropic exponent of a micro-bubble
    "f_act_hz": 1.6e6,  # unloaded actuator structural resonance
    "zeta_act": 0.04,
    "film_loss_factor": 1.2,
}

FOREIGN_PHYSICS = {
    "default": dict(T_ref_k=303.15, visc_temp_coeff_per_k=0.03, p0_pa=1.0e5, sigma_n_per_m=0.030,
                    kappa_gas=1.2, f_act_hz=2.175e6, zeta_act=0.03, film_loss_factor=1.5),
    "h20": dict(_DEFAULT_PHYSICS),
    "h16": dict(_DEFAULT_PHYSICS),
    "h12": dict(_DEFAULT_PHYSICS),
    "h5": dict(_DEFAULT_PHYSICS, T_ref_k=313.15, visc_temp_coeff_per_k=0.03,
               sigma_n_per_m=0.032, f_act_hz=1.05e6, zeta_act=0.05, film_loss_factor=1.0),
}
"""Per head: constants of the fault physics that a datasheet does not give (SI units).

``f_act_hz`` is each head's own unloaded-actuator resonance (the empty classes); it stays
below the Nyquist frequency of the head's sampling over the empty classes' range.
"""

FOREIGN_SPREADS = {
    "temperature_std_k": 1.2,
    "nozzle_radius_rel": 0.012,
    "nozzle_length_rel": 0.025,
    "restrictor_radius_rel": 0.015,
    "actuator_compliance_rel": 0.04,
    "coupling_rel": 0.04,
    "drive_rel": 0.015,
    "gain_rel": 0.06,
    "offset_std_v": 0.015,
}
"""Per-trace spreads (relative values are log-normal standard deviations; K; V)."""

_NOMINAL_CHANNEL_KEYS = ("rho", "mu", "r_n", "L_n", "V_ch", "c")


def _head(name):
    """Head dict (deep copy) and its physics constants for a name or a head dict."""
    if isinstance(name, str):
        if name not in FOREIGN_HEADS:
            raise ValueError(f"unknown foreign head {name!r}; expected one of {sorted(FOREIGN_HEADS)}")
        return copy.deepcopy(FOREIGN_HEADS[name]), dict(FOREIGN_PHYSICS[name]), dict(FOREIGN_SPREADS)
    if isinstance(name, dict):
        missing = [k for k in ("sampling", "channel", "drive", "sensor") if k not in name]
        if missing:
            raise ValueError(f"head dict lacks {missing}")
        head = copy.deepcopy(name)
        physics = dict(_DEFAULT_PHYSICS, **head.pop("physics", {}))
        spreads = dict(FOREIGN_SPREADS, **head.pop("spreads", {}))
        return head, physics, spreads
    raise ValueError(f"head must be a name or a head dict, got {type(name).__name__}")


def nominal_profile(name) -> dict:
    """What a datasheet and the drive settings give about head ``name``.

    Returns
    -------
    dict
        ``{"name", "sampling", "drive", "channel"}`` with ``channel`` holding only
        ``rho, mu, r_n, L_n, V_ch, c`` (SI); no sensor.
    """
    head, _, _ = _head(name)
    return {
        "name": name if isinstance(name, str) else "custom",
        "sampling": head["sampling"],
        "drive": head["drive"],
        "channel": {k: head["channel"][k] for k in _NOMINAL_CHANNEL_KEYS},
    }


def true_profile(name) -> dict:
    """The head's full true profile: ``{"name", "sampling", "channel", "drive", "sensor"}``."""
    head, _, _ = _head(name)
    return {"name": name if isinstance(name, str) else "custom", **head}


def _class_value(c) -> str:
    v = getattr(c, "value", c)
    if not isinstance(v, str) or v not in _MECH:
        raise ValueError(f"unknown fault class {c!r}; expected one of: {', '.join(CLASS_VALUES)}")
    return v


def _check_counts(counts) -> dict:
    if not hasattr(counts, "items"):
        raise ValueError(f"counts must be a mapping class -> int, got {type(counts).__name__}")
    out = {}
    for c, k in counts.items():
        v = _class_value(c)
        if isinstance(k, bool) or not isinstance(k, numbers.Integral) or k < 0:
            raise ValueError(f"counts[{v!r}] must be an int >= 0, got {k!r}")
        out[v] = out.get(v, 0) + int(k)
    return out


def _expm(M):
    """Matrix exponentials of a stack of small matrices, batched (no per-matrix Python step).

    Scaling and squaring with a degree-18 Taylor polynomial: the stack is scaled by ``2**-s``
    so that every matrix's 1-norm is at most 0.5 (truncation error below 1e-20 relative),
    the polynomial is evaluated by Horner's rule and squared back ``s`` times.

    Parameters
    ----------
    M : ndarray, shape (n, m, m)
        Dimensionless matrices.

    Returns
    -------
    ndarray, shape (n, m, m)
    """
    M = np.asarray(M, dtype=float)
    norm = np.abs(M).sum(axis=-2).max(initial=0.0)
    s = max(0, int(math.ceil(math.log2(norm / 0.5)))) if norm > 0 else 0
    X = M / 2.0**s
    eye = np.broadcast_to(np.eye(M.shape[-1]), M.shape)
    E = eye.copy()
    for k in range(18, 0, -1):  # Horner: I + X/1 (I + X/2 (I + ... ))
        E = eye + np.matmul(X, E) / k
    for _ in range(s):
        E = np.matmul(E, E)
    return E


def _propagate_pulse(A, B, drive, tau):
    """State after the trapezoidal pulse, per trace, by exact augmented expm per segment.

    Parameters
    ----------
    A : ndarray, shape (n, 4, 4)
        Dimensionless system matrices (time unit ``tau``).
    B : ndarray, shape (n, 4)
        Dimensionless input vectors (input = drive voltage in V).
    drive : ndarray, shape (n,)
        Pulse amplitude per trace, V.

    Returns
    -------
    ndarray, shape (n, 4)
        Dimensionless state at the end of the pulse.
    """
    n = A.shape[0]
    M = np.zeros((n, 6, 6))
    M[:, :4, :4] = A
    M[:, :4, 4] = B
    M[:, 4, 5] = 1.0
    d = drive
    z = np.zeros((n, 6))
    segments = ((d["rise_s"], 1.0 / d["rise_s"]), (d["dwell_s"], 0.0), (d["fall_s"], -1.0 / d["fall_s"]))
    amp = d["amplitude"]
    for dur, slope in segments:
        z[:, 5] = amp * slope * tau  # u' in V per time unit
        z = np.einsum("nij,nj->ni", _expm(M * (dur / tau)), z)
    return z[:, :4]


def _sample_window(Phi, x, n_samples, block=32):
    """Outputs ``y_k = C Phi^k x`` (``C = [0, 0, 1, 1]``), k = 0..n_samples-1, batched.

    Parameters
    ----------
    Phi : ndarray, shape (n, 4, 4)
        One-sample transition matrices.
    x : ndarray, shape (n, 4)
        States at the first sample.

    Returns
    -------
    ndarray, shape (n, n_samples)
        Dimensionless outflow ``V_r' + V_n'``.
    """
    n = x.shape[0]
    rows = np.empty((n, block, 4))  # C Phi^m, m = 0..block-1
    r = np.zeros((n, 4))
    r[:, 2:] = 1.0
    for m in range(block):
        rows[:, m] = r
        r = np.einsum("ni,nij->nj", r, Phi)
    step = np.linalg.matrix_power(Phi, block) if n else Phi
    y = np.empty((n, -(-n_samples // block) * block))
    for j in range(0, y.shape[1], block):  # a loop over blocks of samples, batched over traces
        y[:, j:j + block] = np.einsum("nmi,ni->nm", rows, x)
        x = np.einsum("nij,nj->ni", step, x)
    return y[:, :n_samples]


#: The spreads that belong to a nozzle (its geometry, actuator, driver and sense channel), in
#: the order :func:`simulate_foreign` draws them; temperature and offset vary frame to frame.
NOZZLE_SPREADS = ("nozzle_radius_rel", "nozzle_length_rel", "restrictor_radius_rel", "actuator_compliance_rel",
                  "coupling_rel", "drive_rel", "gain_rel")


def simulate_foreign(name, counts, seed=0, *, ideal: bool = False, severity=None, nozzles=None,
                     nozzle_seed=None) -> dict:
    """Simulate self-sensing traces of a foreign head, class by class.

    Parameters
    ----------
    name : str or dict
        A key of :data:`FOREIGN_HEADS`, or a head dict of the same layout (optionally with
        ``"physics"`` and ``"spreads"`` overrides of :data:`FOREIGN_PHYSICS` entries and
        :data:`FOREIGN_SPREADS`).
    counts : mapping of str (or FaultClass) -> int
        Traces per class. Rows come out grouped by class in :data:`CLASS_VALUES` order.
    seed : int
        Seed of ``numpy.random.default_rng``; same seed and arguments give identical output.
    ideal : bool
        No spreads, no noise, no offset, no ADC (severities are still drawn).
    severity : mapping of class -> array_like, optional
        Fixed severities (one per trace of that class; units of the class's severity).
    nozzles : array_like of int, shape (n,), optional
        Nozzle id of each row (default ``0 .. n - 1``), >= 0.
    nozzle_seed : int, optional
        Give the nozzles persistent spreads: the :data:`NOZZLE_SPREADS` of nozzle ``k`` are
        drawn from ``default_rng(nozzle_seed)`` for ids ``0 .. max(nozzles)``, so every
        call with the same ``nozzle_seed`` simulates the same nozzles (a commissioning
        recording and a later test recording of one head); temperature, offset, severity
        and noise still come from ``seed``. Default: every spread drawn per row from
        ``seed`` (each row its own nozzle).

    Returns
    -------
    dict
        ``traces`` (n, n_samples) float32 V; ``labels`` (n,) class strings;
        ``sample_rate_hz`` float Hz; ``mu`` (n,) channel ink viscosity, Pa s;
        ``mu_nozzle`` (n,) nozzle ink viscosity, Pa s; ``viscosity_ratio`` (n,)
        ``mu_nozzle / mu``; ``fm`` (n,) 1/s, ``-alpha (mu_nozzle - mu)``;
        ``nozzle`` (n,) int; ``severity`` (n,) (NaN for classes without one);
        ``frequency_hz``, ``damping_ratio`` (n,) of the model's oscillatory mode;
        ``drive_v``, ``gain``, ``offset_v`` (n,); ``noise_std_v`` float.

    Raises
    ------
    ValueError
        Unknown head or class, bad counts or severities.
    """
    head, phys, spr = _head(name)
    counts = _check_counts(counts)
    order = [v for v in CLASS_VALUES if counts.get(v, 0) > 0]
    labels = np.concatenate([np.full(counts[v], v, dtype=object) for v in order]) if order else np.zeros(0, object)
    n = labels.size
    fs = float(head["sampling"]["sample_rate_hz"])
    n_samples = int(head["sampling"]["n_samples"])
    ch, dr, se = head["channel"], head["drive"], head["sensor"]
    ids = np.arange(n, dtype=np.int64) if nozzles is None else np.asarray(nozzles)
    if ids.shape != (n,) or not np.issubdtype(ids.dtype, np.integer) or (n and ids.min() < 0):
        raise ValueError(f"nozzles must be {n} integer ids >= 0, got shape {ids.shape}, dtype {ids.dtype}")
    if n == 0:
        return _pack(np.zeros((0, n_samples), np.float32), labels, fs, *[np.zeros(0)] * 10, 0.0)
    table = None
    if nozzle_seed is not None:  # nozzle k's draws are row k: the same whatever the largest id
        table = dict(zip(NOZZLE_SPREADS, np.random.default_rng(nozzle_seed).standard_normal(
            (int(ids.max()) + 1, len(NOZZLE_SPREADS))).T))

    rng = np.random.default_rng(seed)
    kinds = np.array([_MECH[v][0] for v in labels])
    lo = np.array([_MECH[v][1] for v in labels])
    hi = np.array([_MECH[v][2] for v in labels])
    factor = np.array([_MECH[v][3] for v in labels])

    def spread(key):
        z = rng.standard_normal(n)  # drawn always: one fixed order of draws
        if table is not None:
            z = table[key][ids]
        rel = spr[key]
        return np.ones(n) if ideal or rel <= 0 else np.exp(rel * z)

    dT = rng.standard_normal(n) * (0.0 if ideal else spr["temperature_std_k"])
    r_n = ch["r_n"] * spread("nozzle_radius_rel")
    L_n = ch["L_n"] * spread("nozzle_length_rel")
    r_r = ch["r_r"] * spread("restrictor_radius_rel")
    B_act = ch["B_act"] * spread("actuator_compliance_rel")
    b = ch["b"] * spread("coupling_rel")
    drive_v = dr["amplitude_v"] * factor * spread("drive_rel")
    gain = se["gain_v_per_m3s"] * spread("gain_rel")
    z_off = rng.standard_normal(n)
    offset = np.zeros(n) if ideal else float(se["offset_v"]) + spr["offset_std_v"] * z_off
    sev = lo + (hi - lo) * rng.random(n)
    if severity:
        for c, vals in severity.items():
            v = _class_value(c)
            rows = labels == v
            vals = np.asarray(vals, dtype=float).reshape(-1)
            if vals.size != rows.sum() or not np.all(np.isfinite(vals)):
                raise ValueError(f"severity[{v!r}] needs {rows.sum()} finite values, got {vals.size}")
            sev[rows] = vals
    has_sev = hi > lo
    for kind, ok in (("dried", sev >= 1.0), ("nozzle_bubble", (sev >= 0) & (sev < 1)),
                     ("particle", (sev > 0) & (sev < 1)), ("chamber_bubble", sev > 0), ("empty", sev >= 0)):
        bad = (kinds == kind) & ~ok
        if bad.any():
            raise ValueError(f"severity out of physical bounds for {kind} rows: {sev[bad][:3]}")

    # ink viscosity at each trace's temperature (Andrade: ln mu = a + c/T)
    T0 = phys["T_ref_k"]
    T = T0 + dT
    mu = ch["mu"] * np.exp(phys["visc_temp_coeff_per_k"] * T0**2 * (1.0 / T - 1.0 / T0))
    rho = float(ch["rho"])
    mu_n = np.where(kinds == "dried", sev * mu, mu)

    B_extra = np.zeros(n)
    cb = kinds == "chamber_bubble"
    if cb.any():
        r_b = sev[cb]
        p_g = phys["p0_pa"] + 2.0 * phys["sigma_n_per_m"] / r_b
        B_extra[cb] = (4.0 / 3.0 * math.pi * r_b**3) / (phys["kappa_gas"] * p_g - 2.0 * phys["sigma_n_per_m"] / (3.0 * r_b))
    B_t = B_act + ch["V_ch"] / (rho * ch["c"] ** 2) + B_extra

    # nozzle branch: moving ink column (bubble cuts it), particle annulus
    col = np.where(kinds == "nozzle_bubble", (1.0 - sev) * L_n, L_n)
    I_n = rho * (col + math.pi * r_n / 4.0) / (math.pi * r_n**2)
    R_n = 8.0 * mu_n * col / (math.pi * r_n**4)
    pb = kinds == "particle"
    if pb.any():
        r, a, L = r_n[pb], sev[pb] * r_n[pb], L_n[pb]
        ell = _PARTICLE_LENGTH_FRACTION * L
        free = L - ell
        I_n[pb] = rho * ((free + math.pi * r / 4.0) / (math.pi * r**2) + ell / (math.pi * (r**2 - a**2)))
        R_n[pb] = 8.0 * mu_n[pb] * free / (math.pi * r**4) + 8.0 * mu_n[pb] * ell / (
            math.pi * (r**4 - a**4 - (r**2 - a**2) ** 2 / np.log(r / a)))
    I_r = rho * ch["L_r"] / (math.pi * r_r**2)
    R_r = 8.0 * mu * ch["L_r"] / (math.pi * r_r**4)
    open_r = np.ones(n)
    open_n = np.where(kinds == "blocked", 0.0, 1.0)

    em = kinds == "empty"
    if em.any():
        # actuator alone: its structural mode, mass-loaded and damped by an ink film
        I_act = 1.0 / ((2.0 * math.pi * phys["f_act_hz"]) ** 2 * ch["B_act"])
        R_act = 2.0 * phys["zeta_act"] * math.sqrt(I_act / ch["B_act"])
        m = sev[em]
        B_t[em] = B_act[em]
        I_n[em] = I_act * (1.0 + m)
        R_n[em] = R_act * (1.0 + phys["film_loss_factor"] * m * mu[em] / ch["mu"])
        open_r[em] = 0.0

    # dimensionless system: time in tau = 1 us, volume in b x 1 V
    tau = 1e-6
    kr = open_r * tau**2 / (I_r * B_t)
    kn = open_n * tau**2 / (I_n * B_t)
    A = np.zeros((n, 4, 4))
    A[:, 0, 2] = 1.0
    A[:, 1, 3] = 1.0
    A[:, 2, 0] = A[:, 2, 1] = -kr
    A[:, 2, 2] = -R_r / I_r * tau
    A[:, 3, 0] = A[:, 3, 1] = -kn
    A[:, 3, 3] = -R_n / I_n * tau
    Bv = np.zeros((n, 4))
    Bv[:, 2] = kr
    Bv[:, 3] = kn

    x = _propagate_pulse(A, Bv, {**dr, "amplitude": drive_v}, tau)
    x = np.einsum("nij,nj->ni", _expm(A * (dr["switch_delay_s"] / tau)), x)
    y = _sample_window(_expm(A * (1.0 / (fs * tau))), x, n_samples) * (b / tau)[:, None]  # m^3/s

    volts = gain[:, None] * y + offset[:, None]
    noise_std = 0.0 if ideal else float(se["noise_std_v"])
    if noise_std > 0:
        volts += noise_std * rng.standard_normal(volts.shape)
    if not ideal and se.get("adc_bits") is not None:
        lsb = 2.0 * se["adc_range_v"] / 2 ** int(se["adc_bits"])
        codes = np.clip(np.round(volts / lsb), -(2 ** (int(se["adc_bits"]) - 1)), 2 ** (int(se["adc_bits"]) - 1) - 1)
        volts = codes * lsb

    lam = np.linalg.eigvals(A) / tau
    osc = np.abs(lam.imag)
    i = np.argmax(osc, axis=1)
    lam1 = lam[np.arange(n), i]
    freq = np.abs(lam1.imag) / (2 * math.pi)
    zeta = -lam1.real / np.abs(lam1)
    alpha = 8.0 * L_n / (rho * (L_n + math.pi * r_n / 4.0) * r_n**2)
    fm = -alpha * (mu_n - mu)
    return _pack(volts.astype(np.float32), labels, fs, mu, mu_n, fm, np.where(has_sev, sev, np.nan),
                 freq, zeta, drive_v, gain, offset, ids, noise_std)


def _pack(traces, labels, fs, mu, mu_n, fm, sev, freq, zeta, drive_v, gain, offset, nozzle=None, noise_std=0.0):
    n = labels.size
    return {
        "traces": traces,
        "labels": labels.astype(str) if n else np.zeros(0, dtype="<U1"),
        "sample_rate_hz": float(fs),
        "mu": mu,
        "mu_nozzle": mu_n,
        "viscosity_ratio": mu_n / mu if n else np.zeros(0),
        "fm": fm,
        "nozzle": np.arange(n, dtype=np.int64) if nozzle is None else np.asarray(nozzle, dtype=np.int64),
        "severity": sev,
        "frequency_hz": freq,
        "damping_ratio": zeta,
        "drive_v": drive_v,
        "gain": gain,
        "offset_v": offset,
        "noise_std_v": float(noise_std),
    }


def write_recording(path, sim, *, frame_id=0, stamp=0.0) -> None:
    """Write ``sim`` (from :func:`simulate_foreign`) as an issue-14 RECORDING ``.npz``.

    Arrays: ``traces`` (n, n_samples) float32 V, ``sample_rate_hz`` scalar Hz,
    ``nozzle`` (n,) int64, ``frame_id`` (n,) int64 (all ``frame_id``), ``stamp`` (n,)
    float64 s (all ``stamp``), ``label`` (n,) class strings.
    """
    traces = np.asarray(sim["traces"], dtype=np.float32)
    n = traces.shape[0]
    np.savez(
        path,
        traces=traces,
        sample_rate_hz=np.float64(sim["sample_rate_hz"]),
        nozzle=np.asarray(sim["nozzle"], dtype=np.int64),
        frame_id=np.full(n, frame_id, dtype=np.int64),
        stamp=np.full(n, stamp, dtype=np.float64),
        label=np.asarray(sim["labels"]).astype(str),
    )


def _yaml_doc(profile: dict) -> dict:
    def clean(v):
        if isinstance(v, dict):
            return {k: clean(x) for k, x in v.items()}
        if isinstance(v, (bool, np.bool_)) or v is None:
            return v
        if isinstance(v, numbers.Integral):
            return int(v)
        if isinstance(v, numbers.Real):
            return float(v)
        return v

    doc = {"schema": "inkdiag.head_profile", "schema_version": 1, "name": profile["name"]}
    for key in ("sampling", "channel", "drive", "sensor"):
        if key in profile:
            doc[key] = clean(profile[key])
    doc["sampling"]["n_samples"] = int(doc["sampling"]["n_samples"])
    return doc


def _dump(path, doc) -> None:
    # PyYAML writes floats in a form it reads back as floats (1.0e-05, 20000000.0)
    with open(path, "w", encoding="utf-8") as fh:
        yaml.safe_dump(doc, fh, sort_keys=False)


def write_nominal_yaml(path, name) -> None:
    """Write :func:`nominal_profile` as a head-profile YAML (``schema: inkdiag.head_profile``)."""
    _dump(path, _yaml_doc(nominal_profile(name)))


def write_true_yaml(path, name) -> None:
    """Write :func:`true_profile` (channel, drive, sampling and sensor) as a head-profile YAML."""
    _dump(path, _yaml_doc(true_profile(name)))
