"""fdi: fault detection and isolation of every trace message of one printhead.

``traces`` -> decode -> label (:mod:`.labelling_backend`) -> ``labels``, ``drying_nozzles``; ``/diagnostics``. A model or
baselines of another ``head_profile``: refused. docs/parameters.md; topics, counters: docs/controller.md; docs/nodes.md."""

from __future__ import annotations


import numpy as np
from rclpy.node import Node

from inkdiag_core import FrameFailure, LabellerConfigError, ModelFileError, load_labeller
from msg_defs import (DIAGNOSTICS_MSG_TYPE, DIAGNOSTICS_QOS, DRYING_MSG_TYPE, LABELS_MSG_TYPE, RELIABLE_QOS,
                      TRACE_MSG_TYPE, TRACES_QOS, DryingNozzles, FrameError, LabelsReport, build_diagnostics,
                      decode_traces_serialized, serialize_drying, serialize_labels, topics)

from . import _params
from ._head import HEAD_PROFILE_PARAM, SAMPLING_PARAMS, head_from_parameters
from ._spin import exit_now, spin_node, take_into
from .labelling_backend import InlinePipeline, LabellingPipeline, ThreadBackend, make_backend
from .stats import FdiStats

PARAMS = (
    ("model_path", "", "FaultDetector model file (.joblib with its .manifest.json beside it)", str, None),
    ("n_nozzles", 0, "nozzles of this head: frames with ids >= n_nozzles are rejected (0: no check)", int, (0, 2**24)),
    HEAD_PROFILE_PARAM,
    *SAMPLING_PARAMS,
    ("diagnostics_period_s", 1.0, "period of /diagnostics, s", float, (0.1, 60.0)),
    ("max_queued_frames", 64, "frames waiting for the classifier at most; a full queue drops its oldest", int, (1, 100000)),
    ("max_batch_traces", 16384, "traces classified in one pass at most (a larger frame is one pass)", int, (1, 2**24)),
    ("baseline_path", "", "the head's per-nozzle baselines (.npz from record_baseline) for the model's baseline "
     "branch; empty: none", str, None),
    ("max_abs_sample_v", 0.0, "largest sample magnitude a sensor can produce, V; a row beyond it is invalid "
     "('out_of_range'). 0: 5x the head profile's ADC range (10 V for the default head)", float, (0.0, 1e30)),
    ("labelling_process", False, "label in a child process (its own core and GIL), not on the executor thread", bool, None),
)
#: What a labels report is built from (FrameLabels' columns; the class codes: no string read per row).
_ROWS = ("classes", "confidence", "valid", "reasons", "gate_cleared", "class_codes", "class_names")


