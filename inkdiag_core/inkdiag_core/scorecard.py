"""Scorecard of a simulated run: the graph's outputs against the simulator's ground truth.

Pure Python on decoded messages (no ROS). Label accuracy counts every nozzle
of every frame that has both a truth and a labels message; the two healthy
classes count as one (the simulator's healthy nozzles are jetting-pulse
traces, and ``ok_signal`` vs ``healthy_nozzle`` is an operating condition, not a
fault). A nozzle labelled ``unknown`` (the model's open-set layer, issue 16)
counts as a wrong label (the simulator's classes are all known) but as a
detected fault: ``label_scores`` counts them per true class and scores fault
detection with them. f_m tracking compares each estimate (and its trend) with the true f_m
of the same nozzle in the same frame.
"""

from __future__ import annotations

from collections import Counter, OrderedDict

import numpy as np

from .faults import HEALTHY_VALUES, FaultClass
from .openset import UNKNOWN

__all__ = ["Scorecard", "HEALTHY"]

HEALTHY = HEALTHY_VALUES  # former local spelling, kept for imports


def _norm(c: str) -> str:
    return "healthy" if c in HEALTHY_VALUES else c


class Scorecard:
    """The graph's decoded outputs scored against the simulator's truth, frame by frame.

    Parameters
    ----------
    keep_frames : int
        Frames of truth, labels and unmatched estimates kept (oldest dropped first).
    """

    def __init__(self, keep_frames: int = 10_000):
        self.truth = OrderedDict()
        self.labels = OrderedDict()
        self.fm_rows = []  # (frame_id, nozzle, fm_est, fm_trend, fm_true)
        self._pending_est = OrderedDict()
        self.keep = keep_frames

    def _trim(self, d):
        while len(d) > self.keep:
            d.popitem(last=False)

    def add_truth(self, t) -> None:
        self.truth[t.frame_id] = t
        self._trim(self.truth)
        if t.frame_id in self._pending_est:
            self._match_estimates(self._pending_est.pop(t.frame_id))

    def add_labels(self, report) -> None:
        self.labels[report.frame_id] = report
        self._trim(self.labels)

    def add_estimates(self, est) -> None:
        if est.frame_id in self.truth:
            self._match_estimates(est)
        else:
            self._pending_est[est.frame_id] = est
            self._trim(self._pending_est)

    def _match_estimates(self, est) -> None:
        faults = {nz: fm for nz, _, fm, _ in self.truth[est.frame_id].faults}
        for nz, fm, trend in zip(est.nozzles.tolist(), est.column("fm"), est.column("fm_trend")):
            if nz in faults and faults[nz] != 0.0:
                self.fm_rows.append((est.frame_id, nz, float(fm), float(trend), faults[nz]))

    def label_scores(self) -> dict:
        total = correct = 0
        per_class = Counter()
        per_class_ok = Counter()
        per_class_unknown = Counter()
        missed = false_alarms = n_faults = 0
        for fid, rep in self.labels.items():
            t = self.truth.get(fid)
            if t is None:
                continue
            true = {nz: c for nz, c, _, _ in t.faults}
            got = {nz: c for nz, c, _ in rep.faults}
            invalid = {nz for nz, _ in rep.invalid}
            for nz in range(rep.first_nozzle, rep.first_nozzle + rep.n_nozzles):
                if nz in invalid:
                    continue
                tc = _norm(true.get(nz, FaultClass.HEALTHY_NOZZLE.value))
                gc = _norm(got.get(nz, FaultClass.HEALTHY_NOZZLE.value))
                total += 1
                per_class[tc] += 1
                if tc == gc:
                    correct += 1
                    per_class_ok[tc] += 1
                per_class_unknown[tc] += gc == UNKNOWN
                n_faults += tc != "healthy"
                missed += tc != "healthy" and gc == "healthy"  # an unknown is a detected fault
                false_alarms += tc == "healthy" and gc != "healthy"
        n_healthy = total - n_faults
        return {
            "frames": sum(1 for f in self.labels if f in self.truth),
            "nozzle_labels": total,
            "accuracy": correct / total if total else float("nan"),
            "per_class": {c: (per_class_ok[c], per_class[c]) for c in sorted(per_class)},
            "unknown": sum(per_class_unknown.values()),
            "unknown_per_class": {c: per_class_unknown[c] for c in sorted(per_class)},
            "fd_missed": missed / n_faults if n_faults else float("nan"),
            "fd_false_alarms": false_alarms / n_healthy if n_healthy else float("nan"),
        }

    def fm_scores(self) -> dict:
        if not self.fm_rows:
            return {"estimates": 0}
        a = np.array([r[2:] for r in self.fm_rows])
        est_err = np.abs(a[:, 0] - a[:, 2]) / np.abs(a[:, 2])
        ok = np.isfinite(a[:, 1])
        trend_err = np.abs(a[ok, 1] - a[ok, 2]) / np.abs(a[ok, 2])
        first, last = self.fm_rows[0], self.fm_rows[-1]
        return {
            "estimates": len(self.fm_rows),
            "nozzles": sorted({r[1] for r in self.fm_rows}),
            "median_rel_error": float(np.median(est_err)),
            "p90_rel_error": float(np.percentile(est_err, 90)),
            "trend_median_rel_error": float(np.median(trend_err)) if trend_err.size else float("nan"),
            "first": first, "last": last,
        }

    def format(self) -> str:
        ls, fs = self.label_scores(), self.fm_scores()
        lines = ["scorecard against the simulator's ground truth"]
        if ls["nozzle_labels"]:
            lines.append(f"  labels: {ls['frames']} frames, {ls['nozzle_labels']} nozzle labels, "
                         f"accuracy {_pct(ls['accuracy'], 1)}; {ls['unknown']} called unknown; fault detection: "
                         f"missed {_pct(ls['fd_missed'], 2, 'no faulty nozzle')}, "
                         f"false alarms {_pct(ls['fd_false_alarms'], 2, 'no healthy nozzle')}")
        else:
            lines.append("  labels: no labelled frame matched a frame of the ground truth")
        for c, (ok, n) in ls["per_class"].items():
            lines.append(f"    {c:<24} {ok:>6}/{n:<6} {100 * ok / n:5.1f} %  unknown {ls['unknown_per_class'][c]}")
        if fs["estimates"]:
            f0, f1 = fs["first"], fs["last"]
            lines += [
                f"  f_m of drying nozzles {fs['nozzles']}: {fs['estimates']} estimates, per-frame "
                f"error median {100 * fs['median_rel_error']:.1f} % (p90 {100 * fs['p90_rel_error']:.1f} %), "
                f"trend error median {100 * fs['trend_median_rel_error']:.1f} %",
                f"    nozzle {f0[1]}: true f_m {f0[4]:.3g} -> {f1[4]:.3g} 1/s, "
                f"estimated {f0[2]:.3g} -> {f1[2]:.3g} 1/s (trend {f1[3]:.3g})",
            ]
        else:
            lines.append("  f_m: no estimate matched a drying nozzle of the ground truth")
        return "\n".join(lines)


def _pct(fraction: float, digits: int, none: str = "") -> str:
    """``fraction`` in per cent with ``digits`` decimals, or ``n/a (none)`` where it is NaN (nothing to count)."""
    if np.isnan(fraction):
        return f"n/a ({none})" if none else "n/a"
    return f"{100 * fraction:.{digits}f} %"
