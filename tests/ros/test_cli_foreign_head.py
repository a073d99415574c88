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


@pytest.fixture(scope="module")
def commissioned(run):
    """The same calibrated head, commissioned: 8 healthy frames of every nozzle, then later frames
    of the same nozzles (``nozzle_seed``: a nozzle keeps its geometry, actuator, drive and gain)."""
    d, _, _ = run
    n = 40 * len(FaultClass)
    test = fh.simulate_foreign("h20", {c.value: 40 for c in FaultClass}, 13, nozzles=np.arange(n), nozzle_seed=14)
    fh.write_recording(d / "test_c.npz", test)
    fh.write_recording(d / "commission.npz", fh.simulate_foreign(
        "h20", {"healthy_nozzle": 8 * n}, 15, nozzles=np.tile(np.arange(n), 8), nozzle_seed=14))
    inkdiag("baseline", d / "commission.npz", "--profile", d / "head.yaml", "--out", d / "baselines.npz",
            "--fm-frames", 0)
    inkdiag("train", "--profile", d / "head.yaml", "--out", d / "model_b.joblib", "--n-per-class", 300, "--baseline",
            "--quiet")
    inkdiag("label", d / "test_c.npz", "--model", d / "model.joblib", "--out", d / "labels_plain.csv")
    inkdiag("label", d / "test_c.npz", "--model", d / "model_b.joblib", "--baselines", d / "baselines.npz",
            "--out", d / "labels_b.csv")
    return d, np.asarray(test["labels"], dtype=object)


def test_a_commissioned_heads_baselines_isolate_what_single_traces_blur(commissioned):
    """Each nozzle against its own healthy baseline: partially blocked and dried nozzles, which the
    spread between nozzles blurs in single traces, are told apart far more often (reports/heads.md,
    *calibrated + baselines*)."""
    d, truth = commissioned
    plain = np.array([r["class"] for r in rows(d / "labels_plain.csv")], dtype=object)
    out = rows(d / "labels_b.csv")
    assert all(r["baseline"] == "1" for r in out)  # every nozzle has its baseline
    with_b = np.array([r["class"] for r in out], dtype=object)
    overlap = np.isin(truth, ["partially_blocked"] + [c.value for c in DRIED_CLASSES])
    acc_plain, acc_b = np.mean(plain[overlap] == truth[overlap]), np.mean(with_b[overlap] == truth[overlap])
    assert acc_b >= acc_plain + 0.04, (acc_plain, acc_b)
    assert np.mean(with_b == truth) >= 0.92 and np.mean(with_b == truth) > np.mean(plain == truth)
