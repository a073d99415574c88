"""fe: fault estimation (f_m) of the drying nozzles of one printhead.

``traces`` (sensor-data QoS) and ``drying_nozzles`` (reliable, from fdi, one list per
trace message's nozzle range) -> :class:`inkdiag_core.DryingTracker`, which joins them on
``(frame_id, first_nozzle)`` in either order (every range is estimated with that same
frame's list; waiting partners are held in bounded buffers, ``max_pending``), screens
the listed rows, estimates their f_m in one batch on the head profile's model and
"vp_cal" constants, and feeds each nozzle's Kalman trend -> ``fm_estimates`` (JSON) and
``fm_estimates/array`` (Float64MultiArray), reliable, per frame and range with estimates.

``baseline_path``: the head's baselines with healthy f_m (``record_baseline``), each
estimate relative to its nozzle's healthy reading (``reports/fe.md``); one without f_m is
logged and not used. ``head_profile`` (empty: the shipped default head): frames of another
sampling are malformed. A bad or nominal profile, or baselines that do not load or are of
another head, stop the node at start (exit status 2). docs/nodes.md has the details.

    fe --ros-args -r __ns:=/head_00
"""

from __future__ import annotations


from rclpy.node import Node

from ._head import HEAD_PROFILE_PARAM, head_from_parameters, load_fm_baselines
from ._spin import exit_now, spin_node
from .stats import FeStats

from inkdiag_core import DryingTracker
from msg_defs import (
    DIAGNOSTICS_MSG_TYPE,
    DIAGNOSTICS_QOS,
    DRYING_MSG_TYPE,
    ESTIMATES_ARRAY_MSG_TYPE,
    ESTIMATES_MSG_TYPE,
    RELIABLE_QOS,
    TRACE_MSG_TYPE,
    TRACES_QOS,
    FmEstimates,
    build_diagnostics,
    decode_drying,
    decode_traces_serialized,
    encode_estimates,
    encode_estimates_array,
    topics,
)

from . import _params

PARAMS = (
    ("max_estimates_per_frame", 64, "at most this many drying nozzles are estimated per frame and "
     "nozzle range (lowest ids first); bounds the cost per trace message. May change at runtime "
     "(ros2 param set)", int, (1, 100_000)),
    ("max_pending", 128, "trace messages (one frame's nozzle range), and drying lists, each held at most "
     "while waiting for their partner; the oldest is dropped beyond this. Keep it above fdi's "
     "max_queued_frames plus 32 (fdi lags by up to that many messages). Held traces keep their message's memory",
     int, (1, 10_000)),
    ("trend_accel_std", 5e3, "white acceleration noise of the f_m trend, 1/s^3", float, (1.0, 1e9)),
    ("trend_rel_floor", 0.05, "relative floor of one estimate's standard deviation", float, (0.0, 1.0)),
    ("baseline_path", "", "the head's per-nozzle baselines with healthy f_m (.npz from record_baseline): "
     "each estimate is relative to its nozzle's healthy reading; empty: none", str, None),
    HEAD_PROFILE_PARAM,
    ("diagnostics_period_s", 1.0, "period of fe's status on /diagnostics ('inkdiag fe: <namespace>'), s", float,
     (0.1, 60.0)),
)
DYNAMIC = ("max_estimates_per_frame",)  # may change at runtime (ros2 param set); the others are read-only


