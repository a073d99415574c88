"""Online f_m estimation of the drying nozzles, frame by frame and nozzle range by range.

A printer controller may send one frame of a head as several trace messages,
one per contiguous *nozzle range* (``first_nozzle``, ``n_nozzles``), and the
FDI stage answers each of them with its own list of drying nozzles. The two
streams arrive in either order and on different paths (the traces best effort,
the lists reliable, after the labelling). :class:`DryingTracker` joins them
on ``(frame_id, first_nozzle)``: each range of each frame is estimated with
*that* frame's list for *that* range, never with an earlier frame's or
another range's. What waits for its partner is held in two bounded buffers
(oldest dropped first, and counted). The FDI stage answers each range's messages
in frame order, so a range's traces still held when a later frame's list for that
range comes will get no list (the FDI stage never had that frame): they are
dropped then, and counted, instead of holding their message's memory until the
buffer is full.

For each joined pair the rows of the listed nozzles are screened
(:func:`~inkdiag_core.screen_traces`), f_m is estimated in one batch
(:func:`~inkdiag_core.estimate_fm_batch`, relative to each nozzle's healthy
reading when :class:`~inkdiag_core.NozzleBaselines` with f_m are given) and
each nozzle's trend is updated (:class:`~inkdiag_core.FmTrendBank`). Pure
numpy; no ROS.

A list whose range is unknown (``first_nozzle=None``: an FDI stage that does
not say which range it labelled) applies to every range of its frame: each
held range with a listed nozzle is estimated; lists of one frame without a
range are merged; they stay until evicted, since more ranges of that frame
may still come, and a range none of them names waits until it is evicted.

With a :class:`~inkdiag_core.HeadProfile` the tracker estimates on that head:
its model, its ``"vp_cal"`` constants (:func:`~inkdiag_core.estimation.vp_cal_for`),
its deeply-dried level (:func:`~inkdiag_core.deeply_dried_fm` of its channel)
and its sampling (trace messages of another sample rate or length are
refused with a ``ValueError``). :meth:`DryingTracker.estimate_rows` is the
screening-estimation-trend step on its own, for offline use
(``inkdiag estimate``): the node and the command run the same code.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass, field

import numpy as np

from .estimation import MIN_FM_SAMPLES, estimate_fm_batch
from .model import InkChannelModel
from .screening import screen_traces


def _default_head():
    from .head_profile import HeadProfile

    return HeadProfile.default()
from .trend import CLOCK_RESET_S, FmTrendBank, deeply_dried_fm

__all__ = ["AT_BOUND_REASON", "BELOW_NOISE_REASON", "ESTIMATE_COLUMNS", "MISFIT_REASON", "NONPHYSICAL_REASON",
           "RECOVERY_FRAMES", "DryingTracker", "RangeEstimates", "RowEstimates"]


#: Reason of a row whose estimate means a viscosity <= 0 (``channel.mu + d_mu``): no nozzle the linear
#: channel model describes (an empty channel, an air bubble), so not an estimate of its ink.
NONPHYSICAL_REASON = "viscosity_not_positive"
#: Reason of a row whose f_m fit ended at an edge of its search interval (``FmBatchEstimate.at_bound``: a
#: viscosity 16x the ink's, or thinner than the ink): the edge, not an estimate. Fully blocked nozzles, empty
#: channels and some small air bubbles end there (a viscosity 22x the ink's for a blocked one, 0.85x for an empty
#: one, reported as estimates before); drying nozzles of the simulated classes (up to about 10x) do not.
AT_BOUND_REASON = "at_search_bound"
#: Frames in a row that must leave a nozzle out of their drying lists before its trend ends as recovered: one
#: frame labelled otherwise is most often a misclassification. 100 nozzles drying from 2.4 to 9 times the ink's
#: viscosity over 20 s at 5 frames/s, none recovering (the default model, no baselines): their trends restarted 76
#: times at 1 frame, 28 at 2, 17 at 3, 9 at 4 (``scripts/report trend_recovery``, ``reports/trend_recovery.md``).
RECOVERY_FRAMES = 3
#: Reason of a row whose fitted drying channel leaves more than :data:`MISFIT_REL` of the row's variation
#: unexplained (``FmBatchEstimate.residual_rel``), and, with a profile, more than :data:`MISFIT_NOISE_FACTOR` times
#: its sensor noise: a trace the drying model does not describe (an air bubble, a ringing of another kind that fdi
#: listed as dried), whose f_m would be a number and no estimate.
MISFIT_REASON = "misfit"
#: Dried rows of the five heads of ``tests/foreign_head.py`` (300 a class and head, 30 dB) leave at most 0.19 with
#: their true profiles and 0.26 with calibrated ones (h5's deeply dried); healthy rows up to 0.44 (about 1 in 100 of
#: them above 0.35 on those heads: a healthy row estimated, as ``inkdiag estimate`` does every row by default, may
#: be a misfit), small air bubbles 0.25-0.46, mature and intermediate ones about 0.9, empty channels 1.0 (the
#: default head). A ratio of rms values: 0.35 is 12 % of the row's variance.
MISFIT_REL = 0.35
#: Dried rows leave at most 4.8 times the sensor noise in their residual's rms (h5 calibrated, as above); a row whose
#: residual is noise (a low SNR) is no misfit however large its share.
MISFIT_NOISE_FACTOR = 6.0
#: Reason of a row of a head with a profile whose AC rms is at most :data:`BELOW_NOISE_FACTOR` times the
#: profile's sensor noise (``noise_std_v``): no ringing to fit (a nozzle that did not fire, traces in other
#: units). White noise once came out as f_m -4.6e6 1/s with no reason.
BELOW_NOISE_REASON = "below_noise"
#: White noise reads 1 (within a few per cent over 256 samples or more); deeply dried traces of the five heads of
#: ``tests/foreign_head.py`` (30 dB) ring at 9.3 times their noise_std_v and more: at about half a healthy trace's
#: amplitude, they stay above 2 down to an SNR of about 12 dB.
BELOW_NOISE_FACTOR = 2.0
#: An estimate below this times the ink's viscosity (the profile's ``channel.mu``) is counted in
#: :attr:`DryingTracker.estimates_thinner`: no nozzle thins its ink so, so most rows there mean a profile of another
#: head or ink (helper-109: another head's profile of the same sampling read healthy nozzles at 0.4 mu, +1.7e5 1/s;
#: healthy rows of the right one scatter about 0.05 mu).
THIN_FACTOR = 0.7
#: Samples at one of the ADC's end codes that make a row ``clipped`` for estimation (:func:`at_rails`).
MIN_RAIL_SAMPLES = 2
#: An ADC of fewer bits has no rail check (its windows of 1.5 steps would hold most of a trace).
MIN_RAIL_BITS = 6


def adc_rails(profile):
    """The windows, V, around the ADC's lowest and highest codes of a profile that gives ``sensor.adc_range_v``
    (None otherwise, and for an ADC of fewer than :data:`MIN_RAIL_BITS` bits): ``((lo_min, lo_max), (hi_min,
    hi_max))``. With ``adc_bits`` the codes run from
    ``-range`` to ``range - lsb``; a recorder may also write the top code as ``+range``: both are in the window,
    half an lsb either side. Without bits, ``+-range`` with a relative 1e-6."""
    if "adc_range_v" not in profile.sensor:  # the default's 2 V is assumed, not known: no rail to rest on
        return None
    r = profile.adc_range_v
    bits = profile.adc_bits
    if bits is not None and int(bits) < MIN_RAIL_BITS:  # its end codes are much of its range: a trace rests there
        return None
    half = r / 2 ** int(bits) if bits else 1e-6 * r  # half an lsb
    return (-r - half, -r + half), (r - 3 * half, r + half)


def at_rails(rows, rails) -> np.ndarray:
    """(n,) bool: rows (n, m), V, with :data:`MIN_RAIL_SAMPLES` or more samples in one of ``rails``' windows
    (:func:`adc_rails`): an ADC held at its end code. Screening's ``clipped`` needs a run of 0.5 us; a fit of the
    ringing is biased by a few samples on the rail already (3-4 samples at 10 MHz: f_m 13-16 % low). A row whose
    extreme lies beyond the window is not railed (an ADC range the profile states too small)."""
    (lo0, lo1), (hi0, hi1) = rails
    low = np.count_nonzero((rows >= lo0) & (rows <= lo1), axis=1) >= MIN_RAIL_SAMPLES
    high = np.count_nonzero((rows >= hi0) & (rows <= hi1), axis=1) >= MIN_RAIL_SAMPLES
    return low | high


#: Columns of :attr:`RangeEstimates.columns`, in this order (the fields of ``fm_estimates``).
ESTIMATE_COLUMNS = ("nozzle", "fm", "fm_std", "d_mu", "viscosity", "fm_trend", "fm_rate",
                    "eta_deeply_dried_s")


@dataclass(frozen=True)
class RangeEstimates:
    """The estimates of one nozzle range of one frame.

    Attributes
    ----------
    frame_id : int
    stamp : float
        Measurement time of the trace frame, s.
    first_nozzle, n_nozzles : int
        The range of the trace message: nozzles ``first_nozzle .. first_nozzle + n_nozzles - 1``.
    columns : dict of str -> ndarray, shape (n,)
        One array per name of :data:`ESTIMATE_COLUMNS`, rows by increasing nozzle id:
        ``nozzle`` (int64), ``fm`` and ``fm_std`` (1/s), ``d_mu`` and ``viscosity``
        (Pa s), ``fm_trend`` (1/s), ``fm_rate`` (1/s^2), ``eta_deeply_dried_s`` (s; NaN
        when unknown).
    note : str
        Why the f_m baselines were not used for this range ("" when they were, or
        when there are none).
    """

    frame_id: int
    stamp: float
    first_nozzle: int
    n_nozzles: int
    columns: dict = field(default_factory=dict)
    note: str = ""

    @property
    def nozzles(self) -> np.ndarray:
        """Nozzle ids, int64 (n,)."""
        return self.columns["nozzle"]



def _default_constants(cal) -> bool:
    """``cal`` is the default head's ``vp_cal`` constants (None: they are)."""
    from .estimation import VP_CAL

    keys = ("a_sigma", "b_sigma", "a_omega", "b_omega")
    return cal is None or all(float(cal[k]) == float(VP_CAL[k]) for k in keys)

