"""A foreign head end to end through the ``inkdiag`` command, as a user runs it.

Traces come from ``tests/foreign_head.py`` (independent code, not inkdiag's
simulator). From a nominal profile and 300 recorded healthy traces:
``calibrate`` -> ``train`` -> ``label`` every class -> ``estimate`` the dried
rows. Small training and test sets keep it under a minute; the full-size run
is ``scripts/report heads`` (reports/heads.md).
"""

import csv
import subprocess
import sys

import numpy as np
import pytest

import foreign_head as fh
from inkdiag_core import FaultClass, HeadProfile
from inkdiag_core.faults import DRIED_CLASSES

HEALTHY = {FaultClass.OK_SIGNAL.value, FaultClass.HEALTHY_NOZZLE.value}


def inkdiag(*args):
    r = subprocess.run([sys.executable, "-m", "inkdiag_ros.cli", *map(str, args)], capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, f"inkdiag {args[0]} exit {r.returncode}: {r.stderr[-1500:]}"
    return r


def rows(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    d = tmp_path_factory.mktemp("h20")
    fh.write_nominal_yaml(d / "nominal.yaml", "h20")
    fh.write_recording(d / "healthy.npz", fh.simulate_foreign("h20", {"healthy_nozzle": 300}, 10))
    test = fh.simulate_foreign("h20", {c.value: 40 for c in FaultClass}, 11)
    fh.write_recording(d / "test.npz", test)
    dried = fh.simulate_foreign("h20", {c.value: 30 for c in DRIED_CLASSES}, 12)
    fh.write_recording(d / "dried.npz", dried)
    inkdiag("calibrate", d / "healthy.npz", "--nominal", d / "nominal.yaml", "--out", d / "head.yaml")
    inkdiag("train", "--profile", d / "head.yaml", "--out", d / "model.joblib", "--n-per-class", 300, "--quiet")
    inkdiag("label", d / "test.npz", "--model", d / "model.joblib", "--out", d / "labels.csv")
    inkdiag("estimate", d / "dried.npz", "--profile", d / "head.yaml", "--out", d / "fm.csv")
    return d, test, dried


def test_calibrated_profile_is_complete_and_has_the_heads_mode(run):
    d, _, _ = run
    prof = HeadProfile.load(d / "head.yaml")
    true = HeadProfile.from_dict({"schema": "inkdiag.head_profile", "schema_version": 1,
                                  **{k: fh.FOREIGN_HEADS["h20"][k] for k in ("sampling", "channel", "drive", "sensor")}})
    assert prof.is_complete and prof.calibration["method"] == "inkdiag calibrate"
    assert prof.healthy_mode()[0] == pytest.approx(true.healthy_mode()[0], rel=0.01)


def test_labels_detect_and_isolate_the_foreign_heads_faults(run):
    d, test, _ = run
    out = rows(d / "labels.csv")
    assert list(out[0])[:6] == ["row", "nozzle", "frame_id", "class", "confidence", "reason"]
    assert len(out) == len(test["labels"])
    pred = np.array([r["class"] for r in out], dtype=object)
    truth = np.asarray(test["labels"], dtype=object)[[int(r["row"]) for r in out]]
    fd = np.mean([(p in HEALTHY) == (t in HEALTHY) for p, t in zip(pred, truth)])
    assert fd >= 0.97
    assert np.mean(pred == truth) >= 0.80
    # classes whose physics carries over cleanly are isolated almost always
    for c in ("empty_channel_1", "empty_channel_2", "small_air_bubble", "fully_blocked"):
        assert np.mean(pred[truth == c] == c) >= 0.9, c


def test_estimates_of_the_dried_rows(run):
    d, _, dried = run
    out = rows(d / "fm.csv")
    assert list(out[0])[:6] == ["row", "nozzle", "fm", "fm_std", "d_mu", "viscosity"]
    idx = np.array([int(r["row"]) for r in out])
    d_mu = np.array([float(r["d_mu"]) for r in out])
    true = (np.asarray(dried["mu_nozzle"]) - np.asarray(dried["mu"]))[idx]  # each trace's own ink viscosity
    err = np.abs(d_mu - true) / true
    # a sanity bound, not the 10 % target: this small calibrated run gives 10-15 % (reports/heads.md)
    assert np.isfinite(err).all() and np.median(err) <= 0.2
