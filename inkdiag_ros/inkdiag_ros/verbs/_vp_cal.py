"""Say on stderr when a verb first fits a head's ``vp_cal`` constants (a few seconds), and fit them."""

from __future__ import annotations

import sys


def fit_vp_cal_said(profile, verb: str) -> None:
    """Fit ``profile``'s ``vp_cal`` constants now if it needs a fit (:func:`vp_cal_needs_fit`), saying so
    on stderr before and after; the fit is kept for the process (:func:`vp_cal_for`)."""
    from inkdiag_core.estimation import vp_cal_for, vp_cal_needs_fit

    if not vp_cal_needs_fit(profile):
        return
    print(f"inkdiag {verb}: fitting the vp_cal constants of head {profile.name!r} (first use of this head "
          "in this process)...", file=sys.stderr, flush=True)
    cal = vp_cal_for(profile)
    if "seconds" in cal:
        print(f"inkdiag {verb}: vp_cal fitted in {cal['seconds']:.1f} s on {cal['n_traces']} simulated traces",
              file=sys.stderr, flush=True)
