"""fdi: fault detection and isolation of every trace frame of one printhead.

Subscribes to ``traces`` (sensor-data QoS); per frame: decode and validate ->
screen and classify the whole batch with the FDI model -> publish ``labels``
and ``drying_nozzles`` (reliable), one of each per trace message (a frame, or
one nozzle range of it: both say the range, ``first_nozzle`` and
``n_nozzles``, so fe joins each list with its own traces). Decoding runs in
the subscription callback; labelling runs on a worker thread that takes every
frame queued while it was busy and classifies them in one pass
(:mod:`.batching`): one frame at a time when the load is light, larger
batches under load. A full queue (``max_queued_frames``) drops its oldest
frame and counts it (``frames_dropped`` in ``/diagnostics``). A malformed frame is logged (throttled)
with what was wrong and counted; invalid rows (NaN/Inf, flat, clipped) are
labelled invalid with their reason, as are rows with a sample beyond
``max_abs_sample_v`` (``out_of_range``: no sensor produces it) and rows whose
features come out non-finite (``non_finite_features``). Publishes ``/diagnostics`` every
``diagnostics_period_s``. The model file is verified against its manifest
(sha256, library versions) before it is loaded.

With ``labelling_process`` the classifier runs in a child process instead
(:mod:`.labelling_process`): the worker thread hands each batch to it and a
collector thread publishes the labels, so receiving, labelling and
publishing overlap on two cores instead of sharing one GIL. A child that
dies costs the frames it had (``frames_failed``); the next batch starts a new one.

With ``baseline_path`` (the head's recorded per-nozzle baselines, ``record_baseline``)
and ``baseline_model_path`` (a ``kpi_y+baseline`` model), the rows of nozzles that
have a baseline are classified against it, the others with ``model_path``'s model
(``rows_with_baseline`` in ``/diagnostics``). A baseline or model that does not
load or does not fit the node's settings is logged and reported, and the node
labels without baselines.

    fdi --ros-args -r __ns:=/head_00 -p model_path:=models/fdi_default.joblib
"""

from __future__ import annotations

import queue
import sys
import threading
import time

import numpy as np
from rclpy.node import Node

from ._spin import spin_node

from inkdiag_core import (
    BaselineFileError,
    BaselineModel,
    ModelFileError,
    NozzleBaselines,
    label_frames_isolated,
    load_model,
)
from msg_defs import (
    DIAGNOSTICS_MSG_TYPE,
    DIAGNOSTICS_QOS,
    DRYING_MSG_TYPE,
    LABELS_MSG_TYPE,
    RELIABLE_QOS,
    TRACE_MSG_TYPE,
    TRACES_QOS,
    DryingNozzles,
    FrameError,
    LabelsReport,
    build_diagnostics,
    decode_traces,
    encode_drying,
    encode_labels,
    topics,
)

from . import _params
from .batching import BatchWorker
from .labelling_process import LabellingProcess, LabellingProcessError
from .stats import FdiStats

PARAMS = (
    ("model_path", "", "FDI model file (.joblib with its .manifest.json beside it)", str, None),
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
    ("baseline_path", "", "the head's per-nozzle healthy baselines (.npz from record_baseline); "
     "empty: none", str, None),
    ("baseline_model_path", "", "kpi_y+baseline FDI model for the nozzles that have a baseline", str, None),
    ("max_abs_sample_v", 10.0, "largest sample magnitude a sensor can produce, V; a row with a sample "
     "beyond it is invalid ('out_of_range'). Default: 5x the default head's +-2 V ADC range",
     float, (1e-6, 1e30)),
    ("labelling_process", False, "label in a child process (a core of its own: no GIL shared with "
     "receiving and publishing) instead of a thread of this one", bool, None),
)


def model_id(manifest: dict) -> str:
    """Short id of a model file: ``fdi-<kind>-<features>-<first 12 hex digits of its sha256>``."""
    cfg = manifest.get("config", {})
    return f"fdi-{cfg.get('kind', '?')}-{cfg.get('features', '?')}-{str(manifest.get('sha256', ''))[:12]}"


