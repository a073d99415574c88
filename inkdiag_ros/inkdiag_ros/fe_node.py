"""fe: fault estimation (f_m) of the drying nozzles of one printhead.

Subscribes to ``traces`` (sensor-data QoS) and ``drying_nozzles`` (reliable,
from the fdi node). For each trace frame, the rows of the nozzles currently
labelled dried are screened and their f_m estimated in one batch (x0-free
variable projection on the nominal channel model: the traces' unknown gain
and offset drop out); each nozzle's history feeds a Kalman trend
(:class:`inkdiag_core.FmTrendBank`) that gives the smoothed f_m, its rate and
the time until the deeply-dried level. Publishes ``fm_estimates`` (JSON) and
``fm_estimates/array`` (Float64MultiArray), reliable.

With ``baseline_path`` (the head's baselines from ``record_baseline``, with
healthy f_m per nozzle), each nozzle's estimate is taken relative to its own
healthy reading (``estimate_fm_batch(..., baseline_fm=...)``): a real nozzle
differs from the nominal model within its tolerances and the estimator reads
that as a fault; its healthy reading removes the part that acts as an offset
(``reports/fe.md``). Nozzles without one are estimated as before. A file that
does not load or has no f_m is logged and the node runs without it.

    fe --ros-args -r __ns:=/head_00
"""

from __future__ import annotations

import sys

import numpy as np
from rclpy.node import Node

from ._spin import spin_node

from inkdiag_core import (
    BaselineFileError,
    FmTrendBank,
    InkChannelModel,
    NozzleBaselines,
    estimate_fm_batch,
    screen_traces,
)
from msg_defs import (
    DRYING_MSG_TYPE,
    ESTIMATES_ARRAY_MSG_TYPE,
    ESTIMATES_MSG_TYPE,
    RELIABLE_QOS,
    TRACE_MSG_TYPE,
    TRACES_QOS,
    FmEstimates,
    MessageError,
    decode_drying,
    decode_traces,
    encode_estimates,
    encode_estimates_array,
    topics,
)

from . import _params

PARAMS = (
    ("max_estimates_per_frame", 64, "at most this many drying nozzles are estimated per frame "
     "(lowest ids first); bounds the cost per frame", int, (1, 100_000)),
    ("trend_accel_std", 5e3, "white acceleration noise of the f_m trend, 1/s^3", float, (1.0, 1e9)),
    ("trend_rel_floor", 0.05, "relative floor of one estimate's standard deviation", float, (0.0, 1.0)),
    ("baseline_path", "", "the head's per-nozzle baselines with healthy f_m (.npz from record_baseline): "
     "each estimate is relative to its nozzle's healthy reading; empty: none", str, None),
)


class FeNode(Node):
    """Decode -> rows of the drying nozzles -> estimate_fm_batch -> trend -> encode -> publish."""

    def __init__(self, **kwargs):
        super().__init__("fe", **kwargs)
        self.config = _params.declare_all(self, PARAMS)
        self.add_on_set_parameters_callback(self._on_set)
        self.model = InkChannelModel()
        self.trends = FmTrendBank(accel_std=self.config["trend_accel_std"],
                                  rel_floor=self.config["trend_rel_floor"])
        self.drying = ()
        self.frames_malformed = 0
        self.estimates_published = 0
        self.estimates_with_baseline = 0  # nozzle estimates taken relative to the nozzle's healthy f_m
        self.baselines = self._load_baselines(self.config["baseline_path"])
        self._pub = self.create_publisher(ESTIMATES_MSG_TYPE, topics.FM_ESTIMATES, RELIABLE_QOS)
        self._array_pub = self.create_publisher(ESTIMATES_ARRAY_MSG_TYPE, topics.FM_ESTIMATES_ARRAY,
                                                RELIABLE_QOS)
        self._drying_sub = self.create_subscription(DRYING_MSG_TYPE, topics.DRYING_NOZZLES,
                                                    self._on_drying, RELIABLE_QOS)
        self._traces_sub = self.create_subscription(TRACE_MSG_TYPE, topics.TRACES, self._on_traces,
                                                    TRACES_QOS)

    def _load_baselines(self, path: str):
        if not path:
            return None
        try:
            baselines = NozzleBaselines.load(path)
        except BaselineFileError as exc:
            self.get_logger().error(f"f_m baselines not used: {exc}")
            return None
        n_fm = 0 if baselines.fm is None else int((~np.isnan(baselines.fm)).sum())
        if not n_fm:
            self.get_logger().error(f"f_m baselines not used: {path} holds no healthy f_m "
                                    "(recorded with fm_frames:=0?)")
            return None
        self.get_logger().info(f"healthy f_m baselines of {n_fm} nozzles from {path}")
        return baselines

    def _baseline_fm(self, ids, frame, n_samples):
        """Healthy f_m of the nozzles ``ids`` (0: none), or None without usable baselines."""
        b = self.baselines
        if b is None:
            return None
        if (frame.sample_rate_hz, n_samples) != (b.sample_rate_hz, b.n_samples):
            self.get_logger().warning(
                f"frame {frame.frame_id} is {frame.sample_rate_hz:g} Hz x {n_samples} samples, the f_m "
                f"baselines {b.sample_rate_hz:g} Hz x {b.n_samples}: estimated without them",
                throttle_duration_sec=5.0)
            return None
        has, fm = b.lookup_fm(ids)
        self.estimates_with_baseline += int(has.sum())
        return fm

    def _on_set(self, params):
        for p in params:
            if p.name == "max_estimates_per_frame":
                continue  # read at each frame
            return _params.fixed_at_start([p])
        return _params.result(True)

    def _on_drying(self, msg) -> None:
        try:
            self.drying = decode_drying(msg).nozzles
        except MessageError as exc:
            self.frames_malformed += 1
            self.get_logger().warning(f"dropped a malformed drying_nozzles message: {exc}",
                                      throttle_duration_sec=1.0)

    def _on_traces(self, msg) -> None:
        if not self.drying:
            return
        try:
            frame = decode_traces(msg)
        except MessageError as exc:
            self.frames_malformed += 1
            self.get_logger().warning(f"dropped a malformed trace frame: {exc}", throttle_duration_sec=1.0)
            return
        cap = self.get_parameter("max_estimates_per_frame").value
        ids, rows = frame.rows_of(self.drying[:cap])
        valid, _ = screen_traces(rows)
        ids, rows = ids[valid], rows[valid]
        if ids.size == 0:
            return
        est = estimate_fm_batch(rows, self.model, frame.sample_rate_hz,
                                baseline_fm=self._baseline_fm(ids, frame, rows.shape[1]))
        trend, rate, eta = self.trends.update(frame.stamp, ids, est.fm, est.std)
        out = FmEstimates.from_columns(
            frame.frame_id, frame.stamp, nozzle=ids, fm=est.fm, fm_std=est.std, d_mu=est.d_mu,
            viscosity=est.viscosity, fm_trend=trend, fm_rate=rate, eta_deeply_dried_s=eta)
        self._pub.publish(encode_estimates(out))
        self._array_pub.publish(encode_estimates_array(out))
        self.estimates_published += 1


def main(args=None) -> int:
    return spin_node(FeNode, args)


if __name__ == "__main__":
    sys.exit(main())
