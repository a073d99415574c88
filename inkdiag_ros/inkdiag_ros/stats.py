"""Counters of the FDI node, kept out of the node (as ``ros2 topic hz`` keeps its statistics)."""

from __future__ import annotations

import threading
import time
from collections import Counter

from msg_defs.labels import HEALTHY_CLASSES, INVALID_KEY


#: A diagnostics period whose rows are more than this fraction faults or ``unknown`` is a warning:
#: a working head has a few faulty nozzles; most of them at once is a failing head, or a model or
#: baselines of another head (the healthy gate then clears nothing and every nozzle looks unlike
#: its baseline).
MOSTLY_FAULTY = 0.5
#: Rows :data:`MOSTLY_FAULTY` is judged on: the rows since the last judgement, over as many periods as a
#: small head needs to label them (a 64-nozzle head at 5 frames/s: about 3 s); the verdict holds until the
#: next judgement.
MOSTLY_FAULTY_MIN_ROWS = 1000
#: With the healthy gate in use, a judgement (over as many rows as :data:`MOSTLY_FAULTY_MIN_ROWS`) whose
#: healthy rows with a baseline the gate cleared fewer than this fraction of is a warning: on a head whose
#: baselines are its own it clears about 99 % of them (reports/gate.md: 99.40 %); baselines of another head,
#: or of renumbered nozzles, match few (helper-88: 14 of 64 rows cleared, no warning: 25 % faults, under half).
GATE_MIN_CLEARED = 0.5


class FdiStats:
    """What the FDI node has seen; :meth:`period` turns it into a diagnostics snapshot.

    The node's executor thread updates it, and with a labelling process its
    collector thread too; every method holds one lock, so a snapshot never sees
    half an update.
    """

    def __init__(self):
        self._lock = threading.Lock()
        self.frames_received = 0
        self.frames_labelled = 0
        self.frames_malformed = 0
        self.frames_failed = 0
        self.frames_dropped = 0
        self.batches = 0
        self.busy_s = 0.0
        self.rows_invalid = 0
        self.traces_labelled = 0
        self.rows_with_baseline = 0
        self.rows_gate_cleared = 0
        self.rows_faulty = 0  # valid rows of a fault class or unknown
        self.counts = Counter()
        self.last_error = ""
        self.config_error = ""  # a setting the node could not honour (it runs without it)
        self._mark = (time.monotonic(), 0, 0, 0, 0, 0, 0, 0.0)
        self._fault_window = (0, 0)  # traces_labelled, rows_faulty at the last mostly-faulty judgement
        self._mostly_faulty = ""  # that judgement's warning, or ""
        self.gate_in_use = False  # the labeller's healthy gate takes the rows with a reference (the node sets it)
        self.rows_gate_eligible = 0  # healthy rows with a baseline (at least): what the gate should have cleared
        self._gate_window = (0, 0)  # rows_gate_eligible, rows_gate_cleared at the last gate judgement
        self._gate_misses = ""

    def malformed(self, reason: str) -> None:
        with self._lock:
            self.frames_malformed += 1
            self.last_error = reason

    def failed(self, reason: str) -> None:
        with self._lock:
            self.frames_failed += 1
            self.last_error = reason

    def misconfigured(self, reason: str) -> None:
        """A setting the node runs without (e.g. baselines that did not load): WARN until fixed."""
        with self._lock:
            self.config_error = reason
            self.last_error = reason

    def dropped(self, reason: str) -> None:
        with self._lock:
            self.frames_dropped += 1
            self.last_error = reason

    def batch(self, n_frames: int, seconds: float) -> None:
        """One labelling pass over ``n_frames`` frames took ``seconds`` (wall clock)."""
        with self._lock:
            self.batches += 1
            self.busy_s += seconds

    def received(self) -> None:
        with self._lock:
            self.frames_received += 1

    def labelled(self, counts: dict, n_rows: int, n_baseline: int = 0, n_gate_cleared: int = 0) -> None:
        with self._lock:
            self.frames_labelled += 1
            self.traces_labelled += n_rows
            self.rows_with_baseline += n_baseline
            self.rows_gate_cleared += n_gate_cleared
            self.counts.update(counts)
            self.rows_invalid += counts.get(INVALID_KEY, 0)
            n_healthy = sum(counts.get(c, 0) for c in HEALTHY_CLASSES)
            self.rows_faulty += n_rows - counts.get(INVALID_KEY, 0) - n_healthy
            if self.gate_in_use:  # healthy rows that have a baseline, at least this many
                self.rows_gate_eligible += max(0, n_healthy + n_baseline - (n_rows - counts.get(INVALID_KEY, 0)))

    def since_period(self) -> float:
        """Seconds since the last :meth:`period` (or since this object was made)."""
        with self._lock:
            return time.monotonic() - self._mark[0]

    def period(self, model_loaded: bool):
        """``(level, message, values, counts, gate_cleared)`` over the time since the last call.

        ``counts`` is a copy of the cumulative rows per label (``"invalid"`` always, 0 before
        any labelled frame); ``gate_cleared`` the cumulative rows the healthy gate cleared.
        """
        with self._lock:
            return self._period(model_loaded) + ({INVALID_KEY: 0, **self.counts}, self.rows_gate_cleared)

    def _period(self, model_loaded: bool):
        now = time.monotonic()
        t0, f0, n0, m0, i0, b0, lf0, busy0 = self._mark
        dt = max(now - t0, 1e-9)
        d_frames = self.frames_labelled - f0
        d_bad = self.frames_malformed + self.frames_failed + self.frames_dropped - m0
        d_invalid = self.rows_invalid - i0
        values = {
            "frames_received": self.frames_received,
            "frames_labelled": self.frames_labelled,
            "frames_malformed": self.frames_malformed,
            "frames_failed": self.frames_failed,
            "frames_dropped": self.frames_dropped,
            "rows_invalid": self.rows_invalid,
            "rows_with_baseline": self.rows_with_baseline,
            "rows_faulty": self.rows_faulty,
            "frames_per_s": d_frames / dt,
            "traces_per_s": (self.traces_labelled - n0) / dt,
            "frames_per_batch": (self.frames_labelled - lf0) / max(self.batches - b0, 1),
            "labeller_busy": (self.busy_s - busy0) / dt,
            "last_error": self.last_error,
            "config_error": self.config_error,
        }
        w_rows, w_faulty = self.traces_labelled - self._fault_window[0], self.rows_faulty - self._fault_window[1]
        if w_rows >= MOSTLY_FAULTY_MIN_ROWS:  # judged on the rows since the last judgement; held until the next
            self._mostly_faulty = "" if w_faulty <= MOSTLY_FAULTY * w_rows else (
                f"{100 * w_faulty / w_rows:.0f} % of the last {w_rows} rows were faults or unknown: a failing head, a "
                "sensor gain other than the head profile's, or a model or baselines that are not this head's (another "
                "head, renumbered nozzles: record the baselines again)")
            self._fault_window = (self.traces_labelled, self.rows_faulty)
        w_el, w_cl = self.rows_gate_eligible - self._gate_window[0], self.rows_gate_cleared - self._gate_window[1]
        if w_el >= MOSTLY_FAULTY_MIN_ROWS:  # as above: judged on the rows since the last judgement
            self._gate_misses = "" if w_cl >= GATE_MIN_CLEARED * w_el else (
                f"the healthy gate cleared {w_cl} of the last {w_el} healthy rows with a baseline (about 99 % on a "
                "head whose baselines are its own): baselines of another head, of renumbered nozzles, or from "
                "before the head changed (record the baselines again)")
            self._gate_window = (self.rows_gate_eligible, self.rows_gate_cleared)
        warnings = [w for w in (
            self.config_error,
            d_bad and f"{d_bad} malformed, failed or dropped frame(s) in the last {dt:.1f} s",
            self._mostly_faulty,
            self._gate_misses,
            d_invalid and f"{d_invalid} invalid row(s) in the last {dt:.1f} s") if w]
        if not model_loaded:  # and why (fdi's config_error: no model_path, a missing or refused model file)
            level, message = "error", f"{self.config_error or 'no FDI model loaded'}: frames are not labelled"
        elif warnings:
            level, message = "warn", "; ".join(warnings)
        elif self.frames_received == 0:
            level, message = "stale", "no trace frame received yet"
        elif d_frames == 0:
            level, message = "stale", f"no trace frame labelled in the last {dt:.1f} s"
        else:
            level, message = "ok", f"{d_frames} frame(s) labelled in the last {dt:.1f} s"
        self._mark = (now, self.frames_labelled, self.traces_labelled,
                      self.frames_malformed + self.frames_failed + self.frames_dropped, self.rows_invalid,
                      self.batches, self.frames_labelled, self.busy_s)
        return level, message, values