class FdiNode(Node):
    """Decode, label and publish on the executor thread; or decode there, label in a child, publish on a collector."""

    def __init__(self, **kwargs):
        super().__init__("fdi", **kwargs)
        self.config = c = _params.declare_all(self, PARAMS)
        self.add_on_set_parameters_callback(lambda params: _params.fixed_at_start(params))
        self.head = head_from_parameters(c)  # a bad file or sampling: ValueError, exit 2 at start
        c["max_abs_sample_v"] = c["max_abs_sample_v"] or self.head.max_abs_v
        self.stats = FdiStats()
        self.labeller = self._load_labeller()
        self.stats.gate_in_use = bool(self.labeller and self.labeller.uses_gate)  # /diagnostics: its clear rate
        self.model_id = self.labeller.model_id if self.labeller else "none"
        self._max_id = c["n_nozzles"] - 1 if c["n_nozzles"] > 0 else None
        self._labels_pub = self.create_publisher(LABELS_MSG_TYPE, topics.LABELS, RELIABLE_QOS)
        self._drying_pub = self.create_publisher(DRYING_MSG_TYPE, topics.DRYING_NOZZLES, RELIABLE_QOS)
        self._diag_pub = self.create_publisher(DIAGNOSTICS_MSG_TYPE, topics.DIAGNOSTICS, DIAGNOSTICS_QOS)
        backend, why = make_backend(self.labeller, in_process=c["labelling_process"] and bool(self.labeller))
        if why:
            self._config_error(why)
        self._pipeline = (InlinePipeline if isinstance(backend, ThreadBackend) else LabellingPipeline)(
            backend, self._publish, on_batch=self._on_batch, on_drop=self._on_dropped, on_error=self._failed,
            max_queued=c["max_queued_frames"], max_batch_rows=c["max_batch_traces"], name="fdi-labeller")
        self.close_outputs = self._pipeline.close  # _spin.tear_down: the batches out published before nodes go
        # raw: the traces are viewed in the taken bytes, not converted to a Python message first (as fe)
        self._sub = self.create_subscription(TRACE_MSG_TYPE, topics.TRACES, self._on_traces, TRACES_QOS, raw=True)
        self._diag_timer = self.create_timer(c["diagnostics_period_s"], lambda: self._on_diagnostics(0.5))

    def _load_labeller(self):
        if not (c := self.config)["model_path"]:
            return self._config_error("no FDI model: no model_path given")  # None: runs unlabelled
        try:
            labeller, baseline_error = load_labeller(c["model_path"], c["baseline_path"], max_abs_v=c["max_abs_sample_v"],
                                                     sample_rate_hz=c["sample_rate_hz"], n_samples=c["n_samples"],
                                                     profile=self.head, n_nozzles=c["n_nozzles"])
        except (ModelFileError, LabellerConfigError) as exc:  # runs unlabelled; /diagnostics says why (ERROR)
            return self._config_error(f"FDI model not loaded: {exc}")
        self.get_logger().info(f"FDI model {labeller.model_id} loaded from {c['model_path']}")
        if why := (f"per-nozzle baselines not used: {baseline_error}" if baseline_error is not None else
                   labeller.uses_baselines and labeller.baselines.gain_mismatch(self.head)):  # used, but unlike its head
            self._config_error(why)
        elif labeller.uses_baselines:
            self.get_logger().info(f"per-nozzle baselines of {len(labeller.baselines)} nozzles from {c['baseline_path']}")
        return labeller

    def _config_error(self, why: str) -> None:
        self.stats.misconfigured(why)
        self.get_logger().error(why)

    def destroy_node(self):
        if getattr(self, "_pipeline", None) is not None:  # absent if __init__ failed part-way; else
            self._pipeline.close()  # the batches out are published first (once: tear_down may have)
        return super().destroy_node()

    def wait_idle(self, timeout: float | None = None) -> bool:  # for tests and tools: all received labelled, published
        return self._pipeline.wait_idle(timeout)

    def _on_traces(self, msg) -> None:
        k = min(64, self.config["max_queued_frames"])
        try:
            self._on_trace_msg(msg)
            take_into(self._sub, k - 1, self._on_trace_msg)  # the rest of a burst
        finally:  # labelled, published here (a child's pipeline: no-op); what arrives meanwhile screened too
            self._pipeline.flush(self.context.ok, refill=lambda: take_into(self._sub, k, self._on_trace_msg))
        self._on_diagnostics(1.0)  # under load the timer waits behind this callback: /diagnostics on time

    def _on_trace_msg(self, msg) -> None:
        self.stats.received()
        c = self.config
        try:
            frame = decode_traces_serialized(msg, max_nozzle_id=self._max_id, n_samples=c["n_samples"],
                                             sample_rate_hz=c["sample_rate_hz"])
        except FrameError as exc:
            why = f"{exc} (head {self.head.name!r}: {c['sample_rate_hz']:g} Hz x {c['n_samples']} samples)"
            self.stats.malformed(why)
            self.get_logger().warning(f"dropped a malformed trace frame: {why}", throttle_duration_sec=1.0)
            return
        if self.labeller is not None:
            self._pipeline.submit(frame)

    def _on_dropped(self, frame) -> None:  # the labelling queue was full
        self.stats.dropped(f"frame {frame.frame_id}: dropped, the labelling queue was full")
        self.get_logger().warning("labelling queue full: dropped the oldest frame", throttle_duration_sec=1.0)

    def _on_batch(self, n_frames: int, busy_s: float) -> None:
        if (why := self._pipeline.backend.config_error) and self.stats.config_error != why:  # e.g. no child could start
            self._config_error(why)
        self.stats.batch(n_frames, busy_s)

    def _publish(self, frame, result) -> None:
        try:
            if isinstance(result, FrameFailure):
                raise result.error
            report = LabelsReport.from_arrays(frame_id=frame.frame_id, stamp=frame.stamp, model_id=self.model_id,
                                              first_nozzle=frame.first_nozzle, **{k: getattr(result, k) for k in _ROWS})
            self._labels_pub.publish(serialize_labels(report))  # bytes: no conversion by rclpy
            self._drying_pub.publish(serialize_drying(DryingNozzles.from_labels(report)))
        except Exception as exc:  # noqa: BLE001 - this frame failed; the batch's others go on
            return self._failed(frame, exc)
        self.stats.labelled(report.counts, report.n_nozzles, int(np.count_nonzero(result.baseline)), report.gate_cleared)

    def _failed(self, frame, exc) -> None:
        if self.context.ok():  # else shutting down: nothing left to publish to
            self.stats.failed(f"frame {frame.frame_id}: {(why := f'{type(exc).__name__}: {exc}')}")
            self.get_logger().error(f"labelling frame {frame.frame_id} failed: {why}", throttle_duration_sec=1.0)

    def _on_diagnostics(self, at_least: float) -> None:  # at least that many periods after the last one
        if self.context.ok() and self.stats.since_period() >= at_least * self.config["diagnostics_period_s"]:
            level, message, values, counts, gate_cleared = self.stats.period(self.labeller is not None)
            self._diag_pub.publish(build_diagnostics(
                namespace=self.get_namespace(), level=level, message=message, counts=counts, gate_cleared=gate_cleared,
                values={"model_id": self.model_id, **values}, stamp=self.get_clock().now().to_msg()))


def main(args=None) -> int:
    return spin_node(FdiNode, args, events=True)  # no wait set rebuilt in Python per message (issue 17)


if __name__ == "__main__":
    exit_now(main())  # the nodes down: not the interpreter's teardown too
