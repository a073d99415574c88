"""Head profiles: one printhead's sampling, channel, drive and sensor, as a YAML file.

A :class:`HeadProfile` is everything inkdiag knows about one printhead. The
simulator, the feature bands, the residual filters, screening, the estimators,
their calibration and the trend's deeply-dried level all take it, so nothing
in the core assumes the default head; that head is just the shipped profile
(:meth:`HeadProfile.default`).

The file (YAML, SI units)::

    schema: inkdiag.head_profile
    schema_version: 1
    name: my_head
    sampling: {sample_rate_hz: 20.0e+6, n_samples: 1024}
    channel:   # InkChannelParams field names
      rho: 1100.0        # kg/m^3
      mu: 6.0e-3         # Pa s
      r_n: 11.0e-6       # m
      L_n: 45.0e-6       # m
      V_ch: 3.0e-12      # m^3
      c: 1300.0          # m/s
      r_r: ...           # m      } left out of a *nominal* profile:
      L_r: ...           # m      } calibration (``inkdiag calibrate``)
      B_act: ...         # m^3/Pa } fits them to recorded healthy traces
      b: ...             # m^3/V  }
      f_act: 1.6e+6      # Hz, optional: the actuator's own resonance (an empty channel; from
      zeta_act: 0.03     #     its datasheet, or `inkdiag calibrate --empty`), and its damping ratio
    drive:     # DriveWaveform field names
      {amplitude_v: 25.0, rise_s: 1.0e-6, dwell_s: 2.0e-6, fall_s: 1.0e-6, switch_delay_s: 1.0e-6}
    sensor:
      gain_v_per_m3s: 1.0e+10   # V per (m^3/s)
      offset_v: 0.0             # V, mean offset
      noise_std_v: 0.004        # V, white noise (or snr_db, dB of the healthy trace)
      adc_range_v: 2.0          # V, the ADC reads +-adc_range_v
      adc_bits: 12              # 4 to 32, or null: no quantisation
    spreads:   # optional: per-trace variation of a head (Spreads field names)
      temperature_std_k: 1.5
    calibration: {...}          # optional: how the profile was made (its posterior: what training spreads over)

A *nominal* profile is what a datasheet and the drive settings give:
``sampling``, ``drive`` and the channel keys :data:`NOMINAL_CHANNEL_KEYS`; every
other ``channel`` and ``sensor`` key may be missing. A *complete* profile
(:attr:`HeadProfile.is_complete`) has every channel key and the sensor gain;
the simulator and the estimators need one.

Errors (:class:`ProfileError`, a ``ValueError``) name the file, the key and
the expected unit.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import math
import numbers
import re
from collections.abc import Mapping
from importlib import resources
from pathlib import Path

import numpy as np

from .checks import InputError
from .model import InkChannelModel, InkChannelParams
from .simulation.channels import DriveWaveform, Spreads
from .simulation.linear import simulate
from .simulation.modal import nominal_rms

__all__ = [
    "CHANNEL_UNITS",
    "DRIVE_UNITS",
    "HeadProfile",
    "MIN_PLAUSIBLE_RATE_HZ",
    "NOMINAL_CHANNEL_KEYS",
    "PLAUSIBLE_CHANNEL",
    "ProfileError",
    "SCHEMA",
    "SCHEMA_VERSION",
    "SENSOR_UNITS",
    "SPREAD_KEYS",
    "implausible_values",
    "same_sample_rate",
    "spread_cap",
]

SCHEMA = "inkdiag.head_profile"
SCHEMA_VERSION = 1

CHANNEL_UNITS = {
    "rho": "kg/m^3", "mu": "Pa s", "mu_nozzle": "Pa s", "r_n": "m", "L_n": "m", "r_r": "m",
    "L_r": "m", "V_ch": "m^3", "c": "m/s", "B_act": "m^3/Pa", "b": "m^3/V", "B_extra": "m^3/Pa",
    "f_act": "Hz", "zeta_act": "1",
}
"""The ``channel`` keys (the :class:`InkChannelParams` fields) and their SI units."""

NOMINAL_CHANNEL_KEYS = ("rho", "mu", "r_n", "L_n", "V_ch", "c")
"""Channel keys a nominal profile must give (a datasheet's nozzle, chamber and ink)."""

_OPTIONAL_CHANNEL_KEYS = ("mu_nozzle", "B_extra", "f_act", "zeta_act")

DRIVE_UNITS = {"amplitude_v": "V", "rise_s": "s", "dwell_s": "s", "fall_s": "s", "switch_delay_s": "s"}
"""The ``drive`` keys (the :class:`DriveWaveform` fields) and their SI units."""

PLAUSIBLE_CHANNEL = {"rho": (500.0, 3000.0, "kg/m^3"), "mu": (1e-4, 0.5, "Pa s"), "r_n": (1e-6, 1e-4, "m"),
                     "L_n": (1e-6, 1e-3, "m"), "V_ch": (1e-15, 1e-9, "m^3"), "c": (300.0, 3000.0, "m/s")}
"""Ranges of an inkjet head's nominal channel values, SI (``key: (low, high, unit)``): a value outside is
named where a profile or a calibration fails (a value in other units: ``mu`` in mPa s, ``r_n`` in um)."""

MIN_PLAUSIBLE_RATE_HZ = 1e5
"""A sample rate below this (Hz) is named where a profile fails (MHz written as Hz)."""

MAX_SAMPLE_RATE_HZ = 1e10
"""The largest ``sampling.sample_rate_hz`` a profile accepts, Hz (a sensing ADC's: tens of MHz)."""

MAX_N_SAMPLES = 65536
"""The largest ``sampling.n_samples`` a profile accepts: a trace is a row of every frame and of every training
set (a bound far above any head's, 250-2,000 samples, that keeps a slip from asking for tens of GiB)."""


def same_sample_rate(recorded_hz, head_hz) -> bool:
    """Whether a recording's sample rate is the head's: within 1e-9 relative, or the head's rate
    rounded to float32 (a trace message's header carries it so, and the nodes compare it so)."""
    recorded_hz, head_hz = float(recorded_hz), float(head_hz)
    return math.isclose(recorded_hz, head_hz, rel_tol=1e-9) or recorded_hz == float(np.float32(head_hz))


def implausible_values(channel, factor: float = 1.0) -> list:
    """The :data:`PLAUSIBLE_CHANNEL` values of ``channel`` (a mapping; missing keys skipped) outside their
    range (widened ``factor`` times each way), each as ``"channel.KEY VALUE UNIT (an inkjet head's: LOW to HIGH
    UNIT)"``."""
    return [f"channel.{k} {channel[k]:g} {unit} (an inkjet head's: {lo:g} to {hi:g} {unit})"
            for k, (lo, hi, unit) in PLAUSIBLE_CHANNEL.items()
            if channel.get(k) is not None and not lo / factor <= channel[k] <= hi * factor]


ABSURD_FACTOR = 1e3
"""A channel value this many times outside its :data:`PLAUSIBLE_CHANNEL` range is refused at once (a value
merely outside is named only where the physics fails: an unusual head may have one)."""


EMPTY_MIN_RATIO = 2.5
"""An empty channel's mode (``channel.f_act``, or recorded empty-channel traces) must be at least this many times
the healthy mode (the actuator alone rings far above the ink channel: 7.5-9.6 times on the heads of
``tests/foreign_head.py`` and the walkthrough's h12; 5.0-6.3 with a heavy ink film, the ``empty_channel_2`` class,
which is not what ``calibrate(empty=...)`` takes and which this does not catch). A lower ``f_act`` is in other
units (kHz written as Hz): a model trained with it called empty channels dried or bubbles (helper-125)."""
F_ACT_MIN_RATIO = 2.0
"""A complete profile's ``channel.f_act`` must be above this many times the healthy mode of its channel model:
looser than :data:`EMPTY_MIN_RATIO`, which calibration checks against the recorded mode, so that a profile
calibration wrote (its model's mode within a few per cent of the recorded one) always loads."""

MIN_ADC_BITS = 4
"""Fewest ``sensor.adc_bits`` a profile accepts: a 1-bit ADC's traces trained a model of 8 % FI without a word
(helper-125); a sensing ADC has about 8-16."""

MAX_DRIVE_TIME_S = 1e-4
"""Longest ``drive.rise_s``, ``dwell_s``, ``fall_s`` or ``switch_delay_s`` a profile accepts, s. A piezo
drive's rise, dwell and fall and the switch-over delay to sensing last about 0.5-20 us (every shipped
profile 0.6-3.2 us): a longer one is a time in other units (microseconds written as seconds or as
milliseconds), which calibration would otherwise fit without complaint (a slow rise only scales the
trace's amplitude, which the fit absorbs)."""

PLAUSIBLE_DRIVE_AMPLITUDE_V = (1.0, 500.0)
"""Range of ``drive.amplitude_v`` a profile accepts, V. A piezo inkjet drive swings about 10-150 V (every
profile in this repository, shipped or in its tests, 18-28 V): a value outside is in other units (millivolts
written as volts, or kilovolts), which training would otherwise take without complaint (a model trained on a
28,000 V drive labelled a 20 MHz head's traces 31 % right, helper-76's QA)."""

MAX_SNR_DB = 200.0
"""The largest ``sensor.snr_db`` a profile accepts, dB (a sensing chain's: about 20-60 dB; ``noise_std_v: 0``
is no noise at all). 1e4 dB had overflowed the simulator's noise with a traceback (helper-137's QA)."""

MAX_SPREAD = {"relative (std)": 1.0, "K": 30.0, "V": 10.0}
"""The largest ``spreads`` value a profile accepts, per unit: a relative spread (a log-normal's sigma: a
tolerance's, about 0.01-0.1), an ink temperature's spread (K) and the sensor offset's (V). 1e300 had
overflowed the simulation into NaN traces without a word (helper-137's QA)."""

VP_CAL_KEYS = ("a_sigma", "b_sigma", "a_omega", "b_omega")
"""The four constants of a ``calibration: vp_cal:`` section (:mod:`inkdiag_core.estimation.vp_calibration`)."""

MAX_VP_CAL = 1e3
"""The largest magnitude of a stored ``calibration: vp_cal:`` constant a profile accepts (dimensionless; the
heads fitted so far: 1.3-15)."""

SAMPLING_UNITS = {"sample_rate_hz": "Hz", "n_samples": "samples"}

SENSOR_UNITS = {
    "gain_v_per_m3s": "V/(m^3/s)", "offset_v": "V", "noise_std_v": "V", "snr_db": "dB",
    "adc_range_v": "V", "adc_bits": "bits",
}
"""The ``sensor`` keys and their units (``noise_std_v`` and ``snr_db`` are alternatives)."""

SPREAD_KEYS = tuple(f.name for f in dataclasses.fields(Spreads)
                    if f.name not in ("snr_db", "adc_bits", "adc_range_v"))
"""The ``spreads`` keys: :class:`Spreads` fields other than the sensor's noise and ADC."""
_SPREAD_KEYS = SPREAD_KEYS
_SPREAD_UNITS = {k: ("K" if k.endswith("_k") else "V" if k.endswith("_v") else "relative (std)")
                 for k in _SPREAD_KEYS}


def spread_cap(key: str) -> float:
    """The largest value a profile takes for ``spreads.<key>`` (:data:`MAX_SPREAD` in its unit)."""
    return MAX_SPREAD[_SPREAD_UNITS[key]]


_TOP_KEYS = ("schema", "schema_version", "name", "sampling", "channel", "drive", "sensor", "spreads",
             "calibration")

#: The simulator's nominal sense gain, V per (m^3/s): the default head's convention.
_DEFAULT_SENSOR = {"gain_v_per_m3s": 1.0e10, "offset_v": 0.0, "adc_range_v": 2.0, "adc_bits": 12}


class ProfileError(InputError):
    """A head profile that cannot be used: missing, malformed, another schema, incomplete."""


MAX_PROFILE_BYTES = 1 << 20
"""Largest head profile file or text taken, bytes (a profile is a few kB; a calibrated one's posterior and fit
report add about 2 kB): a 200 MB file had PyYAML parse for minutes (helper-125)."""
MAX_PROFILE_VALUES = 100_000
"""Most values (keys, scalars, entries) a profile may hold once its YAML aliases are expanded: nested aliases of a
few hundred bytes expanded to a 173 MB manifest (helper-125)."""


def _count_values(doc, budget: int) -> int:
    """Values of ``doc`` (nested mappings and sequences, each alias counted where it is used: YAML's ``!!pairs``,
    ``!!omap`` and ``!!set`` give tuples and sets), counting stops past ``budget``."""
    n, stack = 0, [doc]
    while stack and n <= budget:
        v = stack.pop()
        n += 1
        if isinstance(v, Mapping):
            n += len(v)  # the keys
            stack.extend(v.values())
        elif isinstance(v, (list, tuple, set, frozenset)):
            stack.extend(v)
    return n


_PLAIN = (str, int, float, bool, type(None))


def _check_plain(value, where: str, source: str) -> None:
    """Raise :class:`ProfileError` unless ``value`` (the ``calibration`` section) is plain data: mappings of string
    keys, lists (and tuples), strings, numbers, booleans, null (numpy values too, from Python): what a profile's
    sha256 and a model's manifest write. A YAML date or set there had made them fail with a TypeError."""
    if isinstance(value, Mapping):
        for k, v in value.items():
            if not isinstance(k, str):
                raise ProfileError(f"{source}: {where}: the key {k!r} is not a name: quote it (YAML reads on, off, "
                                   "yes and no as true and false, and digits as a number)")
            _check_plain(v, f"{where}.{k}", source)
    elif isinstance(value, (list, tuple)):  # a tuple: from Python (vp_cal's seeds), or YAML's !!pairs; a JSON list
        for i, v in enumerate(value):
            _check_plain(v, f"{where}[{i}]", source)
    elif isinstance(value, np.ndarray) and value.dtype.kind in "biuf":  # from Python: numbers, written as lists
        pass
    elif isinstance(value, np.generic) and value.dtype.kind in "biuf":
        pass
    elif not isinstance(value, _PLAIN):
        raise ProfileError(f"{source}: {where}: a {type(value).__name__} is not a plain value (a number, a string, "
                           "true/false, null, a list or a mapping; quote a date)")


def _check_vp_cal(cal, source: str) -> None:
    """Raise :class:`ProfileError` unless a ``calibration: vp_cal:`` section (None: none) holds its four constants as
    finite numbers of magnitude at most :data:`MAX_VP_CAL`: the section is outside the profile's sha256 (it is
    how the profile was made), and an edited constant had scaled every f_m estimate without a word (helper-137)."""
    if cal is None:
        return
    if not isinstance(cal, Mapping):
        raise ProfileError(f"{source}: calibration.vp_cal: expected a mapping, got {type(cal).__name__}")
    for k in VP_CAL_KEYS:
        v = cal.get(k)
        a = np.asarray(v) if isinstance(v, (numbers.Real, np.generic, np.ndarray)) else None  # 0-d arrays too
        if a is None or a.ndim or a.dtype.kind not in "iuf" or not abs(float(a)) <= MAX_VP_CAL:
            raise ProfileError(f"{source}: calibration.vp_cal.{k}: expected a number (dimensionless, magnitude at "
                               f"most {MAX_VP_CAL:g}), got {v!r}: remove the section (inkdiag fits it again) or "
                               "run inkdiag calibrate again")


# YAML 1.1 (PyYAML) reads "15e-6" as a string; a head profile means a number.
def _loader():
    import yaml

    class Loader(yaml.SafeLoader):
        def construct_mapping(self, node, deep=False):
            seen = set()
            for key_node, _ in node.value:
                key = self.construct_object(key_node, deep=deep)
                try:
                    hash(key)
                except TypeError:  # "? [1, 2]": PyYAML's own check comes after this one's `in`
                    raise yaml.constructor.ConstructorError(
                        None, None, f"a key that is a {type(key).__name__}, not a name", key_node.start_mark) from None
                if key in seen:
                    raise yaml.constructor.ConstructorError(
                        None, None, f"duplicate key {key!r}", key_node.start_mark)
                seen.add(key)
            return super().construct_mapping(node, deep=deep)

    Loader.add_implicit_resolver(
        "tag:yaml.org,2002:float",
        re.compile(r"^[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"),
        list("-+0123456789"))
    return Loader


def _number(where, key, value, unit, *, positive=True, integer=False, allow_none=False):
    if value is None and allow_none:
        return None
    if integer:
        if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value <= 0:
            raise ProfileError(f"{where}.{key}: expected a positive integer ({unit}), got {value!r}")
        return int(value)
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
        kind = "a positive" if positive else "a finite"
        raise ProfileError(f"{where}.{key}: expected {kind} number in {unit}, got {value!r}")
    value = float(value)
    if positive and value <= 0:
        raise ProfileError(f"{where}.{key}: expected a positive number in {unit}, got {value!r}")
    return value


def _section(doc, key, units, source, *, required=(), optional_keys=()):
    sec = doc.get(key, {})
    if sec is None:
        sec = {}
    if not isinstance(sec, Mapping):
        raise ProfileError(f"{source}: {key}: expected a mapping of {', '.join(units)}, got {type(sec).__name__}")
    unknown = sorted(set(sec) - set(units))
    if unknown:
        raise ProfileError(f"{source}: {key}.{unknown[0]}: unknown key (expected one of {', '.join(units)})")
    missing = [k for k in required if k not in sec]
    if missing:
        raise ProfileError(f"{source}: {key}.{missing[0]}: missing (a number in {units[missing[0]]})")
    return dict(sec)


def _yaml_problem(exc, text: str = "") -> str:
    """PyYAML's error as one line with where it is: ``" at line 4, column 1: expected ',' or ']', but got
    '<stream end>' (while parsing a flow sequence at line 3, column 44)"``, lines and columns from 1 (of
    ``text``, the document, for a character it cannot read)."""
    def at(mark):
        return f"line {mark.line + 1}, column {mark.column + 1}"

    problem, mark = getattr(exc, "problem", None), getattr(exc, "problem_mark", None)
    if not problem:  # not a MarkedYAMLError: a ReaderError (a control character) gives its offset in the text
        first = (str(exc).splitlines() or [type(exc).__name__])[0]
        pos = getattr(exc, "position", None)
        if isinstance(pos, int) and isinstance(text, str) and 0 <= pos <= len(text):
            line, column = text.count("\n", 0, pos) + 1, pos - text.rfind("\n", 0, pos)
            return f" at line {line}, column {column}: {first}"
        return ": " + first
    where = f" at {at(mark)}" if mark is not None else ""
    context, cmark = getattr(exc, "context", None), getattr(exc, "context_mark", None)
    if context:
        context = f" ({context}{' at ' + at(cmark) if cmark is not None else ''})"
    return f"{where}: {problem}{context or ''}"


@dataclasses.dataclass(frozen=True, eq=False)
class HeadProfile:
    """One printhead: sampling, channel, drive, sensor and spreads (SI units).

    Build one with :meth:`load` (a YAML file), :meth:`from_dict` or
    :meth:`default`; every constructor validates. Instances are immutable;
    :meth:`replace` returns a validated copy.

    Parameters
    ----------
    name : str
        A name for people (``"default"``, a head's type or serial).
    sample_rate_hz : float
        ADC sample rate of the sensed traces, Hz.
    n_samples : int
        Samples per trace.
    channel : mapping of str -> float
        :class:`InkChannelParams` fields, SI (see :data:`CHANNEL_UNITS`); a nominal
        profile gives at least :data:`NOMINAL_CHANNEL_KEYS`.
    drive : DriveWaveform
        The drive pulse the head is fired with when it is sensed.
    sensor : mapping of str -> float
        ``gain_v_per_m3s`` (V per m^3/s), ``offset_v`` (V), ``noise_std_v`` (V) or
        ``snr_db`` (dB of the nominal healthy trace), ``adc_range_v`` (V), ``adc_bits``
        (int or None). Missing keys take the default head's convention, except the
        gain, which a complete profile must give.
    spreads : mapping of str -> float
        Overrides of :class:`Spreads` fields (per-trace physical variation).
    calibration : mapping
        Provenance (what calibration fitted, its residual), free-form but for ``posterior``,
        which training reads (:func:`inkdiag_core.calibration.posterior_profiles`); not part of
        :attr:`sha256`.
    """

    name: str
    sample_rate_hz: float
    n_samples: int
    channel: Mapping
    drive: DriveWaveform
    sensor: Mapping = dataclasses.field(default_factory=dict)
    spreads_overrides: Mapping = dataclasses.field(default_factory=dict)
    calibration: Mapping = dataclasses.field(default_factory=dict)

    # -- construction -----------------------------------------------------------------------

    @classmethod
    def from_dict(cls, doc, *, source: str = "head profile") -> "HeadProfile":
        """Validate a parsed profile document and build the profile.

        Parameters
        ----------
        doc : mapping
            The YAML document (see the module docstring).
        source : str
            Where it came from, for error messages (a file name).

        Raises
        ------
        ProfileError
            Another schema or version, an unknown or missing key, a value of the
            wrong type or sign (the message names the key and its unit).
        """
        if not isinstance(doc, Mapping):
            raise ProfileError(f"{source}: not a head profile (expected a mapping with schema: {SCHEMA})")
        if _count_values(doc, MAX_PROFILE_VALUES) > MAX_PROFILE_VALUES:
            raise ProfileError(f"{source}: more than {MAX_PROFILE_VALUES:,} values once its YAML aliases are expanded "
                               "(a profile holds about a hundred)")
        if doc.get("schema") != SCHEMA:
            raise ProfileError(f"{source}: schema is {doc.get('schema')!r}, expected {SCHEMA!r}")
        if doc.get("schema_version") != SCHEMA_VERSION:
            raise ProfileError(f"{source}: schema_version is {doc.get('schema_version')!r}; this inkdiag reads "
                               f"version {SCHEMA_VERSION}")
        unknown = sorted(set(doc) - set(_TOP_KEYS))
        if unknown:
            raise ProfileError(f"{source}: {unknown[0]}: unknown key (expected {', '.join(_TOP_KEYS)})")
        name = doc.get("name", "head")
        if not isinstance(name, str) or not name:
            raise ProfileError(f"{source}: name: expected a non-empty string, got {name!r}")
        samp = _section(doc, "sampling", SAMPLING_UNITS, source, required=tuple(SAMPLING_UNITS))
        fs = _number(f"{source}: sampling", "sample_rate_hz", samp["sample_rate_hz"], "Hz")
        n = _number(f"{source}: sampling", "n_samples", samp["n_samples"], "samples", integer=True)
        if n < 16:
            raise ProfileError(f"{source}: sampling.n_samples: at least 16 samples per trace, got {n}")
        if n > MAX_N_SAMPLES:
            raise ProfileError(f"{source}: sampling.n_samples: at most {MAX_N_SAMPLES} samples per trace, got {n} "
                               "(a self-sensing trace is tens of microseconds: about 250-2,000 samples)")
        if fs > MAX_SAMPLE_RATE_HZ:
            raise ProfileError(f"{source}: sampling.sample_rate_hz: at most {MAX_SAMPLE_RATE_HZ:g} Hz, got {fs:g}")
        ch = _section(doc, "channel", CHANNEL_UNITS, source, required=NOMINAL_CHANNEL_KEYS)
        channel = {}
        for k, v in ch.items():
            if k == "mu_nozzle" and v is None:
                continue
            channel[k] = _number(f"{source}: channel", k, v, CHANNEL_UNITS[k], positive=k != "B_extra")
            if k == "B_extra" and channel[k] < 0:
                raise ProfileError(f"{source}: channel.B_extra: expected a number >= 0 in m^3/Pa, got {v!r}")
            if k == "zeta_act" and not channel[k] < 1:
                raise ProfileError(f"{source}: channel.zeta_act: the actuator's damping ratio must be below 1 (an "
                                   f"oscillating resonance), got {v!r}")
        absurd = implausible_values(channel, factor=ABSURD_FACTOR)
        if absurd:  # 1e-300 or 1e308: the model's arithmetic fails, or a later step does (a singular matrix)
            raise ProfileError(f"{source}: channel values no inkjet head has (implausible: {'; '.join(absurd)}: more "
                               f"than {ABSURD_FACTOR:g} times outside; a value in other units? SI: m, m^3, m/s, "
                               "kg/m^3, Pa s)")
        if "f_act" in channel and not channel["f_act"] < fs / 2:
            raise ProfileError(f"{source}: channel.f_act: the actuator's resonance {channel['f_act'] / 1e3:.4g} kHz is "
                               f"not below the Nyquist frequency {fs / 2e3:.1f} kHz of sampling.sample_rate_hz (Hz)")
        dr = _section(doc, "drive", DRIVE_UNITS, source, required=tuple(DRIVE_UNITS))
        drive = DriveWaveform(**{k: _number(f"{source}: drive", k, v, DRIVE_UNITS[k]) for k, v in dr.items()})
        lo, hi = PLAUSIBLE_DRIVE_AMPLITUDE_V
        if not lo <= drive.amplitude_v <= hi:
            unit = "mV" if drive.amplitude_v > hi else "kV"
            raise ProfileError(f"{source}: drive.amplitude_v: {drive.amplitude_v:g} V is outside {lo:g}-{hi:g} V, a "
                               f"piezo drive's range (about 10-150 V): the profile's amplitude is in volts, not {unit}")
        for k in ("rise_s", "dwell_s", "fall_s", "switch_delay_s"):
            if getattr(drive, k) > MAX_DRIVE_TIME_S:
                raise ProfileError(
                    f"{source}: drive.{k}: {getattr(drive, k):g} s is longer than {MAX_DRIVE_TIME_S * 1e6:g} us: a "
                    "drive's rise, dwell and fall and the switch delay last microseconds (about 0.5-20 us); the "
                    "profile's times are in seconds, 1 us = 1.0e-6")
        se = _section(doc, "sensor", SENSOR_UNITS, source)
        sensor = {}
        for k, v in se.items():
            if k == "adc_bits":
                sensor[k] = _number(f"{source}: sensor", k, v, "bits", integer=True, allow_none=True)
                if sensor[k] is not None and not MIN_ADC_BITS <= sensor[k] <= 32:
                    raise ProfileError(f"{source}: sensor.adc_bits: {MIN_ADC_BITS} to 32 bits (a sensing ADC's: "
                                       f"about 8-16), got {v!r}")
            else:
                sensor[k] = _number(f"{source}: sensor", k, v, SENSOR_UNITS[k],
                                    positive=k not in ("offset_v", "noise_std_v", "snr_db"))
        if "noise_std_v" in sensor and "snr_db" in sensor:
            raise ProfileError(f"{source}: sensor: give noise_std_v (V) or snr_db (dB), not both")
        if sensor.get("noise_std_v", 0.0) < 0:
            raise ProfileError(f"{source}: sensor.noise_std_v: expected a number >= 0 in V, got "
                               f"{sensor['noise_std_v']!r}")
        if not 0 <= sensor.get("snr_db", 0.0) <= MAX_SNR_DB:  # the simulator's noise takes an SNR of 0 dB or more
            raise ProfileError(f"{source}: sensor.snr_db: expected a number from 0 to {MAX_SNR_DB:g} dB (a sensing "
                               f"chain's: about 20-60 dB), got {sensor['snr_db']!r}")
        sp = _section(doc, "spreads", _SPREAD_UNITS, source)
        spreads = {k: _number(f"{source}: spreads", k, v, _SPREAD_UNITS[k], positive=False) for k, v in sp.items()}
        for k, v in spreads.items():
            if not 0 <= v <= MAX_SPREAD[_SPREAD_UNITS[k]]:
                raise ProfileError(f"{source}: spreads.{k}: expected a number from 0 to "
                                   f"{MAX_SPREAD[_SPREAD_UNITS[k]]:g} ({_SPREAD_UNITS[k]}), got {v!r}")
        cal = doc.get("calibration") or {}
        if not isinstance(cal, Mapping):
            raise ProfileError(f"{source}: calibration: expected a mapping, got {type(cal).__name__}")
        _check_plain(cal, "calibration", source)
        _check_vp_cal(cal.get("vp_cal"), source)
        prof = cls(name, fs, n, channel, drive, sensor, spreads, dict(cal))
        if prof.is_complete:
            prof._check_physics(source)
        return prof

    @classmethod
    def loads(cls, text: str, *, source: str = "head profile") -> "HeadProfile":
        """Parse YAML text (see :meth:`from_dict`)."""
        import yaml

        if len(text) > MAX_PROFILE_BYTES:
            raise ProfileError(f"{source}: {len(text):,} characters is not a head profile (a profile is a few kB; at "
                               f"most {MAX_PROFILE_BYTES:,})")
        try:
            doc = yaml.load(text, Loader=_loader())  # noqa: S506 (a SafeLoader subclass)
        except yaml.YAMLError as exc:
            raise ProfileError(f"{source}: not valid YAML{_yaml_problem(exc, text)}") from None
        except RecursionError:  # PyYAML composes and constructs nested nodes recursively
            raise ProfileError(f"{source}: not valid YAML: nested too deeply") from None
        return cls.from_dict(doc, source=source)

    @classmethod
    def load(cls, path) -> "HeadProfile":
        """Read a profile file (YAML).

        Raises
        ------
        ProfileError
            The file is missing or unreadable, or its content is not a valid profile.
        """
        path = Path(path)
        try:
            if path.is_file() and path.stat().st_size > MAX_PROFILE_BYTES:  # not read: it is no profile
                raise ProfileError(f"{path}: {path.stat().st_size:,} bytes is not a head profile (a profile is a few "
                                   f"kB; at most {MAX_PROFILE_BYTES:,})")
            text = path.read_text(encoding="utf-8")
        except FileNotFoundError:
            raise ProfileError(f"{path}: no such head profile file") from None
        except UnicodeDecodeError:
            raise ProfileError(f"{path}: not a head profile: a binary file, not YAML text (a model file? a profile "
                               "is the head's YAML file)") from None
        except OSError as exc:
            raise ProfileError(f"{path}: cannot read the head profile: {exc}") from None
        return cls.loads(text, source=str(path))

    @classmethod
    def default(cls) -> "HeadProfile":
        """The default head (the simulator's 15 x 60 um nozzle, 237 kHz, 10 MHz x 512), a shipped file."""
        return _default_profile()

    def replace(self, **changes) -> "HeadProfile":
        """A validated copy with top-level fields changed; ``channel``/``sensor`` mappings merge.

        ``channel={"r_r": 2e-5}`` updates that key and keeps the others (a value of
        ``None`` removes a key); the same for ``sensor``, ``spreads_overrides``
        and ``calibration``. ``drive`` may be a mapping of :class:`DriveWaveform` fields.
        """
        doc = self.to_dict()
        mapping = {"channel": "channel", "sensor": "sensor", "spreads_overrides": "spreads",
                   "calibration": "calibration"}
        for key, value in changes.items():
            if key in mapping:
                sec = dict(doc.get(mapping[key], {}))
                for k, v in dict(value).items():
                    if v is None:
                        sec.pop(k, None)
                    else:
                        sec[k] = v
                doc[mapping[key]] = sec
            elif key == "drive":
                doc["drive"] = {**doc["drive"], **(dataclasses.asdict(value) if isinstance(value, DriveWaveform)
                                                   else dict(value))}
            elif key in ("sample_rate_hz", "n_samples"):
                doc["sampling"][key] = value
            elif key == "name":
                doc["name"] = value
            else:
                raise TypeError(f"HeadProfile.replace: unknown field {key!r}")
        return HeadProfile.from_dict(doc, source=f"profile {self.name!r}")

    def _check_physics(self, source):
        fs, n = self.sample_rate_hz, self.n_samples
        odd = implausible_values(self.channel) + ([f"sampling.sample_rate_hz {fs:g} Hz (an inkjet head's: "
                                                   f"{MIN_PLAUSIBLE_RATE_HZ:g} Hz or more)"]
                                                  if fs < MIN_PLAUSIBLE_RATE_HZ else [])
        hint = f" (implausible: {'; '.join(odd)}: a value in other units? SI: m, m^3, m/s, kg/m^3, Pa s, Hz)" if odd else ""
        try:
            with np.errstate(all="ignore"):
                f0, zeta = self.healthy_mode()
        except (ArithmeticError, ValueError) as exc:  # r_n 1e308: r_n ** 2 overflows; mu 1e300: a matrix of infs
            raise ProfileError(f"{source}: the channel's model cannot be computed from its values "
                               f"({type(exc).__name__}: {exc})" + hint) from None
        if not (0 < zeta < 1):
            raise ProfileError(f"{source}: the channel has no oscillating healthy mode (damping ratio {zeta:.3g})"
                               + hint)
        if f0 >= fs / 2:
            raise ProfileError(f"{source}: the healthy mode {f0 / 1e3:.1f} kHz is above the Nyquist frequency "
                               f"{fs / 2e3:.1f} kHz of sampling.sample_rate_hz" + hint)
        f_act = self.channel.get("f_act")
        if f_act is not None and not f_act > F_ACT_MIN_RATIO * f0:
            raise ProfileError(f"{source}: channel.f_act, {f_act / 1e3:.4g} kHz, is not above {F_ACT_MIN_RATIO:g} times "
                               f"the healthy mode ({f0 / 1e3:.1f} kHz), as an actuator's own resonance is (7.5-9.6 "
                               "times on the heads measured): it is in Hz (a value in kHz?)")
        if n / fs * f0 < 3:
            raise ProfileError(f"{source}: a trace of {n} samples at {fs:g} Hz holds {n / fs * f0:.1f} periods of the "
                               f"healthy mode ({f0 / 1e3:.1f} kHz); at least 3 are needed")
        with np.errstate(all="ignore"):
            rms = nominal_rms(self.channel_params(), self.drive, n, fs) * self.sensor_gain_v_per_m3s
        adc, offset = self.adc_range_v, self.sensor_offset_v  # the default's 2 V where the profile leaves it out
        if not np.isfinite(rms):  # b 1e300: the model's output overflows
            raise ProfileError(f"{source}: the nominal healthy trace overflows (rms {rms:g} V): check channel.b "
                               "(m^3 per V s), channel.B_act and sensor.gain_v_per_m3s (V per m^3/s)" + hint)
        step = 2 * adc / 2 ** self.adc_bits if self.adc_bits else 0.0
        if not rms >= step / 4:  # the ring-down is quantisation noise: a gain off by 1e3, or the range in mV
            raise ProfileError(f"{source}: the nominal healthy trace (rms {rms:.3g} V) is smaller than a quarter of one "
                               f"step of the ADC ({step:.3g} V: +-{adc:g} V, {self.adc_bits} bits): check "
                               "sensor.gain_v_per_m3s (V per m^3/s), sensor.adc_range_v (V) and sensor.adc_bits")
        noise = self.sensor.get("noise_std_v", 0.0)
        if noise and not noise <= rms:  # as spreads() refuses it: the simulator takes an SNR of 0 dB or more
            raise ProfileError(f"{source}: sensor.noise_std_v {noise:g} V is more than the nominal healthy trace's "
                               f"rms, {rms:.3g} V (an SNR below 0 dB; the simulator takes 0 dB or more): is it in volts, "
                               "and sensor.gain_v_per_m3s in V per m^3/s?")
        if "adc_range_v" not in self.sensor:  # the default's 2 V: a head of larger traces may leave it out
            return
        if not (rms < adc and abs(offset) < adc):  # every healthy trace clipped, or all of it out of range
            raise ProfileError(f"{source}: sensor.adc_range_v {adc:g} V: an ADC reading +-{adc:g} V clips the nominal "
                               f"healthy trace (rms {rms:.3g} V about an offset of {offset:g} V): is it in volts?")

    # -- serialisation ----------------------------------------------------------------------

    def to_dict(self) -> dict:
        """The profile as a YAML-ready document (plain Python types)."""
        doc = {
            "schema": SCHEMA,
            "schema_version": SCHEMA_VERSION,
            "name": self.name,
            "sampling": {"sample_rate_hz": float(self.sample_rate_hz), "n_samples": int(self.n_samples)},
            "channel": {k: float(self.channel[k]) for k in CHANNEL_UNITS if k in self.channel},
            "drive": {k: float(v) for k, v in dataclasses.asdict(self.drive).items()},
        }
        if self.sensor:
            doc["sensor"] = {k: (None if v is None else int(v) if k == "adc_bits" else float(v))
                             for k, v in ((k, self.sensor[k]) for k in SENSOR_UNITS if k in self.sensor)}
        if self.spreads_overrides:
            doc["spreads"] = {k: float(self.spreads_overrides[k]) for k in _SPREAD_KEYS
                              if k in self.spreads_overrides}
        if self.calibration:
            doc["calibration"] = json.loads(json.dumps(self.calibration, default=_plain))
        return doc

    def dumps(self) -> str:
        """The profile as YAML text (numbers written so that they read back exactly)."""
        import yaml

        return yaml.safe_dump(self.to_dict(), sort_keys=False, default_flow_style=False)

    def save(self, path) -> Path:
        """Write the profile as YAML to ``path``; returns the path."""
        path = Path(path)
        path.write_text(self.dumps(), encoding="utf-8")
        return path

    @functools.cached_property
    def sha256(self) -> str:
        """sha256 (hex) of the profile's content (canonical JSON of everything but ``name`` and ``calibration``).

        Two files that describe the same head the same way share it, whatever
        their layout; a model records it to refuse another head.
        """
        doc = self.to_dict()
        doc.pop("name")
        doc.pop("calibration", None)
        return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()

    def __eq__(self, other):
        return isinstance(other, HeadProfile) and self.to_dict() == other.to_dict()

    __hash__ = None

    def __repr__(self):
        kind = "complete" if self.is_complete else "nominal"
        return (f"HeadProfile({self.name!r}, {kind}, {self.sample_rate_hz / 1e6:g} MHz x {self.n_samples}, "
                f"sha256={self.sha256[:12]})")

    # -- what the rest of the core asks --------------------------------------------------------

    @property
    def missing(self) -> tuple[str, ...]:
        """Keys a complete profile needs and this one lacks (``"channel.r_r"``, ``"sensor.gain_v_per_m3s"``)."""
        out = [f"channel.{k}" for k in CHANNEL_UNITS if k not in _OPTIONAL_CHANNEL_KEYS and k not in self.channel]
        if "gain_v_per_m3s" not in self.sensor:
            out.append("sensor.gain_v_per_m3s")
        return tuple(out)

    @property
    def is_complete(self) -> bool:
        """True when the channel and the sensor gain are all given (simulation and estimation need it)."""
        return not self.missing

    def _need_complete(self, what):
        if self.missing:
            raise ProfileError(f"profile {self.name!r} is nominal ({', '.join(self.missing)} missing): {what} needs a "
                               "complete profile (run `inkdiag calibrate` on recorded healthy traces)")

    def channel_params(self) -> InkChannelParams:
        """The healthy channel as :class:`InkChannelParams` (complete profiles only)."""
        self._need_complete("the channel model")
        return InkChannelParams(**self.channel)

    def model(self) -> InkChannelModel:
        """The healthy channel's linear model (eq. 12)."""
        return InkChannelModel(self.channel_params())

    def healthy_mode(self) -> tuple[float, float]:
        """Frequency (Hz) and damping ratio of the healthy channel's dominant mode."""
        return self.model().dominant_mode()

    def frequency_scale(self) -> float:
        """This head's healthy mode over the default head's (237.15 kHz), dimensionless.

        Frequency bands tuned on the default head (feature bands, residual
        filter bands) are that head's bands times this factor: they follow the
        head's modes instead of fixed Hz.
        """
        return self.healthy_mode()[0] / _default_profile().healthy_mode()[0]

    @property
    def sensor_gain_v_per_m3s(self) -> float:
        """Nominal sense gain, V per (m^3/s)."""
        self._need_complete("the sense gain")
        return float(self.sensor["gain_v_per_m3s"])

    @property
    def sensor_offset_v(self) -> float:
        """Mean sense offset, V."""
        return float(self.sensor.get("offset_v", 0.0))

    @property
    def adc_range_v(self) -> float:
        """The ADC reads +- this, V."""
        return float(self.sensor.get("adc_range_v", _DEFAULT_SENSOR["adc_range_v"]))

    @property
    def max_abs_v(self) -> float:
        """Largest sample magnitude this head's sensor can produce, V: 5x :attr:`adc_range_v`.

        A row with a sample beyond it is out of range (:func:`inkdiag_core.screen_traces`),
        for fdi, training, calibration, baselines and the estimators alike.
        """
        return 5.0 * self.adc_range_v

    @property
    def adc_bits(self):
        """ADC resolution (int), or None for no quantisation."""
        return self.sensor.get("adc_bits", _DEFAULT_SENSOR["adc_bits"])

    def noise_std_v(self) -> float:
        """White-noise standard deviation, V (from ``noise_std_v``, or ``snr_db`` of the nominal healthy trace)."""
        if "noise_std_v" in self.sensor:
            return float(self.sensor["noise_std_v"])
        snr = float(self.sensor.get("snr_db", Spreads().snr_db))
        rms = nominal_rms(self.channel_params(), self.drive, self.n_samples, self.sample_rate_hz)
        return rms * self.sensor_gain_v_per_m3s / 10 ** (snr / 20)

    def spreads(self) -> Spreads:
        """The simulator's :class:`Spreads` for this head: its overrides, its noise and its ADC."""
        if "noise_std_v" in self.sensor:
            noise = float(self.sensor["noise_std_v"])
            if noise == 0:
                snr = math.inf
            else:
                rms = nominal_rms(self.channel_params(), self.drive, self.n_samples, self.sample_rate_hz)
                # >= 0 dB, as the simulator takes it: a noise above the healthy rms is refused at load (_check_physics)
                snr = 20 * math.log10(rms * self.sensor_gain_v_per_m3s / noise)
        else:
            snr = float(self.sensor.get("snr_db", Spreads().snr_db))
        return dataclasses.replace(Spreads(), **self.spreads_overrides, snr_db=snr, adc_bits=self.adc_bits,
                                   adc_range_v=self.adc_range_v)

    def simulate(self, counts, *, seed=0, spreads: Spreads | None = None, **kwargs):
        """:func:`inkdiag_core.simulate` on this head: its channel, drive, sampling, sensor and spreads.

        Parameters
        ----------
        counts : mapping of FaultClass (or its value) -> int
            Traces per class.
        seed : int or numpy.random.Generator
        spreads : Spreads, optional
            Instead of :meth:`spreads` (for instance ``Spreads.none()``).
        **kwargs
            Further keywords of :func:`inkdiag_core.simulate` (``severity``, ...).

        Returns
        -------
        SimulationResult
            ``.traces`` (n, n_samples) float32 volts.
        """
        self._need_complete("simulation")
        return simulate(counts, sample_rate_hz=self.sample_rate_hz, n_samples=self.n_samples, seed=seed,
                        spreads=self.spreads() if spreads is None else spreads, drive=self.drive,
                        base_params=self.channel_params(), sensor_gain_v_per_m3s=self.sensor_gain_v_per_m3s,
                        sensor_offset_v=self.sensor_offset_v, **kwargs)

    def check_traces(self, traces, sample_rate_hz, *, what: str = "recording") -> None:
        """Refuse traces of another sampling: a clear :class:`ProfileError`.

        Parameters
        ----------
        traces : array_like, shape (n, n_samples)
        sample_rate_hz : float
            Their sample rate, Hz.
        """
        shape = np.shape(traces)
        length = f" x {shape[1]} samples" if len(shape) == 2 else ""
        if not same_sample_rate(sample_rate_hz, self.sample_rate_hz):
            raise ProfileError(f"{what} is sampled at {float(sample_rate_hz):.10g} Hz{length}; profile {self.name!r} "
                               f"is {self.sample_rate_hz:.10g} Hz x {self.n_samples} samples")
        if len(shape) != 2 or shape[1] != self.n_samples:
            got = shape[1] if len(shape) == 2 else f"shape {shape}"
            raise ProfileError(f"{what} has traces of {got} samples; profile {self.name!r} has {self.n_samples}")


def _plain(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"calibration: {type(o).__name__} is not a plain value")


@functools.lru_cache(maxsize=1)
def _default_profile() -> HeadProfile:
    text = resources.files(__package__).joinpath("profiles/default_head.yaml").read_text(encoding="utf-8")
    return HeadProfile.loads(text, source="inkdiag_core/profiles/default_head.yaml")
