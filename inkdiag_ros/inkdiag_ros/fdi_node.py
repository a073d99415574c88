"""fdi: fault detection and isolation of every trace frame of one printhead.

Subscribes to ``traces`` (sensor-data QoS); per frame: decode -> label with the
core's :class:`inkdiag_core.FrameLabeller` (screening, one
:class:`inkdiag_core.FaultDetector` call per batch, each frame isolated) ->
publish ``labels`` and ``drying_nozzles`` (reliable), one of each per trace
message (a frame or one nozzle range of it, ``first_nozzle`` and ``n_nozzles``).
A worker thread takes every frame queued while the labeller was busy and hands
them on as one batch (:mod:`.batching`); a full queue (``max_queued_frames``)
drops its oldest frame (``frames_dropped``). The batch is labelled on that
thread, or with ``labelling_process`` in a child process
(:mod:`.labelling_backend`); one collector thread publishes every batch in
order. A malformed frame, a frame that fails and invalid rows (with their
reason) are counted in ``/diagnostics`` (every ``diagnostics_period_s``).

``model_path`` is a FaultDetector file (verified against its manifest); an old
plain-pipeline file is refused: retrain with ``python -m inkdiag_ros.model_cache``.
With ``baseline_path`` (the head's recorded baselines, ``record_baseline``) the
rows of nozzles that have a baseline go to the detector's baseline branch
(``rows_with_baseline``); baselines that do not load or do not fit the model
are reported and the node labels without them.

    fdi --ros-args -r __ns:=/head_00 -p model_path:=models/fdi_default.joblib
"""

from __future__ import annotations

import queue
import sys
import threading

import numpy as np
from rclpy.node import Node

from inkdiag_core import (BaselineFileError, FrameFailure, FrameLabeller, LabellerConfigError, ModelFileError,
                          NozzleBaselines, load_detector)
from msg_defs import (DIAGNOSTICS_MSG_TYPE, DIAGNOSTICS_QOS, DRYING_MSG_TYPE, LABELS_MSG_TYPE, RELIABLE_QOS,
                      TRACE_MSG_TYPE, TRACES_QOS, DryingNozzles, FrameError, LabelsReport, build_diagnostics,
                      decode_traces, encode_drying, encode_labels, topics)

from . import _params
from ._spin import spin_node
from .batching import BatchWorker
from .labelling_backend import make_backend
from .stats import FdiStats

PARAMS = (
    ("model_path", "", "FaultDetector model file (.joblib with its .manifest.json beside it)", str, None),
    ("n_nozzles", 0, "nozzles of this head: frames with ids >= n_nozzles are rejected (0: no check)",
     int, (0, 2**24)),
    ("n_samples", 512, "samples per trace the model was built for; other frames are rejected",
     int, (16, 65536)),
    ("sample_rate_hz", 10e6, "sample rate the model was built for, Hz; other frames are rejected",
     float, (1e3, 1e9)),
    ("diagnostics_period_s", 1.0, "period of /diagnostics, s", float, (0.1, 60.0)),
    ("max_queued_frames", 64, "frames waiting for the classifier at most; a full queue drops its oldest",
     int, (1, 100000)),
    ("max_batch_traces", 16384, "traces classified in one pass at most", int, (1, 2**24)),
    ("baseline_path", "", "the head's per-nozzle healthy baselines (.npz from record_baseline), classified "
     "by the model's baseline branch; empty: none", str, None),
    ("max_abs_sample_v", 10.0, "largest sample magnitude a sensor can produce, V; a row with a sample "
     "beyond it is invalid ('out_of_range'). Default: 5x the default head's +-2 V ADC range",
     float, (1e-6, 1e30)),
    ("labelling_process", False, "label in a child process (a core of its own: no GIL shared with "
     "receiving and publishing) instead of a thread of this one", bool, None),
)


