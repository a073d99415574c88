"""One vocabulary of class groups: defined in inkdiag_core.faults, used everywhere, msg_defs pinned to it."""

import inspect
import pathlib
import re

import numpy as np
import pytest

import msg_defs
from inkdiag_core import fdi, kpis, openset, residual
from inkdiag_core import estimation
from inkdiag_core.faults import (
    DRIED_CLASSES,
    DRIED_VALUES,
    FAULT_CLASSES,
    FAULT_VALUES,
    HEALTHY_CLASSES,
    HEALTHY_VALUES,
    MECHANISMS,
    FaultClass,
    class_values,
    dried_mask,
    healthy_mask,
    is_dried,
    is_healthy,
)
from inkdiag_core import scorecard
from inkdiag_core.simulation import scenario
from msg_defs import truth

ROOT = pathlib.Path(__file__).resolve().parents[2]


def test_groups_follow_the_mechanisms_and_partition_the_classes():
    assert HEALTHY_CLASSES == {c for c in FaultClass if MECHANISMS[c].kind == "healthy"}
    assert set(DRIED_CLASSES) == {c for c in FaultClass if MECHANISMS[c].kind == "dried"}
    assert [MECHANISMS[c].low for c in DRIED_CLASSES] == sorted(MECHANISMS[c].low for c in DRIED_CLASSES)
    assert HEALTHY_VALUES == ("ok_signal", "healthy_nozzle")
    assert DRIED_VALUES == tuple(c.value for c in DRIED_CLASSES)
    assert set(FAULT_CLASSES) | HEALTHY_CLASSES == set(FaultClass) and not set(FAULT_CLASSES) & HEALTHY_CLASSES
    assert FAULT_VALUES == tuple(c.value for c in FAULT_CLASSES) and len(FAULT_CLASSES) == 10
    assert set(scenario.RANDOM_FAULT_CLASSES) == set(FAULT_CLASSES) - set(DRIED_CLASSES)


def test_predicates_and_masks_take_members_and_values():
    assert is_dried("deeply_dried") and is_dried(FaultClass.SLIGHTLY_DRIED) and not is_dried("ok_signal")
    assert is_healthy(FaultClass.HEALTHY_NOZZLE) and not is_healthy("fully_blocked")
    with pytest.raises(ValueError, match="unknown fault class"):
        is_dried("dry")
    labels = ["ok_signal", FaultClass.HEALTHY_NOZZLE, "deeply_dried", FaultClass.SLIGHTLY_DRIED, "", 0]
    assert healthy_mask(labels).tolist() == [True, True, False, False, False, False]
    assert dried_mask(labels).tolist() == [False, False, True, True, False, False]
    assert healthy_mask(np.array(["healthy_nozzle", "fully_blocked"])).tolist() == [True, False]
    assert healthy_mask([]).shape == (0,)
    assert class_values([FaultClass.OK_SIGNAL, "x"]).tolist() == ["ok_signal", "x"]


def test_msg_defs_wire_copy_is_pinned_to_the_core():
    # msg_defs must not import the core, so it keeps its own copy of the value tuples
    assert msg_defs.HEALTHY_CLASSES == HEALTHY_VALUES
    assert msg_defs.DRIED_CLASSES == DRIED_VALUES
    assert msg_defs.UNKNOWN_CLASS == openset.UNKNOWN
    assert inspect.signature(truth.truth_from_arrays).parameters["healthy"].default is msg_defs.HEALTHY_CLASSES
    for path in (ROOT / "msg_defs" / "msg_defs").glob("*.py"):
        assert not re.search(r"^\s*(from|import)\s+inkdiag_core", path.read_text(), re.M), path


def test_core_ros_and_scripts_use_the_one_definition():
    assert fdi.HEALTHY_VALUES is HEALTHY_VALUES
    assert residual.ResidualFilter().healthy_labels == (*HEALTHY_VALUES, 0)
    assert scorecard.HEALTHY is HEALTHY_VALUES
    # nowhere else spells the healthy pair out
    spelled = []
    for sub in ("inkdiag_core/inkdiag_core", "inkdiag_ros/inkdiag_ros", "scripts", "msg_defs/msg_defs"):
        for path in (ROOT / sub).rglob("*.py"):
            text = path.read_text()
            for pair in ('"ok_signal", "healthy_nozzle"', "'ok_signal', 'healthy_nozzle'",
                         '"healthy_nozzle", "ok_signal"'):
                if pair in text:
                    spelled.append(str(path.relative_to(ROOT)))
    assert sorted(set(spelled)) == ["inkdiag_core/inkdiag_core/faults.py", "msg_defs/msg_defs/labels.py"]


def test_the_two_sample_minimums_are_named_apart():
    assert kpis.MIN_KPI_SAMPLES == 2 and kpis.MIN_SAMPLES == kpis.MIN_KPI_SAMPLES
    assert estimation.MIN_SAMPLES == 16  # the f_m estimators' own, separate limit
