"""The fdi node: one FaultDetector model file, a failed batch counts every frame."""

import time

import numpy as np
from rclpy.parameter import Parameter as P

from inkdiag_core import FaultClass, simulate
from msg_defs import encode_traces


def _fdi(ros, model_path, **over):
    from inkdiag_ros.fdi_node import FdiNode

    params = {"model_path": str(model_path), "diagnostics_period_s": 0.2, **over}
    return ros.add(FdiNode(context=ros.context, namespace="/h",
                           parameter_overrides=[P(k, value=v) for k, v in params.items()]))


def test_a_failed_batch_counts_every_frame_it_held(ros, fdi_model, monkeypatch):
    import inkdiag_core
    import inkdiag_ros.fdi_node as fdi_node

    calls = []

    def fail_slowly(*args, **kwargs):  # the first batch holds the worker while the others queue up
        calls.append(1)
        time.sleep(0.5 if len(calls) == 1 else 0.0)
        raise RuntimeError("unexpected labelling error")

    # the labelling call of the node, on this branch and before it (label_frames_isolated)
    if hasattr(inkdiag_core, "FrameLabeller"):
        monkeypatch.setattr(inkdiag_core.FrameLabeller, "label", fail_slowly)
    monkeypatch.setattr(fdi_node, "label_frames_isolated", fail_slowly, raising=False)
    fdi = _fdi(ros, fdi_model)
    x = simulate({FaultClass.HEALTHY_NOZZLE: 4}, seed=1).traces.astype(np.float32)
    for k in range(6):
        fdi._on_trace_msg(encode_traces(x, first_nozzle=0, frame_id=k))
        time.sleep(0.05)
    assert fdi.wait_idle(10)
    s = fdi.stats
    assert len(calls) < 6  # some frames were batched together
    assert s.frames_failed == 6 and s.frames_labelled == 0, (s.frames_failed, len(calls))
    assert "unexpected labelling error" in s.last_error


def test_a_model_file_that_is_not_a_fault_detector_is_refused(ros, tmp_path):
    from inkdiag_core.fdi import train_default_model

    old = tmp_path / "old_pipeline.joblib"
    train_default_model(old, n_per_class=30, features="kpi_y+baseline")  # a plain pipeline file (save_model)
    fdi = _fdi(ros, old)
    assert fdi.labeller is None and fdi.model_id == "none"


def test_baseline_model_path_is_gone(ros, fdi_baseline_model):
    fdi = _fdi(ros, fdi_baseline_model)
    assert not fdi.has_parameter("baseline_model_path") and fdi.has_parameter("baseline_path")
    assert fdi.model_id.startswith("fdi-rf-kpi_y+baseline-") and not fdi.labeller.uses_baselines