@dataclass(frozen=True)
class RowEstimates:
    """The estimates of some rows of one frame, valid or not (:meth:`DryingTracker.estimate_rows`).

    Attributes
    ----------
    columns : dict of str -> ndarray, shape (n,)
        :data:`ESTIMATE_COLUMNS`, one entry per given row in the given order; NaN
        in every estimate column of a row that was not estimated.
    reasons : ndarray of str (object), shape (n,)
        ``""`` for estimated rows; else screening's reason
        (:data:`~inkdiag_core.INVALID_REASONS`), :data:`BELOW_NOISE_REASON` (no ringing above the
        profile's sensor noise), ``"estimate_not_finite"``, :data:`NONPHYSICAL_REASON` (the estimate
        means a viscosity <= 0), :data:`AT_BOUND_REASON` (the fit ended at its search interval's edge) or
        :data:`MISFIT_REASON` (the drying model leaves much of the trace unexplained).
    method : str
        The estimator that ran.
    note : str
        Why the f_m baselines were not used ("" when they were, or there are none).
    """

    columns: dict
    reasons: np.ndarray
    method: str
    note: str = ""


@dataclass
class _Traces:
    traces: np.ndarray
    stamp: float
    sample_rate_hz: float


@dataclass
class _Drying:
    nozzles: np.ndarray  # sorted unique int64
    ranged: bool = False  # the list of one range (first_nozzle given): what it leaves out is not drying
    matched: bool = False