class FeNode(Node):
    """Decode -> DryingTracker (join per frame and range, estimate, trend) -> encode -> publish."""

    def __init__(self, **kwargs):
        super().__init__("fe", **kwargs)
        self.config = c = _params.declare_all(self, PARAMS, dynamic=DYNAMIC)
        self.add_on_set_parameters_callback(lambda params: _params.fixed_at_start(params, dynamic=DYNAMIC))
        self.add_post_set_parameters_callback(self._after_set)
        self.profile = head_from_parameters(c)  # a bad or nominal file: ValueError, exit 2 at start
        self.baselines = load_fm_baselines(c["baseline_path"], self.profile, self.get_logger())
        self.tracker = DryingTracker(
            profile=self.profile, max_estimates=c["max_estimates_per_frame"], max_pending=c["max_pending"],
            baselines=self.baselines, trend_accel_std=c["trend_accel_std"], trend_rel_floor=c["trend_rel_floor"])
        self.tracker.warm_up()  # kernels and estimator loaded now, not on the first frames (0.5 s: a burst was lost)
        self.frames_malformed = 0
        self.estimates_published = 0
        self.stats = FeStats()
        self._clocks_said = 0  # the trend bank's clock restarts (epoch) already logged
        self._pub = self.create_publisher(ESTIMATES_MSG_TYPE, topics.FM_ESTIMATES, RELIABLE_QOS)
        self._array_pub = self.create_publisher(ESTIMATES_ARRAY_MSG_TYPE, topics.FM_ESTIMATES_ARRAY, RELIABLE_QOS)
        self._diag_pub = self.create_publisher(DIAGNOSTICS_MSG_TYPE, topics.DIAGNOSTICS, DIAGNOSTICS_QOS)
        self._diag_timer = self.create_timer(c["diagnostics_period_s"], self._on_diagnostics)
        self._drying_sub = self.create_subscription(DRYING_MSG_TYPE, topics.DRYING_NOZZLES,
                                                    self._on_drying, RELIABLE_QOS)
        # raw: the 2 MB of a 1,024-nozzle frame are viewed in the taken bytes, not converted to a message
        self._traces_sub = self.create_subscription(TRACE_MSG_TYPE, topics.TRACES, self._on_traces,
                                                    TRACES_QOS, raw=True)

    def _on_diagnostics(self) -> None:
        if self.context.ok():
            level, message, values = self.stats.period(self.tracker, self.frames_malformed, self.estimates_published)
            self._diag_pub.publish(build_diagnostics(namespace=self.get_namespace(), level=level, message=message,
                                                     values=values, counts={}, node="fe",
                                                     stamp=self.get_clock().now().to_msg()))

    def _after_set(self, params) -> None:
        self.tracker.max_estimates = self.get_parameter("max_estimates_per_frame").value

    def _on_drying(self, msg) -> None:
        try:
            d = decode_drying(msg)
            out = self.tracker.add_drying(d.frame_id, d.nozzles, first_nozzle=d.first_nozzle, n_nozzles=d.n_nozzles,
                                          complete=not d.dropped, stamp=d.stamp)  # dropped: no trend ends
        except (ValueError, OverflowError) as exc:  # MessageError is a ValueError; the tracker's checks too
            self._malformed("drying_nozzles message", exc)
            return
        _ = d.dropped and self._malformed("part of a drying_nozzles message", d.dropped)  # the rest is used
        self._publish(out)

    def _on_traces(self, msg: bytes) -> None:
        try:
            f = decode_traces_serialized(msg)
            out = self.tracker.add_traces(f.traces, first_nozzle=f.first_nozzle, frame_id=f.frame_id,
                                          stamp=f.stamp, sample_rate_hz=f.sample_rate_hz)
        except (ValueError, OverflowError) as exc:  # a frame the codec or the estimator cannot take
            self._malformed("trace frame", exc)
            return
        self._publish(out)

    def _malformed(self, what, exc) -> None:
        self.frames_malformed += 1
        self.stats.last_error = f"{what}: {exc}"
        self.get_logger().warning(f"dropped a malformed {what}: {exc}", throttle_duration_sec=1.0)

    def _publish(self, results) -> None:
        if self.tracker.trends.epoch > self._clocks_said:  # its own call site: the notes' throttle cannot hide it
            self.get_logger().warning(
                f"the trace stamps went back to {self.tracker.trends.clock:.3f} s (a restarted controller clock, a "
                "replayed recording; often: two clocks publishing here): each nozzle's f_m trend restarts at its next "
                "frame", throttle_duration_sec=5.0)
            self._clocks_said = self.tracker.trends.epoch
        for r in results:
            if r.note:
                self.get_logger().warning(f"frame {r.frame_id}: {r.note}", throttle_duration_sec=5.0)
            out = FmEstimates.from_columns(r.frame_id, r.stamp, first_nozzle=r.first_nozzle, **r.columns)
            try:
                self._pub.publish(encode_estimates(out))
                self._array_pub.publish(encode_estimates_array(out))
            except Exception:  # a stop while a burst was estimated: the context went down, nothing to publish to
                if self.context.ok():
                    raise
                return
            self.estimates_published += 1


def main(args=None) -> int:
    return spin_node(FeNode, args, events=True)  # its cost per frame is the executor's too (issue 12)


if __name__ == "__main__":
    exit_now(main())  # the nodes down: not the interpreter's teardown too
