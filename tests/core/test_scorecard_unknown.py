"""Scorecard with `unknown` labels (issue 16): a wrong class, but a detected fault."""

import numpy as np

from inkdiag_core.scorecard import Scorecard
from msg_defs import LabelsReport, truth


def test_unknown_is_counted_wrong_for_the_class_and_detected_for_fd():
    t = truth.truth_from_arrays(frame_id=1, stamp=0.0, first_nozzle=0,
                                classes=np.array(["healthy_nozzle", "fully_blocked", "healthy_nozzle", "deeply_dried"],
                                                 dtype=object), fm=np.ones(4), mu_nozzle=np.ones(4))
    rep = LabelsReport.from_arrays(frame_id=1, stamp=0.0, first_nozzle=0,
                                   classes=np.array(["unknown", "unknown", "ok_signal", "deeply_dried"], dtype=object),
                                   confidence=np.array([0.995, 0.999, 0.9, 0.8]), valid=np.ones(4, dtype=bool),
                                   reasons=np.array([""] * 4, dtype=object), model_id="m")
    sc = Scorecard()
    sc.add_truth(t)
    sc.add_labels(rep)
    s = sc.label_scores()
    assert s["accuracy"] == 0.5 and s["unknown"] == 2
    assert s["unknown_per_class"] == {"deeply_dried": 0, "fully_blocked": 1, "healthy": 1}
    assert s["fd_missed"] == 0.0 and s["fd_false_alarms"] == 0.5
    assert "2 called unknown" in sc.format()


def test_a_scorecard_with_nothing_to_count_says_so_and_prints_no_nan():
    sc = Scorecard()
    assert "no labelled frame matched" in sc.format() and "nan" not in sc.format()
    t = truth.truth_from_arrays(frame_id=1, stamp=0.0, first_nozzle=0,
                                classes=np.array(["healthy_nozzle", "healthy_nozzle"], dtype=object),
                                fm=np.ones(2), mu_nozzle=np.ones(2))
    rep = LabelsReport.from_arrays(frame_id=1, stamp=0.0, first_nozzle=0,
                                   classes=np.array(["healthy_nozzle", "healthy_nozzle"], dtype=object),
                                   confidence=np.ones(2), valid=np.ones(2, dtype=bool),
                                   reasons=np.array([""] * 2, dtype=object), model_id="m")
    sc.add_truth(t)
    sc.add_labels(rep)
    text = sc.format()
    assert "accuracy 100.0 %" in text and "missed n/a (no faulty nozzle)" in text and "nan" not in text