def _index(name, value) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
        raise ValueError(f"{name} must be a non-negative integer, got {value!r}")
    return int(value)


class DryingTracker:
    """Join trace frames and drying lists per (frame, range); estimate f_m of each joined pair.

    Parameters
    ----------
    model : InkChannelModel, optional
        The nominal channel model of the estimator (default ``InkChannelModel()``,
        the default head's); not with ``profile``.
    profile : HeadProfile, optional
        The head (complete profile): the estimator's model, ``"vp_cal"`` constants,
        deeply-dried level and the sampling its trace messages must have. None:
        the default head, with traces of any sampling.
    max_estimates : int
        At most this many listed nozzles are estimated per frame and range, lowest
        ids first (bounds the cost of one pair). An attribute: may change between calls.
    max_pending : int
        Trace messages, and drying lists, each held at most while waiting for their
        partner; beyond that the oldest is dropped (``traces_unmatched``,
        ``drying_unmatched``). Held traces are views of the caller's arrays.
    baselines : NozzleBaselines, optional
        The head's baselines with healthy f_m (``baselines.fm``): each estimate is
        taken relative to its nozzle's reading (``estimate_fm_batch(baseline_fm=)``)
        when the frame's sample rate and trace length are the baselines'. The readings
        (:attr:`~inkdiag_core.NozzleBaselines.fm_method`, :class:`~inkdiag_core.BaselineRecorder`)
        are the raw ``"vp"`` estimate, taken off ``"vp"`` and ``"vp_cal"`` estimates alike;
        the ``"vp_cal"`` readings of files before format 5 only from ``"vp_cal"`` estimates
        with the default head's constants, as they were taken.
    trend_accel_std, trend_rel_floor : float
        :class:`~inkdiag_core.FmTrend`'s ``accel_std`` (1/s^3) and ``rel_floor``.
    method : {"auto", "vp", "vp_cal"}
        The estimator (``estimate_fm_batch``'s ``method``; "auto" is "vp_cal").
    recovery_frames : int
        A nozzle's trend ends as recovered when this many frames in a row (each later than the one before)
        leave it out of their range's drying list
        (:data:`RECOVERY_FRAMES`; 1: at the first).

    Attributes
    ----------
    trends : FmTrendBank
    traces_received, drying_received : int
        Calls of :meth:`add_traces` and :meth:`add_drying`.
    ranges_joined : int
        (frame, range) pairs that met their partner; ``ranges_estimated`` of them
        gave estimates (the others listed no valid row of the range).
    traces_unmatched, drying_unmatched : int
        Dropped from a full buffer before a partner came (a drying list without a
        range counts only if it matched no range at all); traces also when a later
        frame's list for their range came first.
    rows_stale : int
        Estimates not folded into their nozzle's trend since its last update, or the recovery that
        ended it, is not before their frame's stamp (a repeated frame, one that arrived after a later one, a nozzle
        twice in a frame; :meth:`~inkdiag_core.FmTrendBank.fold_newer`): their trend columns
        are NaN and their range's note says so; folding them would take an old measurement for a
        new one.
    trend_restarts : int
        Nozzle trends restarted since the stamps went back :data:`~inkdiag_core.trend.CLOCK_RESET_S` or
        more (a restarted clock: a controller restarted, a recording replayed again).
    trends_recovered : int
        Nozzle trends ended because the drying lists of their range (ones with ``first_nozzle``) left
        the nozzle out in ``recovery_frames`` frames in a row (it recovered, e.g. purged): if it dries
        again, its trend starts anew. Only frames with a trace screening accepts, after the trend's
        last update, count.
    rows_invalid : int
        Listed rows that screening rejected, or with no ringing above the profile's sensor noise
        (:data:`BELOW_NOISE_REASON`): not estimated.
    estimates, estimates_with_baseline : int
        Nozzle estimates made; those relative to a healthy f_m.
    """

    def __init__(self, model=None, *, profile=None, max_estimates: int = 64, max_pending: int = 128,
                 baselines=None, trend_accel_std: float = 5e3, trend_rel_floor: float = 0.05,
                 method: str = "auto", max_abs_v: float | None = None, recovery_frames: int = None):
        if int(max_estimates) < 1 or int(max_pending) < 1:
            raise ValueError(f"max_estimates and max_pending must be >= 1, got {max_estimates}, {max_pending}")
        self.recovery_frames = RECOVERY_FRAMES if recovery_frames is None else int(recovery_frames)
        if self.recovery_frames < 1:
            raise ValueError(f"recovery_frames must be >= 1, got {recovery_frames!r}")
        if method not in ("auto", "vp", "vp_cal"):
            raise ValueError(f"method must be 'auto', 'vp' or 'vp_cal' (no initial state), got {method!r}")
        if profile is not None and model is not None:
            raise ValueError("give the head's model or its profile, not both")
        self.profile = profile
        self.method = method
        # a sample no sensor can produce: the row is invalid ('out_of_range'), as fdi screens it
        self.max_abs_v = (float(max_abs_v) if max_abs_v is not None
                          else (profile if profile is not None else _default_head()).max_abs_v)
        if not self.max_abs_v > 0:
            raise ValueError(f"max_abs_v must be > 0 V, got {max_abs_v!r}")
        self.vp_cal = None
        fm_deep = None
        self.min_ac_rms_v = 0.0  # rows at or below it: BELOW_NOISE_REASON (a head with a profile)
        self.noise_std_v = 0.0  # the profile's sensor noise, V (0: none known)
        self.rails_v = None  # (low, high) windows of the ADC's end codes: rows resting there are 'clipped'
        if profile is not None:
            from .estimation import vp_cal_for

            self.noise_std_v = profile.noise_std_v()
            self.min_ac_rms_v = BELOW_NOISE_FACTOR * self.noise_std_v
            self.rails_v = adc_rails(profile)

            model = profile.model()
            fm_deep = deeply_dried_fm(profile.channel_params())
            if method != "vp":
                self.vp_cal = vp_cal_for(profile)
        self.model = InkChannelModel() if model is None else model
        self.max_estimates = int(max_estimates)
        self.max_pending = int(max_pending)
        self.baselines = baselines
        self.trends = FmTrendBank(accel_std=trend_accel_std, rel_floor=trend_rel_floor, fm_deep=fm_deep)
        self._traces = OrderedDict()  # (frame_id, first_nozzle) -> _Traces
        self._drying = OrderedDict()  # (frame_id, first_nozzle or None) -> _Drying
        self.traces_received = self.drying_received = 0
        self.ranges_joined = self.ranges_estimated = 0
        self.traces_unmatched = self.drying_unmatched = 0
        self.rows_stale = self.trend_restarts = self.trends_recovered = 0
        self.rows_invalid = self.estimates = self.estimates_with_baseline = 0
        self.estimates_thinner = 0  # of the estimates: a viscosity below THIN_FACTOR x the ink's (another head?)
        self.rows_capped = 0  # listed rows of a range beyond max_estimates: not estimated
        self.rows_no_fit = 0  # rows whose f_m is no estimate (not finite, viscosity <= 0, at a bound, misfit)

    def warm_up(self) -> int:
        """Load now what a first frame would: the compiled screening kernel (numba's import and its cache, about
        1 s) and the estimator's first batch, on two healthy traces the head's profile simulates (the default head's
        without one). Nothing of the tracker's state changes. The fe node calls it at start: its first estimates
        had taken 0.5-0.6 s, and a burst of messages behind them overflowed its queues (helper-127).

        Returns
        -------
        int
            Rows the estimator ran on (2; 0 if screening refused the simulated traces, as for a head whose
            profile and model disagree).
        """
        head = self.profile if self.profile is not None else _default_head()
        rows = head.simulate({"healthy_nozzle": 2}, seed=0).traces.astype(np.float32)
        rows.flags.writeable = False  # as fe decodes them: a read-only float32 view of the message
        valid, _ = self.usable_rows(rows, head.sample_rate_hz)
        if valid.any():
            kw = {} if self.vp_cal is None else {"cal": self.vp_cal}
            with np.errstate(all="ignore"):
                estimate_fm_batch(rows[valid], self.model, head.sample_rate_hz, method=self.method, **kw)
        return int(np.count_nonzero(valid))

    @property
    def pending(self) -> tuple:
        """``(trace messages, drying lists)`` held now."""
        return len(self._traces), len(self._drying)

    def add_traces(self, traces, *, first_nozzle: int, frame_id: int, stamp: float,
                   sample_rate_hz: float) -> list:
        """One trace message: the traces of nozzles ``first_nozzle ..`` of frame ``frame_id``.

        Parameters
        ----------
        traces : array_like, shape (n_nozzles, n_samples)
            Row ``i`` is nozzle ``first_nozzle + i``, sensor units (V). Held without a copy
            until its drying list comes.
        first_nozzle, frame_id : int
        stamp : float
            Measurement time, s.
        sample_rate_hz : float

        Returns
        -------
        list of RangeEstimates
            This range's estimates if its drying list was already here (at most one).
        """
        x = np.asarray(traces)
        if x.ndim != 2 or x.shape[1] < MIN_FM_SAMPLES:
            raise ValueError(f"traces must be 2-D (n_nozzles, n_samples) with n_samples >= {MIN_FM_SAMPLES} "
                             f"(what the f_m estimators take), got shape {x.shape}")
        first, frame_id = _index("first_nozzle", first_nozzle), _index("frame_id", frame_id)
        if not (math.isfinite(sample_rate_hz) and sample_rate_hz > 0 and math.isfinite(stamp)):
            raise ValueError(f"sample_rate_hz must be > 0 and stamp finite, got {sample_rate_hz!r}, {stamp!r}")
        if self.profile is not None:
            self.profile.check_traces(x, sample_rate_hz, what="trace frame")
        self.traces_received += 1
        t = _Traces(x, float(stamp), float(sample_rate_hz))
        d = self._drying.pop((frame_id, first), None)
        if d is not None:
            return self._join(frame_id, first, t, d.nozzles, ranged=d.ranged)
        d = self._drying.get((frame_id, None))
        if d is not None and self._in_range(d.nozzles, first, x.shape[0]).size:
            d.matched = True
            return self._join(frame_id, first, t, d.nozzles)
        self._traces[(frame_id, first)] = t
        self._traces.move_to_end((frame_id, first))
        while len(self._traces) > self.max_pending:
            self._traces.popitem(last=False)
            self.traces_unmatched += 1
        return []

    def add_drying(self, frame_id: int, nozzles, *, first_nozzle: int | None = None,
                   n_nozzles: int | None = None, complete: bool = True, stamp: float | None = None) -> list:
        """One drying list: the nozzles labelled dried in one range of frame ``frame_id``.

        Parameters
        ----------
        frame_id : int
        nozzles : array_like of int, shape (m,)
            Nozzle ids (any order); empty: the range has no dried nozzle, and its
            traces are released.
        first_nozzle : int, optional
            First nozzle of the labelled range (the trace message's). None: unknown,
            the list applies to every range of the frame.
        n_nozzles : int, optional
            Nozzles in the labelled range (checked: ids must lie in it).
        complete : bool
            False: entries of the list were left out as unreadable (``msg_defs.DryingNozzles.dropped``),
            so a nozzle it leaves out may still be drying: no trend of the range ends as recovered.
        stamp : float, optional
            The list's frame time, s. Held traces of the range from an earlier frame id are dropped (their
            list is not coming) unless they are stamped after it: a controller restarted, its frame ids
            counting from 0 again, while the old frames' lists were still on their way.

        Returns
        -------
        list of RangeEstimates
            The estimates of the ranges this list completes (one for a known range).
        """
        frame_id = _index("frame_id", frame_id)
        ids = np.unique(np.asarray(nozzles, dtype=np.int64).reshape(-1))
        if ids.size and ids[0] < 0:
            raise ValueError(f"nozzle ids must be >= 0, got {ids[0]}")
        if first_nozzle is None:
            self.drying_received += 1
            return self._add_unranged(frame_id, ids)
        first = _index("first_nozzle", first_nozzle)
        if n_nozzles is not None and ids.size and not first <= ids[0] <= ids[-1] < first + _index(
                "n_nozzles", n_nozzles):
            raise ValueError(f"drying nozzles {ids[0]}..{ids[-1]} are outside the range "
                             f"{first}..{first + n_nozzles - 1}")
        self.drying_received += 1
        self._drop_stale_traces(frame_id, first, stamp)
        t = self._traces.pop((frame_id, first), None)
        if t is not None:
            return self._join(frame_id, first, t, ids, ranged=bool(complete))
        self._hold_drying((frame_id, first), _Drying(ids, ranged=bool(complete)))
        return []

    def _add_unranged(self, frame_id, ids) -> list:
        d = self._drying.get((frame_id, None))
        if d is None:
            d = _Drying(ids)
            self._hold_drying((frame_id, None), d)
        else:
            d.nozzles = np.union1d(d.nozzles, ids)
        out = []
        for key in [k for k, t in self._traces.items() if k[0] == frame_id
                    and self._in_range(ids, k[1], t.traces.shape[0]).size]:
            d.matched = True
            out += self._join(frame_id, key[1], self._traces.pop(key), d.nozzles)
        return out

    def _drop_stale_traces(self, frame_id, first, stamp=None) -> None:
        """Drop held traces of range ``first`` from frames before ``frame_id`` (their lists
        would have come before this one), but those stamped after ``stamp`` (s; a restarted controller's)."""
        later = stamp is not None and math.isfinite(stamp)
        stale = [k for k, t in self._traces.items() if k[1] == first and k[0] < frame_id
                 and not (later and t.stamp > stamp)]
        for k in stale:
            del self._traces[k]
        self.traces_unmatched += len(stale)

    def _hold_drying(self, key, d) -> None:
        self._drying[key] = d
        self._drying.move_to_end(key)
        while len(self._drying) > self.max_pending:
            _, old = self._drying.popitem(last=False)
            self.drying_unmatched += not old.matched

    @staticmethod
    def _in_range(ids, first, n):
        return ids[(ids >= first) & (ids < first + n)]

    def _join(self, frame_id, first, t: _Traces, nozzles, *, ranged: bool = False) -> list:
        """Estimate the listed nozzles of one trace message; [] when none is valid there. ``ranged``: the list is
        this range's own, so a nozzle of the range it leaves out is not drying (:meth:`_recovered`)."""
        self.ranges_joined += 1
        x = t.traces
        if ranged:
            self._recovered(first, x, nozzles, t)
        ids = self._in_range(nozzles, first, x.shape[0])
        self.trends.heard(ids, t.stamp)  # listed: no frame without it, estimated or not
        self.rows_capped += max(0, ids.size - self.max_estimates)
        ids = ids[: self.max_estimates]
        r = self.estimate_rows(np.array(x[ids - first]), ids, stamp=t.stamp, sample_rate_hz=t.sample_rate_hz)
        ok = r.reasons == ""
        if not ok.any():
            return []
        self.ranges_estimated += 1
        cols = {k: v[ok] for k, v in r.columns.items()}
        return [RangeEstimates(frame_id, t.stamp, first, int(x.shape[0]), cols, r.note)]

    def _recovered(self, first, x, listed, t: _Traces) -> None:
        """:meth:`end_recovered` of the range's nozzles with a trend that its list leaves out."""
        span = np.arange(first, first + x.shape[0], dtype=np.int64)
        gone = span[np.isin(span, self.trends.ids) & ~np.isin(span, listed)]
        if gone.size:
            self.end_recovered(gone, x[gone - first], stamp=t.stamp, sample_rate_hz=t.sample_rate_hz)

    def end_recovered(self, nozzles, traces, *, stamp: float, sample_rate_hz: float) -> int:
        """End the trends of ``nozzles`` that a drying list left out (they recovered, e.g. purged), the
        :attr:`recovery_frames`-th frame in a row that does (the frames before it are counted): only those
        whose row of ``traces`` could be estimated (:meth:`usable_rows`: a clipped, non-finite or silent row is no
        news of a recovery: fdi labels it invalid, not healthy) and whose trend was last updated before ``stamp``
        (a late frame is no news either).

        Parameters
        ----------
        nozzles : array_like of int, shape (m,)
        traces : array_like, shape (m, n_samples)
            Their traces in that frame, V.
        stamp : float
            The frame's time, s (NaN: nothing ends).
        sample_rate_hz : float

        Returns
        -------
        int
            Trends ended (also added to :attr:`trends_recovered`).
        """
        ids = np.asarray(nozzles, dtype=np.int64).reshape(-1)
        if not (ids.size and math.isfinite(stamp)):
            return 0
        valid = self.usable_rows(np.asarray(traces), sample_rate_hz)[0]
        k = self.trends.forget(ids[valid], before=stamp, after=self.recovery_frames)
        self.trends_recovered += k
        return k

    def usable_rows(self, rows, sample_rate_hz: float):
        """``(valid, reasons)`` of rows (n, n_samples), V: screening's (:func:`~inkdiag_core.screen_traces`), then
        with a profile :data:`BELOW_NOISE_REASON` (no ringing above its sensor noise) and ``clipped`` for a row
        resting on its ADC's end code (:func:`at_rails`). ``reasons`` (n,) object, "" where valid."""
        valid, reasons = screen_traces(rows, sample_rate_hz=sample_rate_hz, max_abs_v=self.max_abs_v)
        if self.min_ac_rms_v > 0 and valid.any():
            sel = np.flatnonzero(valid)
            quiet = sel[np.std(rows[sel], axis=1) <= self.min_ac_rms_v]  # the AC rms
            reasons[quiet] = BELOW_NOISE_REASON
            valid[quiet] = False
        if self.rails_v is not None and valid.any():
            sel = np.flatnonzero(valid)
            railed = sel[at_rails(rows[sel], self.rails_v)]
            reasons[railed] = "clipped"
            valid[railed] = False
        return valid, reasons

    def estimate_rows(self, traces, nozzles, *, stamp: float, sample_rate_hz: float) -> RowEstimates:
        """Screen some rows of one frame, estimate f_m of the valid ones in one batch, update their trends.

        The step the tracker runs for every joined (frame, range) pair, on its own:
        rows that screening rejects (:func:`~inkdiag_core.screen_traces`, its
        clipped run a duration at this sample rate) or whose estimate
        comes out non-finite are not estimated and never cost the other rows.

        Parameters
        ----------
        traces : array_like, shape (n, n_samples)
            Sensed traces, V.
        nozzles : array_like of int, shape (n,)
            Their nozzle ids (a nozzle's healthy f_m baseline and trend are keyed by it).
        stamp : float
            Measurement time of the frame, s; NaN: the trends are not updated (their
            columns are NaN).
        sample_rate_hz : float
            Hz.

        Returns
        -------
        RowEstimates
            One entry per row, in the given order.
        """
        rows = np.asarray(traces)
        ids = np.asarray(nozzles, dtype=np.int64).reshape(-1)
        if rows.ndim != 2 or rows.shape[0] != ids.size:
            raise ValueError(f"traces must be (n, n_samples) with one nozzle id per row, got shape "
                             f"{rows.shape} and {ids.size} ids")
        n = ids.size
        valid, reasons = self.usable_rows(rows, sample_rate_hz)
        cols = {k: np.full(n, np.nan) for k in ESTIMATE_COLUMNS}
        cols["nozzle"] = ids.copy()
        self.rows_invalid += int(n - np.count_nonzero(valid))
        method = "vp" if self.method == "vp" else "vp_cal"
        note = ""
        sel = np.flatnonzero(valid)
        if sel.size:
            baseline_fm, with_base, note = self._baseline_fm(ids[sel], sample_rate_hz, rows.shape[1])
            kw = {} if self.vp_cal is None else {"cal": self.vp_cal}
            est = estimate_fm_batch(rows[sel], self.model, sample_rate_hz, baseline_fm=baseline_fm,
                                    method=self.method, **kw)
            bad = ~np.isfinite(est.fm)
            reasons[sel[bad]] = "estimate_not_finite"
            # a viscosity <= 0 is no nozzle the channel model describes (an empty channel, a bubble): not an estimate
            visc = np.asarray(est.viscosity, dtype=float)  # NaN for a matrix model, which has no viscosity
            nonphysical = ~bad & np.isfinite(visc) & (visc <= 0)
            reasons[sel[nonphysical]] = NONPHYSICAL_REASON
            bad |= nonphysical
            edge = ~bad & est.at_bound
            reasons[sel[edge]] = AT_BOUND_REASON
            bad |= edge
            misfit = ~bad & (est.residual_rel > MISFIT_REL)  # NaN (no residual): False
            # a residual of noise alone is no misfit; without a noise figure (no profile, or noise_std_v 0) the
            # share alone decides, so a dried row at a low SNR may be called one (fe and estimate have profiles)
            if self.noise_std_v > 0 and misfit.any():
                misfit &= est.residual_rel * np.std(rows[sel], axis=1) > MISFIT_NOISE_FACTOR * self.noise_std_v
            reasons[sel[misfit]] = MISFIT_REASON
            bad |= misfit
            self.rows_no_fit += int(np.count_nonzero(bad))
            for k, v in zip(("fm", "fm_std", "d_mu", "viscosity"), (est.fm, est.std, est.d_mu, est.viscosity)):
                cols[k][sel] = v
            good = sel[~bad]
            self.estimates += int(good.size)
            mu = getattr(self.model, "params", None)
            if mu is not None:  # a row far thinner than the ink: no drying, a profile of another head or ink
                self.estimates_thinner += int(np.count_nonzero(cols["viscosity"][good] < THIN_FACTOR * mu.mu))
            self.estimates_with_baseline += int(np.count_nonzero(with_base & ~bad))  # of the rows estimated
            if good.size and math.isfinite(stamp):  # each nozzle once, and only after its last update
                trend, rate, eta, folded, restarted = self.trends.fold_newer(
                    stamp, ids[good], cols["fm"][good], cols["fm_std"][good])
                cols["fm_trend"][good], cols["fm_rate"][good], cols["eta_deeply_dried_s"][good] = trend, rate, eta
                note = "; ".join(filter(None, (note, self._fold_note(stamp, ids[good], folded, restarted))))
        for k in ("fm", "fm_std", "d_mu", "viscosity"):
            cols[k][reasons != ""] = np.nan
        return RowEstimates(cols, reasons, method, note)

    def _fold_note(self, stamp, ids, folded, restarted) -> str:
        """Count the estimates :meth:`FmTrendBank.fold_newer` left out or restarted with; say so (or "")."""
        n_stale, n_restart = int(folded.size - np.count_nonzero(folded)), int(np.count_nonzero(restarted))
        self.rows_stale += n_stale
        self.trend_restarts += n_restart
        said = []
        if n_stale:
            said.append(f"{n_stale} estimate(s) at {stamp:.6f} s not folded into their nozzle's trend, whose last "
                        f"update, or the recovery that ended it, is not before it (a repeated or late frame, or a "
                        f"nozzle twice in a frame; nozzle "
                        f"{ids[~folded][0]}{', ...' if n_stale > 1 else ''})")
        if n_restart:
            said.append(f"{n_restart} nozzle trend(s) restarted at {stamp:.6f} s: the stamps went back "
                        f"{CLOCK_RESET_S:g} s or more (a restarted clock)")
        return "; ".join(said)

    def _baseline_fm(self, ids, sample_rate_hz, n_samples):
        """``(healthy f_m of ids or None, whether each id has one, why not used)``."""
        b = self.baselines
        none = np.zeros(len(ids), dtype=bool)
        if b is None or b.fm is None:
            return None, none, ""
        if b.fm_method is None and (self.method == "vp" or not _default_constants(self.vp_cal)):
            # a file before format 5: default-head vp_cal readings, another estimator's on this head
            return None, none, ("the f_m baselines are vp_cal readings with the default head's constants (a file "
                          "recorded before format 5): estimated without them; record the baselines again")
        if (sample_rate_hz, n_samples) != (b.sample_rate_hz, b.n_samples):
            return None, none, (f"traces of {sample_rate_hz:g} Hz x {n_samples} samples, the f_m baselines "
                          f"{b.sample_rate_hz:g} Hz x {b.n_samples}: estimated without them")
        has, fm = b.lookup_fm(ids)
        return fm, has, ""
