"""msg_defs JSON and numeric messages: round trips, schema versions, validation errors."""

import json
import math

import numpy as np
import pytest
from std_msgs.msg import Float64MultiArray, String

import msg_defs
from msg_defs import (
    FIELDS,
    DryingNozzles,
    FmEstimates,
    LabelsReport,
    MessageError,
    build_diagnostics,
    decode_drying,
    decode_estimates,
    decode_estimates_array,
    decode_labels,
    decode_truth,
    diagnostics_values,
    encode_drying,
    encode_estimates,
    encode_estimates_array,
    encode_labels,
    encode_truth,
    truth_from_arrays,
)


def _report():
    classes = ["healthy_nozzle", "deeply_dried", "ok_signal", "fully_blocked", "", "slightly_dried"]
    valid = [True, True, True, True, False, True]
    reasons = ["", "", "", "", "non_finite", ""]
    conf = [0.99, 0.9123, 0.8, 0.77, math.nan, 0.6]
    return LabelsReport.from_arrays(frame_id=2**30, stamp=1763798400.125, first_nozzle=100,
                                    classes=classes, confidence=conf, valid=valid, reasons=reasons,
                                    model_id="fdi-abc")


def test_labels_round_trip_and_content():
    rep = _report()
    msg = encode_labels(rep)
    doc = json.loads(msg.data)
    assert doc["schema"] == "inkdiag.labels" and doc["schema_version"] == msg_defs.JSON_SCHEMA_VERSION
    assert doc["counts"] == {"deeply_dried": 1, "fully_blocked": 1, "healthy_nozzle": 1,
                             "ok_signal": 1, "slightly_dried": 1, "invalid": 1}
    assert doc["faults"] == [{"nozzle": 101, "class": "deeply_dried", "confidence": 0.912},
                             {"nozzle": 103, "class": "fully_blocked", "confidence": 0.77},
                             {"nozzle": 105, "class": "slightly_dried", "confidence": 0.6}]
    assert doc["invalid"] == [{"nozzle": 104, "reason": "non_finite"}]
    back = decode_labels(msg)
    assert back == rep
    d = DryingNozzles.from_labels(back)
    assert d.nozzles == (101, 105) and d.classes == ("deeply_dried", "slightly_dried")
    assert decode_drying(encode_drying(d)) == d


@pytest.mark.parametrize("mutate, match", [
    (lambda d: d.update(schema_version=2), "schema_version"),
    (lambda d: d.update(schema="other"), "expected schema"),
    (lambda d: d.pop("frame_id"), "missing field 'frame_id'"),
    (lambda d: d.update(n_nozzles=7), "counts sum to 6"),
    (lambda d: d.update(stamp="now"), "'stamp' must be float"),
    (lambda d: d["faults"].append({"nozzle": 999, "class": "x", "confidence": 1}), "outside"),
    (lambda d: d["faults"].append({"nozzle": 101}), "malformed"),
])
def test_labels_validation(mutate, match):
    doc = json.loads(encode_labels(_report()).data)
    mutate(doc)
    with pytest.raises(MessageError, match=match):
        decode_labels(String(data=json.dumps(doc)))


def test_not_json_and_wrong_type():
    with pytest.raises(MessageError, match="not valid JSON"):
        decode_labels(String(data="{nope"))
    # nested deeper than json's recursive decoder goes: a MessageError, not a RecursionError (it killed fe)
    for decode in (decode_labels, decode_drying, decode_estimates, decode_truth):
        with pytest.raises(MessageError, match=r"not valid JSON \(nested too deeply\)"):
            decode(String(data="[" * 100_000 + "]" * 100_000))
    with pytest.raises(MessageError, match="std_msgs/String"):
        decode_drying(Float64MultiArray())
    with pytest.raises(ValueError):  # MessageError is a ValueError; FrameError is a MessageError
        raise msg_defs.FrameError("x")
    assert issubclass(msg_defs.FrameError, MessageError)


