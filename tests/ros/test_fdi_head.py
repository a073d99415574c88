"""The fdi node on a head profile (``head_profile``): frames of that head labelled by a model of that
head; a model of another head refused at start; frames of another sampling malformed; a bad profile
file or contradicting sampling parameters: exit status 2 at start. Real rclpy."""

import os
import subprocess
import sys

import numpy as np
import pytest
from rclpy.parameter import Parameter as P

from _helpers import collect
from inkdiag_core import FaultClass, HeadProfile, save_detector, train_detector
from msg_defs import LABELS_MSG_TYPE, RELIABLE_QOS, TRACE_MSG_TYPE, TRACES_QOS, decode_labels, encode_traces, topics


@pytest.fixture(scope="module")
def head(tmp_path_factory):
    h = HeadProfile.default().replace(name="foreign20", sample_rate_hz=20e6, n_samples=1024,
                                      channel={"rho": 1100.0, "mu": 6e-3, "r_n": 11e-6, "L_n": 45e-6})
    path = tmp_path_factory.mktemp("head") / "foreign20.yaml"
    h.save(path)
    return h, path


@pytest.fixture(scope="module")
def head_model(head, tmp_path_factory):
    det, info = train_detector(head[0], n_per_class=24, seed=0)
    path = tmp_path_factory.mktemp("model") / "foreign20.joblib"
    save_detector(det, path, config=info)
    return path


def _fdi(ros, **params):
    from inkdiag_ros.fdi_node import FdiNode

    params = {"diagnostics_period_s": 0.2, **params}
    return ros.add(FdiNode(context=ros.context, namespace="/h",
                           parameter_overrides=[P(k, value=v) for k, v in params.items()]))


@pytest.mark.parametrize("in_child", [False, True], ids=["thread", "labelling_process"])
def test_fdi_labels_a_foreign_heads_frames_with_its_model_and_refuses_other_sampling(ros, head, head_model,
                                                                                     in_child):
    h, path = head
    fdi = _fdi(ros, model_path=str(head_model), head_profile=str(path), labelling_process=in_child)
    assert fdi.labeller is not None and (fdi.config["sample_rate_hz"], fdi.config["n_samples"]) == (20e6, 1024)
    assert fdi.config["max_abs_sample_v"] == 5 * h.adc_range_v
    probe = ros.node("probe", namespace="/h")
    pub = probe.create_publisher(TRACE_MSG_TYPE, topics.TRACES, TRACES_QOS)
    labels = collect(ros, probe, LABELS_MSG_TYPE, topics.LABELS, RELIABLE_QOS, decode_labels)
    ros.spin_until(lambda: pub.get_subscription_count() > 0, 10, "fdi's subscription")
    sim = h.simulate({FaultClass.HEALTHY_NOZZLE: 12, FaultClass.FULLY_BLOCKED: 12}, seed=5)
    x = sim.traces.astype(np.float32)
    x[0, 3] = np.nan
    fdi._on_traces(encode_traces(x, sample_rate_hz=20e6, frame_id=1))  # as the executor calls it
    assert fdi.wait_idle(30)
    ros.spin_until(lambda: labels, 10, "labels")
    rep = labels[-1]
    assert dict(rep.invalid) == {0: "non_finite"} and sum(rep.counts.values()) == 24
    assert rep.counts.get("fully_blocked", 0) >= 10
    # a frame of the default head's sampling is malformed, and the message says the head
    d = HeadProfile.default().simulate({FaultClass.HEALTHY_NOZZLE: 4}, seed=1).traces
    fdi._on_traces(encode_traces(d.astype(np.float32), frame_id=2))
    assert fdi.stats.frames_malformed == 1 and "foreign20" in fdi.stats.last_error


def test_fdi_refuses_a_model_of_another_head_at_start(ros, head, head_model, fdi_model):
    h, path = head
    fdi = _fdi(ros, model_path=str(head_model))  # the default head, a foreign head's model
    assert fdi.labeller is None and fdi.model_id == "none"
    fdi2 = _fdi(ros, model_path=str(fdi_model), head_profile=str(path))  # the foreign head, a default model
    assert fdi2.labeller is None


def test_fdi_with_the_default_head_keeps_its_sampling(ros, fdi_model):
    fdi = _fdi(ros, model_path=str(fdi_model))
    assert fdi.labeller is not None and (fdi.config["sample_rate_hz"], fdi.config["n_samples"]) == (10e6, 512)
    assert fdi.config["max_abs_sample_v"] == 10.0  # as before: 5x the default head's +-2 V
    with pytest.raises(ValueError, match="leave sample_rate_hz 0"):
        _fdi(ros, model_path=str(fdi_model), sample_rate_hz=20e6)


@pytest.mark.parametrize(("args", "match"), [
    (["-p", "head_profile:=/nonexistent/head.yaml"], "no such head profile file"),
    (["-p", "n_samples:=1024"], "head profile 'default'"),
])
def test_fdi_exits_2_on_a_bad_head_profile(ros, tmp_path, args, match):
    env = dict(os.environ, ROS_DOMAIN_ID=str(ros.domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    out = subprocess.run([sys.executable, "-m", "inkdiag_ros.fdi_node", "--ros-args", *args],
                         env=env, capture_output=True, text=True, timeout=60)
    assert out.returncode == 2, out.stderr[-2000:]
    assert match in out.stderr and "Traceback" not in out.stderr, out.stderr[-2000:]


def test_the_packaged_parameters_take_another_heads_profile(ros, head, head_model):
    """helper-108: the packaged config/inkdiag.yaml set fdi's sampling to the default head's, so the README's
    `--params-file ... -p head_profile:=HEAD.yaml` exited 2 for any other head. Its sampling is the profile's."""
    import yaml

    from inkdiag_ros.fdi_node import PARAMS

    cfg = os.path.join(os.path.dirname(__import__("inkdiag_ros").__file__), "config", "inkdiag.yaml")
    with open(cfg) as f:
        shipped = yaml.safe_load(f)["/**/fdi"]["ros__parameters"]
    assert set(shipped) <= {p[0] for p in PARAMS}
    h, path = head
    fdi = _fdi(ros, **{**shipped, "model_path": str(head_model), "head_profile": str(path), "n_nozzles": 0})
    assert fdi.labeller is not None and (fdi.config["sample_rate_hz"], fdi.config["n_samples"]) == (20e6, 1024)