class FdiNode(Node):
    """Decode (executor thread) -> label_frames (worker thread) -> encode -> publish.

    Counters for ``/diagnostics`` are in :attr:`stats`; each counter has one
    writer thread (received / malformed: the executor's; labelled / failed:
    the worker's; dropped: the executor's).
    """

    def __init__(self, **kwargs):
        super().__init__("fdi", **kwargs)
        self.config = _params.declare_all(self, PARAMS)
        self.add_on_set_parameters_callback(lambda params: _params.fixed_at_start(params))
        self.stats = FdiStats()
        self.model = None
        self.model_id = "none"
        self.fd_threshold = 0.5
        self.baseline = None
        self._load(self.config["model_path"])
        self._load_baseline(self.config["baseline_path"], self.config["baseline_model_path"])
        self._labeller = None
        if self.model is not None and self.config["labelling_process"]:
            self._start_labelling_process()
        n = self.config["n_nozzles"]
        self._max_id = n - 1 if n > 0 else None
        self._labels_pub = self.create_publisher(LABELS_MSG_TYPE, topics.LABELS, RELIABLE_QOS)
        self._drying_pub = self.create_publisher(DRYING_MSG_TYPE, topics.DRYING_NOZZLES, RELIABLE_QOS)
        self._diag_pub = self.create_publisher(DIAGNOSTICS_MSG_TYPE, topics.DIAGNOSTICS, DIAGNOSTICS_QOS)
        in_child = self._labeller is not None
        self._worker = BatchWorker(self._submit_batch if in_child else self._label_batch,
                                   max_queued=self.config["max_queued_frames"],
                                   max_batch_rows=self.config["max_batch_traces"],
                                   on_drop=self._on_dropped, on_error=self._on_worker_error,
                                   name="fdi-labeller", max_in_flight=self._labeller.depth if in_child else None)
        if in_child:
            self._handed_on = queue.SimpleQueue()  # batches out in the labelling process, in order
            self._collector = threading.Thread(target=self._collect, name="fdi-collector", daemon=True)
            self._collector.start()
        self._sub = self.create_subscription(TRACE_MSG_TYPE, topics.TRACES, self._on_traces, TRACES_QOS)
        self._diag_timer = self.create_timer(self.config["diagnostics_period_s"], self._on_diagnostics)

    def destroy_node(self):
        worker = getattr(self, "_worker", None)  # absent if __init__ failed part-way
        if worker is not None:
            worker.stop()
        collector = getattr(self, "_collector", None)
        if collector is not None:
            self._handed_on.put(None)  # after the batches out: they are published first
            collector.join(10.0)
        labeller = getattr(self, "_labeller", None)
        if labeller is not None:
            labeller.close()
        return super().destroy_node()

    def wait_idle(self, timeout: float | None = None) -> bool:
        """Block until every received frame is labelled (for tests and tools)."""
        return self._worker.wait_idle(timeout)

    def _load(self, path: str) -> None:
        if not path:
            self.get_logger().error("no model_path given: frames will not be labelled")
            return
        try:
            self.model, manifest = load_model(path)
        except ModelFileError as exc:
            self.get_logger().error(f"FDI model not loaded: {exc}")
            return
        self.model_id = model_id(manifest)
        self.fd_threshold = float(manifest.get("config", {}).get("fd_threshold", 0.5))
        self.get_logger().info(f"FDI model {self.model_id} loaded from {path} "
                               f"(fault-detection threshold {self.fd_threshold:.3g})")

    def _load_baseline(self, path: str, model_path: str) -> None:
        if not path and not model_path:
            return
        try:
            if not (path and model_path):
                raise ValueError("baseline_path and baseline_model_path go together; got only "
                                 + ("baseline_path" if path else "baseline_model_path"))
            baselines = NozzleBaselines.load(path)
            pipe, manifest = load_model(model_path)
            cfg = manifest.get("config", {})
            if cfg.get("features") != "kpi_y+baseline":
                raise ValueError(f"{model_path} is a {cfg.get('features')!r} model, not kpi_y+baseline")
            want = (self.config["sample_rate_hz"], self.config["n_samples"])
            for name, got in ((path, (baselines.sample_rate_hz, baselines.n_samples)),
                              (model_path, (cfg.get("sample_rate_hz", want[0]), cfg.get("n_samples", want[1])))):
                if tuple(got) != want:
                    raise ValueError(f"{name} is for {got[0]:g} Hz x {got[1]} samples, this node takes "
                                     f"{want[0]:g} Hz x {want[1]}")
            threshold = float(cfg.get("fd_threshold", 0.5))
        except (BaselineFileError, ModelFileError, ValueError, TypeError) as exc:
            self.stats.misconfigured(f"per-nozzle baselines not used: {exc}")
            self.get_logger().error(f"per-nozzle baselines not used: {exc}")
            return
        self.baseline = BaselineModel(pipe, baselines, threshold)
        self.model_id = f"{self.model_id}+{model_id(manifest)}"
        self.get_logger().info(f"per-nozzle baselines of {len(baselines)} nozzles from {path}, "
                               f"model {model_id(manifest)}")

    def _start_labelling_process(self) -> None:
        try:
            self._labeller = LabellingProcess(self.model, fd_threshold=self.fd_threshold, baseline=self.baseline,
                                              max_abs_v=self.config["max_abs_sample_v"])
        except LabellingProcessError as exc:
            self.stats.misconfigured(f"labelling in this process: {exc}")
            self.get_logger().error(f"labelling in this process: {exc}")
            return
        self.get_logger().info(f"labelling in child process {self._labeller.pid}")

    def _on_traces(self, msg) -> None:
        self._on_trace_msg(msg)
        # Take what else is queued now, as the executor would (rclpy's Executor._take_subscription):
        # one executor wake-up and wait-set rebuild per burst instead of per message.
        for _ in range(64):
            with self._sub.handle:
                taken = self._sub.handle.take_message(self._sub.msg_type, self._sub.raw)
            if taken is None:
                break
            self._on_trace_msg(taken[0])

    def _on_trace_msg(self, msg) -> None:
        self.stats.received()
        try:
            frame = decode_traces(msg, max_nozzle_id=self._max_id, n_samples=self.config["n_samples"],
                                  sample_rate_hz=self.config["sample_rate_hz"])
        except FrameError as exc:
            self.stats.malformed(str(exc))
            self.get_logger().warning(f"dropped a malformed trace frame: {exc}", throttle_duration_sec=1.0)
            return
        if self.model is None:
            return
        self._worker.submit(frame, rows=frame.traces.shape[0])

    def _on_dropped(self, frame) -> None:
        self.stats.dropped(f"frame {frame.frame_id}: dropped, the labelling queue was full")
        self.get_logger().warning("labelling queue full: dropped the oldest frame",
                                  throttle_duration_sec=1.0)

    def _on_worker_error(self, exc: BaseException) -> None:
        self.stats.failed(f"{type(exc).__name__}: {exc}")
        self.get_logger().error(f"labelling worker error: {exc!r}", throttle_duration_sec=1.0)

    def _label_batch(self, frames) -> None:
        """Worker thread: label the frames together (each alone if that fails), publish each."""
        t0 = time.perf_counter()
        self._publish_all(frames, label_frames_isolated(
            self.model, [f.traces for f in frames], fd_threshold=self.fd_threshold,
            first_nozzles=[f.first_nozzle for f in frames], baseline=self.baseline,
            max_abs_v=self.config["max_abs_sample_v"]))
        self.stats.batch(len(frames), time.perf_counter() - t0)

    def _submit_batch(self, frames) -> None:
        """Labelling thread, with a labelling process: hand the batch to it (the collector publishes).

        If no child can start at all (it fails to import the core), label here instead.
        """
        if self._labeller.broken is None:
            try:
                self._labeller.submit([f.traces for f in frames], [f.first_nozzle for f in frames])
            except Exception as exc:  # noqa: BLE001 - the batch is lost, counted; the node goes on
                if self._labeller.broken is None:
                    self._publish_all(frames, [_why(exc)] * len(frames))
                    self._worker.finished()  # not handed on: done
                    return
            else:
                self._handed_on.put(frames)
                return
        why = f"the labelling process cannot start ({self._labeller.broken}): labelling on a thread"
        if self.stats.config_error != why:
            self.stats.misconfigured(why)
            self.get_logger().error(why)
        self._label_batch(frames)  # if it raises, the worker counts the batch done itself
        self._worker.finished()

    def _collect(self) -> None:
        """Collector thread: publish each batch's labels from the labelling process, in order."""
        while (frames := self._handed_on.get()) is not None:
            busy0 = self._labeller.busy_s
            try:
                try:
                    results = self._labeller.collect()
                except Exception as exc:  # noqa: BLE001 - the child died, or labels did not unpickle
                    results = [_why(exc)] * len(frames)
                self._publish_all(frames, results)
                self.stats.batch(len(frames), self._labeller.busy_s - busy0)
            except Exception as exc:  # noqa: BLE001 - counted and logged; the collector goes on
                self._on_worker_error(exc)
            finally:
                self._worker.finished()

    def _failed(self, frame, why: str) -> None:
        self.stats.failed(f"frame {frame.frame_id}: {why}")
        self.get_logger().error(f"labelling frame {frame.frame_id} failed: {why}", throttle_duration_sec=1.0)

    def _publish_all(self, frames, results) -> None:
        """Publish each frame's labels; count a frame whose result is a ``str`` (why) failed."""
        for frame, rows in zip(frames, results):
            if isinstance(rows, str):
                self._failed(frame, rows)
            else:
                self._publish(frame, rows)

    def _publish(self, frame, rows) -> None:
        try:
            report = LabelsReport.from_arrays(
                frame_id=frame.frame_id, stamp=frame.stamp, first_nozzle=frame.first_nozzle,
                classes=rows.classes, confidence=rows.confidence, valid=rows.valid,
                reasons=rows.reasons, model_id=self.model_id)
            self._labels_pub.publish(encode_labels(report))
            self._drying_pub.publish(encode_drying(DryingNozzles.from_labels(report)))
        except Exception as exc:  # noqa: BLE001 - this frame failed; the batch's others go on
            if self.context.ok():
                self._failed(frame, f"reporting its labels: {type(exc).__name__}: {exc}")
            return  # else shutting down (SIGINT/SIGTERM): nothing left to publish to
        self.stats.labelled(report.counts, report.n_nozzles, int(np.count_nonzero(rows.baseline)))

    def _on_diagnostics(self) -> None:
        level, message, values, counts = self.stats.period(self.model is not None)
        values = {"model_id": self.model_id, **values}
        self._diag_pub.publish(build_diagnostics(
            namespace=self.get_namespace(), level=level, message=message, values=values,
            counts=counts, stamp=self.get_clock().now().to_msg()))


def _why(exc: BaseException) -> str:
    return str(exc) if isinstance(exc, LabellingProcessError) else f"{type(exc).__name__}: {exc}"


def main(args=None) -> int:
    return spin_node(FdiNode, args)


if __name__ == "__main__":
    sys.exit(main())