def test_drying_validation():
    bad = json.loads(encode_drying(DryingNozzles(1, 2.0, (3,), ("deeply_dried",))).data)
    bad["classes"] = ["fully_blocked", "deeply_dried"]
    with pytest.raises(MessageError, match="dried class per nozzle"):  # 2 classes for 1 nozzle: no pairs
        decode_drying(String(data=json.dumps(bad)))


def test_a_bad_drying_entry_costs_only_itself():
    """One bad entry (an id outside the range or not an integer, a class not dried) is left out; the
    list's other nozzles are kept and ``dropped`` says what was left out."""
    good = DryingNozzles(1, 2.0, (200, 205, 399), ("deeply_dried", "slightly_dried", "intermediately_dried"),
                         first_nozzle=200, n_nozzles=200)
    assert decode_drying(encode_drying(good)).dropped == ""
    doc = json.loads(encode_drying(good).data)
    doc["nozzles"] = [200, 400, 205, True, 2.5, 399, 201, 1 << 24]
    doc["classes"] = ["deeply_dried", "deeply_dried", "slightly_dried", "deeply_dried", "deeply_dried",
                      "intermediately_dried", "fully_blocked", "deeply_dried"]
    d = decode_drying(String(data=json.dumps(doc)))
    assert d == good  # dropped is not compared
    assert "left out 5 of 8" in d.dropped and "400" in d.dropped and "fully_blocked" in d.dropped
    del doc["first_nozzle"], doc["n_nozzles"]  # no range: any id in [0, 2**24)
    d = decode_drying(String(data=json.dumps(doc)))
    assert d.nozzles == (200, 400, 205, 399) and "left out 4 of 8" in d.dropped


def _estimates():
    n = 3
    return FmEstimates.from_columns(
        17, 12.5, nozzle=[4, 9, 40], fm=[-4e5, -8e5, -1.5e6], fm_std=[1e4, 2e4, 3e4],
        d_mu=[0.013, 0.027, 0.05], viscosity=[0.023, 0.037, 0.06], fm_trend=[math.nan, -7.9e5, -1.49e6],
        fm_rate=[math.nan, -1e4, -2e4], eta_deeply_dried_s=[math.nan, 60.0, 0.0]) if n else None


def test_estimates_json_and_array_agree():
    e = _estimates()
    js = decode_estimates(encode_estimates(e))
    arr_msg = encode_estimates_array(e)
    assert [d.label for d in arr_msg.layout.dim] == ["estimate", "field"]
    assert arr_msg.layout.dim[1].size == len(FIELDS) and arr_msg.layout.data_offset == 3
    arr = decode_estimates_array(arr_msg)
    for got in (js, arr):
        assert got.frame_id == 17 and got.stamp == 12.5
        np.testing.assert_array_equal(got.table, e.table)  # NaN == NaN positions too
    doc = json.loads(encode_estimates(e).data)
    assert doc["estimates"][0]["fm_trend"] is None and doc["estimates"][0]["nozzle"] == 4
    with pytest.raises(MessageError, match="missing fields"):
        FmEstimates.from_columns(1, 1.0, nozzle=[1])
    arr_msg.layout.dim[1].size = 5
    with pytest.raises(MessageError, match="field size"):
        decode_estimates_array(arr_msg)


def test_truth_round_trip():
    t = truth_from_arrays(frame_id=3, stamp=1.5, first_nozzle=10,
                          classes=["healthy_nozzle", "deeply_dried", "ok_signal"],
                          fm=[0.0, -1.2e6, 0.0], mu_nozzle=[0.01, 0.06, 0.01])
    assert t.faults == ((11, "deeply_dried", -1.2e6, 0.06),) and t.n_nozzles == 3
    assert decode_truth(encode_truth(t)) == t