#: The fe node's counters on ``/diagnostics``, in this order (the tracker's, then the node's).
FE_KEYS = ("traces_received", "drying_received", "frames_malformed", "ranges_joined", "ranges_estimated",
           "estimates", "estimates_published", "estimates_with_baseline", "rows_invalid", "rows_no_fit", "rows_capped",
           "traces_unmatched", "drying_unmatched", "rows_stale", "trend_restarts", "trends_recovered",
           "estimates_thinner", "last_error")
#: Of :data:`FE_KEYS`, the counters whose rise in a period is a warning: input fe could not use.
FE_WARN_KEYS = {"frames_malformed": "malformed message(s)", "traces_unmatched": "trace message(s) never joined by "
                "their drying list", "drying_unmatched": "drying list(s) never joined by their traces",
                "rows_invalid": "listed row(s) screened out (invalid, silent or on the ADC's rail)",
                "rows_no_fit": "listed row(s) the drying model does not fit (no estimate)",
                "rows_capped": "listed row(s) beyond max_estimates_per_frame"}


class FeStats:
    """The fe node's ``/diagnostics`` snapshot from its tracker's counters (one thread: the executor's)."""

    def __init__(self):
        self._mark = (time.monotonic(), {})
        self.last_error = ""

    def period(self, tracker, frames_malformed: int, estimates_published: int):
        """``(level, message, values)`` over the time since the last call: WARN when input fe could not use
        arrived in the period (:data:`FE_WARN_KEYS`), STALE when neither traces nor drying lists arrived, else OK.
        ``values``: :data:`FE_KEYS`, cumulative since the node started."""
        now = time.monotonic()
        t0, before = self._mark
        dt = max(now - t0, 1e-9)
        values = {k: getattr(tracker, k, 0) for k in FE_KEYS}
        values.update(frames_malformed=frames_malformed, estimates_published=estimates_published,
                      last_error=self.last_error)
        warnings = [f"{d} {what} in the last {dt:.1f} s" for k, what in FE_WARN_KEYS.items()
                    if (d := values[k] - before.get(k, 0)) > 0]
        fresh = values["traces_received"] + values["drying_received"] - before.get("traces_received", 0) \
            - before.get("drying_received", 0)
        if warnings:
            level, message = "warn", "; ".join(warnings)
        elif not fresh:
            level, message = "stale", f"no trace message or drying list received in the last {dt:.1f} s"
        else:
            level, message = "ok", (f"{values['estimates_published'] - before.get('estimates_published', 0)} "
                                    f"estimate message(s) published in the last {dt:.1f} s")
        self._mark = (now, {k: v for k, v in values.items() if k != "last_error"})
        return level, message, values