class FdiNode(Node):
    """Decode (executor thread) -> submit (batching thread) -> collect and publish (collector thread)."""

    def __init__(self, **kwargs):
        super().__init__("fdi", **kwargs)
        self.config = c = _params.declare_all(self, PARAMS)
        self.add_on_set_parameters_callback(lambda params: _params.fixed_at_start(params))
        self.stats = FdiStats()
        self.labeller = self._make_labeller()
        self.model_id = self.labeller.model_id if self.labeller else "none"
        self._max_id = c["n_nozzles"] - 1 if c["n_nozzles"] > 0 else None
        self._labels_pub = self.create_publisher(LABELS_MSG_TYPE, topics.LABELS, RELIABLE_QOS)
        self._drying_pub = self.create_publisher(DRYING_MSG_TYPE, topics.DRYING_NOZZLES, RELIABLE_QOS)
        self._diag_pub = self.create_publisher(DIAGNOSTICS_MSG_TYPE, topics.DIAGNOSTICS, DIAGNOSTICS_QOS)
        self._backend, why = make_backend(self.labeller, in_process=c["labelling_process"] and bool(self.labeller))
        if why:
            self._config_error(why)
        self._handed_on = queue.SimpleQueue()  # batches submitted, in order, for the collector
        self._worker = BatchWorker(self._submit, max_queued=c["max_queued_frames"], name="fdi-labeller",
                                   max_batch_rows=c["max_batch_traces"], on_drop=self._on_dropped,
                                   max_in_flight=self._backend.depth)
        self._collector = threading.Thread(target=self._collect, name="fdi-collector", daemon=True)
        self._collector.start()
        self._sub = self.create_subscription(TRACE_MSG_TYPE, topics.TRACES, self._on_traces, TRACES_QOS)
        self._diag_timer = self.create_timer(c["diagnostics_period_s"], self._on_diagnostics)

    def _make_labeller(self):
        c, log = self.config, self.get_logger()
        if not c["model_path"]:
            log.error("no model_path given: frames will not be labelled")
            return None
        checks = dict(sample_rate_hz=c["sample_rate_hz"], n_samples=c["n_samples"], max_abs_v=c["max_abs_sample_v"])
        try:
            labeller = FrameLabeller(load_detector(c["model_path"]), **checks)
        except (ModelFileError, LabellerConfigError) as exc:
            self.get_logger().error(f"FDI model not loaded: {exc} (a model from before FaultDetector: "
                                    "retrain it, python -m inkdiag_ros.model_cache)")
            return None
        log.info(f"FDI model {labeller.model_id} loaded from {c['model_path']}")
        if c["baseline_path"]:
            try:
                baselines = NozzleBaselines.load(c["baseline_path"])
                labeller = FrameLabeller(labeller.detector, baselines, **checks)
                log.info(f"per-nozzle baselines of {len(baselines)} nozzles from {c['baseline_path']}")
            except (BaselineFileError, LabellerConfigError, OSError) as exc:
                self._config_error(f"per-nozzle baselines not used: {exc}")
        return labeller

    def _config_error(self, why: str) -> None:
        self.stats.misconfigured(why)
        self.get_logger().error(why)

    def destroy_node(self):
        if getattr(self, "_collector", None) is not None:
            self._worker.stop()
            self._handed_on.put(None)  # after the batches out: they are published first
            self._collector.join(10.0)
            self._backend.close()
        return super().destroy_node()

    def wait_idle(self, timeout: float | None = None) -> bool:
        """Block until every received frame is labelled and published (for tests and tools)."""
        return self._worker.wait_idle(timeout)

    def _on_traces(self, msg) -> None:
        self._on_trace_msg(msg)
        for taken in self._drain(64):
            self._on_trace_msg(taken)

    def _drain(self, at_most: int):
        """Messages already queued on the subscription, as rclpy's executor takes them: one wake-up per burst."""
        for _ in range(at_most):
            with self._sub.handle:
                taken = self._sub.handle.take_message(self._sub.msg_type, self._sub.raw)
            if taken is None:
                return
            yield taken[0]

    def _on_trace_msg(self, msg) -> None:
        self.stats.received()
        c = self.config
        try:
            frame = decode_traces(msg, max_nozzle_id=self._max_id, n_samples=c["n_samples"],
                                  sample_rate_hz=c["sample_rate_hz"])
        except FrameError as exc:
            self.stats.malformed(str(exc))
            self.get_logger().warning(f"dropped a malformed trace frame: {exc}", throttle_duration_sec=1.0)
            return
        if self.labeller is not None:
            self._worker.submit(frame, rows=frame.traces.shape[0])

    def _on_dropped(self, frame) -> None:
        self.stats.dropped(f"frame {frame.frame_id}: dropped, the labelling queue was full")
        self.get_logger().warning("labelling queue full: dropped the oldest frame", throttle_duration_sec=1.0)

    def _submit(self, frames) -> None:
        """Batching thread: one call to the backend; the collector publishes."""
        try:
            self._backend.submit([f.traces for f in frames], [f.first_nozzle for f in frames])
        except Exception as exc:  # noqa: BLE001 - not out in the backend: every frame of it fails
            self._handed_on.put((frames, exc))
        else:
            self._handed_on.put((frames, None))

    def _collect(self) -> None:
        """Collector thread: each batch's results, in order -> publish (or count failed) every frame."""
        while (item := self._handed_on.get()) is not None:
            frames, error = item
            try:
                if error is not None:
                    raise error
                results, busy_s = self._backend.collect()
            except Exception as exc:  # noqa: BLE001 - the batch is lost: each of its frames is counted
                results, busy_s = [FrameFailure(i, exc) for i in range(len(frames))], 0.0
            try:
                if self._backend.config_error and self.stats.config_error != self._backend.config_error:
                    self._config_error(self._backend.config_error)
                for frame, result in zip(frames, results):
                    self._publish(frame, result)
                self.stats.batch(len(frames), busy_s)
            finally:
                self._worker.finished()

    def _publish(self, frame, result) -> None:
        try:
            if isinstance(result, FrameFailure):
                raise result.error
            report = LabelsReport.from_arrays(
                frame_id=frame.frame_id, stamp=frame.stamp, first_nozzle=frame.first_nozzle, classes=result.classes,
                confidence=result.confidence, valid=result.valid, reasons=result.reasons, model_id=self.model_id)
            self._labels_pub.publish(encode_labels(report))
            self._drying_pub.publish(encode_drying(DryingNozzles.from_labels(report)))
        except Exception as exc:  # noqa: BLE001 - this frame failed; the batch's others go on
            if self.context.ok():  # else shutting down: nothing left to publish to
                why = f"{type(exc).__name__}: {exc}"
                self.stats.failed(f"frame {frame.frame_id}: {why}")
                self.get_logger().error(f"labelling frame {frame.frame_id} failed: {why}", throttle_duration_sec=1.0)
            return
        self.stats.labelled(report.counts, report.n_nozzles, int(np.count_nonzero(result.baseline)))

    def _on_diagnostics(self) -> None:
        level, message, values, counts = self.stats.period(self.labeller is not None)
        self._diag_pub.publish(build_diagnostics(
            namespace=self.get_namespace(), level=level, message=message, values={"model_id": self.model_id, **values},
            counts=counts, stamp=self.get_clock().now().to_msg()))


def main(args=None) -> int:
    return spin_node(FdiNode, args)


if __name__ == "__main__":
    sys.exit(main())