def test_diagnostics_levels_and_values():
    from diagnostic_msgs.msg import DiagnosticStatus

    arr = build_diagnostics(namespace="/head_07", level="warn", message="2 malformed",
                            values={"model_id": "m", "frames_received": 5, "traces_per_s": 1234.5678},
                            counts={"healthy_nozzle": 10, "invalid": 2})
    st = arr.status[0]
    assert st.level == DiagnosticStatus.WARN and st.hardware_id == "/head_07"
    assert st.name == "inkdiag fdi: /head_07"
    v = diagnostics_values(arr)["inkdiag fdi: /head_07"]
    assert v["level"] == "warn" and v["traces_per_s"] == "1234.57" and v["count.invalid"] == "2"
    assert [kv.key for kv in st.values][:3] == ["model_id", "frames_received", "traces_per_s"]


def test_drying_says_its_range_and_a_message_without_one_still_decodes():
    rep = _report()
    d = DryingNozzles.from_labels(rep)
    assert (d.first_nozzle, d.n_nozzles) == (rep.first_nozzle, rep.n_nozzles)
    doc = json.loads(encode_drying(d).data)
    assert (doc["first_nozzle"], doc["n_nozzles"]) == (rep.first_nozzle, rep.n_nozzles)
    assert decode_drying(encode_drying(d)) == d
    del doc["first_nozzle"], doc["n_nozzles"]  # as written before the range existed: range unknown
    old = decode_drying(String(data=json.dumps(doc)))
    assert old.nozzles == d.nozzles and old.first_nozzle is None and old.n_nozzles is None
    half = dict(doc, first_nozzle=100)
    with pytest.raises(MessageError, match="missing field 'n_nozzles'"):
        decode_drying(String(data=json.dumps(half)))
    outside = dict(doc, first_nozzle=102, n_nozzles=2)  # 101 and 105 are not in 102..103
    left = decode_drying(String(data=json.dumps(outside)))
    assert left.nozzles == () and left.first_nozzle == 102 and "left out 2 of 2" in left.dropped


def test_estimates_json_says_its_first_nozzle():
    e = _estimates()
    ranged = FmEstimates(e.frame_id, e.stamp, e.table, first_nozzle=400)
    assert json.loads(encode_estimates(ranged).data)["first_nozzle"] == 400
    assert decode_estimates(encode_estimates(ranged)).first_nozzle == 400
    assert decode_estimates(encode_estimates(e)).first_nozzle is None
    assert "first_nozzle" not in json.loads(encode_estimates(e).data)


@pytest.mark.parametrize("text", ["", "x", "ab", "abc", "abcd", "é ü ∆ 😀", '{"a": "\\u0000"}', "a" * 70000,
                                  "é" * 40000])
def test_serialized_is_rclpy_serialization(text):
    """A node publishes msg_defs.serialized(msg) as bytes: the same CDR rclpy writes for the message, so a
    subscriber (typed or raw) cannot tell them apart."""
    from rclpy.serialization import deserialize_message, serialize_message

    msg = String(data=text)
    wire = msg_defs.serialized(msg)
    assert wire == serialize_message(msg)
    assert deserialize_message(wire, String).data == text


def test_serialized_answers_decode():
    """The fdi node's two answers, published as bytes: rclpy's bytes, and they decode to the same report."""
    from rclpy.serialization import deserialize_message, serialize_message

    report = LabelsReport.from_arrays(frame_id=7, stamp=1.5, first_nozzle=100, model_id="m",
                                      classes=np.array(["healthy_nozzle", "deeply_dried"], dtype=object),
                                      confidence=[0.9, 0.8123], valid=[True, True], reasons=["", ""])
    labels, drying = encode_labels(report), encode_drying(DryingNozzles.from_labels(report))
    for msg in (labels, drying):
        assert msg_defs.serialized(msg) == serialize_message(msg)
    assert decode_labels(deserialize_message(msg_defs.serialized(labels), String)) == report
    assert decode_drying(deserialize_message(msg_defs.serialized(drying), String)).nozzles == (101,)
    with pytest.raises(TypeError, match="std_msgs/String"):
        msg_defs.serialized(Float64MultiArray())


def _random_report(rng, classes, n_max=40):
    """A frame's arrays as the labeller gives them (some invalid rows, some cleared by the gate, a few of them
    wrongly: from_arrays must not trust the gate's column for the classes) and the report built from them."""
    n = int(rng.integers(0, n_max))
    healthy = rng.random(n) < rng.random()
    cls = np.where(healthy, rng.choice(msg_defs.HEALTHY_CLASSES, n), rng.choice(classes, n)).astype(object)
    valid = rng.random(n) > rng.choice([0.0, 0.2])
    reasons = np.where(valid, "", rng.choice(["flat", "non_finite", "clipped"], n)).astype(object)
    cleared = None if rng.random() < 0.2 else (healthy & (rng.random(n) < 0.8)) | (rng.random(n) < rng.choice([0, 0.1]))
    conf = rng.random(n)
    if n and rng.random() < 0.05:
        conf[rng.integers(n)] = rng.choice([math.nan, math.inf])
    kw = dict(frame_id=int(rng.integers(0, 2**40)), stamp=float(rng.choice([rng.random() * 2e9, 3.0, 0.0])),
              first_nozzle=int(rng.integers(0, 2**20)), classes=cls, confidence=conf, valid=valid, reasons=reasons,
              model_id=str(rng.choice(["fdi-rf-kpi_y-3f2a9c1b", "modèle \"ü\"\n", "m"])), gate_cleared=cleared)
    return kw, LabelsReport.from_arrays(**kw)


def _outcome(fn, *args):
    try:
        return fn(*args)
    except Exception as exc:  # noqa: BLE001 - the failure itself is what is compared
        return type(exc)


def test_serialize_labels_and_drying_are_the_json_way_byte_for_byte():
    """The fdi node publishes serialize_labels / serialize_drying: the very bytes of the json encoders'
    messages, and the same error where json raises (a NaN confidence, a numpy scalar, a bool)."""
    rng = np.random.default_rng(5)
    classes = ["deeply_dried", "slightly_dried", "unknown", "empty_channel_1", "fully_blocked", 'odd "cl\u00e4ss"\t']
    seen_error = 0
    for _ in range(3000):
        _, rep = _random_report(rng, classes)
        drying = DryingNozzles.from_labels(rep)
        for old, new, obj in ((encode_labels, msg_defs.serialize_labels, rep),
                              (encode_drying, msg_defs.serialize_drying, drying)):
            want = _outcome(lambda o: msg_defs.serialized(old(o)), obj)
            assert _outcome(new, obj) == want
            seen_error += isinstance(want, type)
    assert seen_error > 0  # the NaN and inf confidences were met
    # entries that are iterators (not tuples), with a later field the json way must write: its bytes, not an
    # iterator read empty by the direct way first
    for change in (lambda: dict(invalid=(iter((1, "flat")),), counts={"ok_signal": 2, "invalid": 1}, gate_cleared=True),
                   lambda: dict(faults=(iter((1, "deeply_dried", 0.5)), (2, "x", np.float64(0.5))))):
        a, b = (LabelsReport(1, 2.0, 0, 3, "m", **{"counts": {"deeply_dried": 1, "invalid": 0, "ok_signal": 2},
                                                  **change()}) for _ in range(2))
        assert _outcome(msg_defs.serialize_labels, a) == _outcome(lambda r: msg_defs.serialized(encode_labels(r)), b)
    # confidences the 3-decimal shortcut must write as repr does, or leave to repr
    for x in (0.0, -0.0, 1.0, 0.001, 0.0005, 0.8734, 0.999, 0.9995, 1e-300, 1.001, 5e-324, 0.1 + 0.2):
        rep = LabelsReport(1, 2.0, 0, 3, "m", {"deeply_dried": 1, "invalid": 0, "ok_signal": 2}, ((1, "deeply_dried", x),))
        assert msg_defs.serialize_labels(rep) == msg_defs.serialized(encode_labels(rep)), x
    # reports built by hand with values json writes otherwise or refuses: the json way, the same outcome
    base = _random_report(np.random.default_rng(1), classes)[1]
    import dataclasses
    for change in (dict(frame_id=np.int64(3)), dict(stamp=np.float64(1.5)), dict(stamp=2), dict(gate_cleared=True),
                   dict(counts={"healthy_nozzle": np.int64(2), "invalid": 0}), dict(model_id=np.str_("m")),
                   dict(faults=((1, "deeply_dried", 1),)), dict(faults=((1, "deeply_dried", np.float32(0.5)),)),
                   dict(stamp=math.nan), dict(invalid=((np.int64(4), "flat"),))):
        rep = dataclasses.replace(base, **change)
        assert _outcome(msg_defs.serialize_labels, rep) == _outcome(lambda r: msg_defs.serialized(encode_labels(r)), rep)
    for change in (dict(stamp=math.inf), dict(frame_id=np.int64(3)), dict(nozzles=(np.int64(5),), classes=("x",))):
        d = dataclasses.replace(DryingNozzles(1, 2.0), **change)
        assert _outcome(msg_defs.serialize_drying, d) == _outcome(lambda x: msg_defs.serialized(encode_drying(x)), d)


def _reference_from_arrays(*, frame_id, stamp, first_nozzle, classes, confidence, valid, reasons, model_id,
                           gate_cleared=None):
    """from_arrays as it was written first (a Counter of every valid row's class, a membership test per row):
    the faster from_arrays must give the same report."""
    from collections import Counter

    cl, ok = list(np.asarray(classes, dtype=object)), np.asarray(valid, dtype=bool).tolist()
    by_class = Counter(c for c, v in zip(cl, ok) if v)
    faulty = [i for i, (c, v) in enumerate(zip(cl, ok)) if v and c not in msg_defs.HEALTHY_CLASSES]
    counts = {str(c): by_class[c] for c in sorted(by_class)}
    counts["invalid"] = len(cl) - sum(ok)
    conf = (np.rint(np.asarray(confidence, dtype=float)[faulty] * 1e3) / 1e3).tolist()
    faults = tuple((first_nozzle + i, str(cl[i]), x) for i, x in zip(faulty, conf))
    invalid = tuple((first_nozzle + i, str(r)) for i, (r, v) in enumerate(zip(reasons, ok)) if not v)
    cleared = 0 if gate_cleared is None else int(np.count_nonzero(np.asarray(gate_cleared, bool) & np.asarray(ok, bool)))
    return LabelsReport(frame_id, stamp, first_nozzle, len(cl), model_id, counts, faults, invalid, cleared)


def test_from_arrays_is_the_reference_and_does_not_trust_the_gate_column_for_classes():
    """from_arrays looks for faults among the rows the gate did not clear: a cleared row of a fault class (a
    labeller bug) is still counted and listed. Against a plain reference, with and without the gate's column."""
    rng = np.random.default_rng(11)
    for _ in range(2000):
        kw, rep = _random_report(rng, ["deeply_dried", "unknown", "fully_blocked", "slightly_dried"])
        assert repr(rep) == repr(_reference_from_arrays(**kw))  # repr: a NaN confidence equals itself
        no_gate = {**kw, "gate_cleared": None}
        assert repr(LabelsReport.from_arrays(**no_gate)) == repr(_reference_from_arrays(**no_gate))
    cls = np.array(["healthy_nozzle", "deeply_dried", "ok_signal"], dtype=object)
    rep = LabelsReport.from_arrays(frame_id=1, stamp=1.0, first_nozzle=10, classes=cls, confidence=[1, 0.5, 1],
                                   valid=[True] * 3, reasons=[""] * 3, model_id="m", gate_cleared=[True, True, True])
    assert rep.faults == ((11, "deeply_dried", 0.5),) and rep.counts["deeply_dried"] == 1 and rep.gate_cleared == 3
    # not plain strings (numpy's str_; an enum that equals its value but hashes by its name): the Counter way
    import enum

    Odd = enum.Enum("Odd", {"H": "healthy_nozzle", "D": "deeply_dried"}, type=str)
    for odd in (np.array(["healthy_nozzle", "deeply_dried"], dtype=np.str_), [np.str_("ok_signal"), "unknown"],
                [Odd.H, Odd.D], ["healthy_nozzle", Odd.H]):
        kw = dict(frame_id=1, stamp=1.0, first_nozzle=0, classes=np.asarray(odd, dtype=object), confidence=[0.9, 0.8],
                  valid=[True, True], reasons=["", ""], model_id="m", gate_cleared=[True, False])
        assert repr(LabelsReport.from_arrays(**kw)) == repr(_reference_from_arrays(**kw))
    # valid not 1-D: refused (it was broadcast against the gate's column)
    with pytest.raises(MessageError, match="must all have shape"):
        LabelsReport.from_arrays(frame_id=1, stamp=1.0, first_nozzle=0, classes=["deeply_dried"] * 2,
                                 confidence=[0.9, 0.8], valid=np.ones((2, 1), bool), reasons=["", ""], model_id="m",
                                 gate_cleared=[False, True])
    # an unhashable class value: the Counter's TypeError, as the reference
    kw = dict(frame_id=1, stamp=1.0, first_nozzle=0, classes=np.array([["x"], "healthy_nozzle"], dtype=object),
              confidence=[0.9, 0.8], valid=[True, True], reasons=["", ""], model_id="m", gate_cleared=[False, True])
    assert _outcome(lambda: LabelsReport.from_arrays(**kw)) is _outcome(lambda: _reference_from_arrays(**kw)) is TypeError
    # a bad confidence or gate column fails as it always did, even when every row is healthy
    healthy = dict(frame_id=1, stamp=1.0, first_nozzle=0, classes=["healthy_nozzle"] * 2, valid=[True, True],
                   reasons=["", ""], model_id="m")
    with pytest.raises(ValueError):
        LabelsReport.from_arrays(**healthy, confidence=["a", "b"])
    with pytest.raises(MessageError, match="gate_cleared must have shape"):
        LabelsReport.from_arrays(**healthy, confidence=[1.0, 1.0], gate_cleared=[True])


def test_serializers_read_iterators_once_and_fail_as_json_does():
    """A hand-built report with iterators, a counts mapping that is not a dict or two bad fields: the json way's
    bytes or error, every time."""
    import dataclasses
    import types

    base = LabelsReport(3, 1.5, 0, 2, "m", {"deeply_dried": 1, "healthy_nozzle": 1, "invalid": 0},
                        ((0, "deeply_dried", 0.5),), ())
    json_way = lambda r: msg_defs.serialized(encode_labels(r))  # noqa: E731
    for change in (lambda: dict(faults=iter(((0, "deeply_dried", 0.5),)), gate_cleared=True),
                   lambda: dict(counts=types.MappingProxyType({"a": 2})), lambda: dict(counts=[("a", 2)]),
                   lambda: dict(stamp=None, faults=((1, "a"),)), lambda: dict(stamp=None, counts=[])):
        a, b = dataclasses.replace(base, **change()), dataclasses.replace(base, **change())  # their own iterators
        assert _outcome(msg_defs.serialize_labels, a) == _outcome(json_way, b)
    d_json = lambda d: msg_defs.serialized(encode_drying(d))  # noqa: E731
    for change in (lambda: dict(nozzles=(5.7, True), classes=("deeply_dried", "slightly_dried")),
                   lambda: dict(frame_id=None, stamp="x"), lambda: dict(frame_id="abc", nozzles=(None,), classes=("x",)),
                   lambda: dict(nozzles=iter((4,)), classes=("deeply_dried",)), lambda: dict(stamp="7.25")):
        a, b = (dataclasses.replace(DryingNozzles(1, 2.0, first_nozzle=0, n_nozzles=9), **change()) for _ in range(2))
        assert _outcome(msg_defs.serialize_drying, a) == _outcome(d_json, b)
