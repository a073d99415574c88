"""printhead_sim: a simulated printhead publishing trace frames and their ground truth.

Publishes ``traces`` (one frame of all its nozzles per timer tick, sensor-data QoS) and ``ground_truth``
(reliable), relative to the node's namespace. The fault scenario (fixed faults, a random fault fraction, drying
nozzles whose viscosity rises over time) is :class:`inkdiag_core.simulation.scenario.HeadScenario`, on the head of
``head_profile`` (a complete :class:`inkdiag_core.HeadProfile` YAML file; empty: the shipped default head): its
channel, drive, sensor, spreads and sampling, which the trace header carries. A nominal profile or a bad file stops
the node at start (one line, exit status 2).

    printhead_sim --ros-args -r __ns:=/head_00 -p n_nozzles:=256 -p drying_nozzles:=[40]
    printhead_sim --ros-args -p head_profile:=heads/my_head.yaml --params-file inkdiag.yaml
    printhead_sim --record bags/sim1 --ros-args -r __ns:=/head_00   # and a rosbag2 bag of what it publishes
"""

from __future__ import annotations

import functools
import sys
import time

import numpy as np
from rclpy.node import Node

from ._spin import exit_now, spin_node
from .bags import pop_record_arg, recording_node

from msg_defs import (MAX_NOZZLE_ID, RELIABLE_QOS, TRACE_MSG_TYPE, TRACES_QOS, TRUTH_MSG_TYPE, FrameError,
                      encode_traces, encode_truth, topics, truth_from_arrays)

from . import _params
from ._head import HEAD_PROFILE_PARAM, head_from_parameters
from inkdiag_core import HeadProfile
from inkdiag_core.simulation.scenario import HeadScenario, defaults_on_head

PARAMS = (
    # name, default, description, kind, range
    ("n_nozzles", 64, "nozzles of the simulated head (one frame holds all of them, n_samples each: 2**27 at most)",
     int, (1, 100_000)),
    ("first_nozzle", 0, "id of the head's first nozzle (first_nozzle + n_nozzles <= 2**24)", int, (0, 2**24 - 1)),
    ("frame_rate_hz", 5.0, "frames published per second", float, (0.01, 1000.0)),
    HEAD_PROFILE_PARAM,
    ("sample_rate_hz", 0.0, "ADC sample rate of the traces, Hz; 0: the head profile's", float, (0.0, 100e6)),
    ("n_samples", 0, "samples per trace; 0: the head profile's", int, (0, 65536)),
    ("seed", 0, "seed of the scenario, of the head's nozzles (their tolerances persist across frames) and of the frames' noise", int, (0, 2**31 - 1)),
    ("fault_nozzles", [3, 11, 19, 27], "nozzle ids with a fixed fault (of this default or the packaged config's, "
     "those not on the head are left out with a warning; a list you give must be the head's)", "int[]", None),
    ("fault_classes", ["fully_blocked", "mature_air_bubble", "small_air_bubble", "empty_channel_1"],
     "fault class value of each fault_nozzles entry", "str[]", None),
    ("random_fault_fraction", 0.0, "fraction of the other nozzles given a random non-drying fault", float, (0.0, 1.0)),
    ("drying_nozzles", [40], "nozzle ids that dry over time (this default not on the head: none, with a warning)",
     "int[]", None),
    ("drying_start_factor", 2.4, "nozzle viscosity / ink viscosity of the drying nozzles at start",
     float, (1.0, 20.0)),
    ("drying_end_factor", 9.0, "nozzle viscosity factor reached after drying_duration_s", float, (1.0, 20.0)),
    ("drying_duration_s", 20.0, "time of the linear rise from start to end factor, s", float, (0.1, 1e6)),
    ("faults_start_s", 0.0, "every nozzle is healthy before this time (to record baselines); the faults "
     "appear and the drying starts then, s", float, (0.0, 1e6)),
    ("max_frames", 0, "publish this many frames, then stop; a printhead_sim process then ends 1 s later (the "
     "subscribers and its bag receive the last ones); 0: never stop", int, (0, 2**31 - 1)),
)


LINGER_S = 1.0
"""Seconds the node process keeps spinning after its last frame (``max_frames``) before it ends."""


class PrintheadSim(Node):
    """Simulated printhead: timer -> scenario -> simulator -> encode -> publish."""

    def __init__(self, *, ends_process: bool = False, shipped=(), **kwargs):
        """``ends_process``: its process ends once :meth:`finished` (the console entry point), else it stops.
        ``shipped``: fault lists given by the graph's packaged config, taken as defaults (left out where not on it)."""
        super().__init__("printhead_sim", **kwargs)
        self._ends_process = ends_process
        p = _params.declare_all(self, PARAMS)
        self.config = p
        self.profile = self._load_profile(p)
        if off := defaults_on_head(p, set(self._parameter_overrides) - set(shipped)):
            self.get_logger().warning(f"default fault or drying nozzles {off} are not on this head (nozzles "
                                      f"{p['first_nozzle']}..{p['first_nozzle'] + p['n_nozzles'] - 1}): left out")
        self._scenario = HeadScenario(
            n_nozzles=p["n_nozzles"], first_nozzle=p["first_nozzle"],
            fault_nozzles=p["fault_nozzles"], fault_classes=p["fault_classes"],
            random_fault_fraction=p["random_fault_fraction"], drying_nozzles=p["drying_nozzles"],
            drying_start_factor=p["drying_start_factor"], drying_end_factor=p["drying_end_factor"],
            drying_duration_s=p["drying_duration_s"], faults_start_s=p["faults_start_s"], seed=p["seed"],
            profile=self.profile)
        self.add_on_set_parameters_callback(lambda params: _params.fixed_at_start(params))
        self._rng = np.random.default_rng(p["seed"] + 1)
        self._pub = self.create_publisher(TRACE_MSG_TYPE, topics.TRACES, TRACES_QOS)
        self._truth_pub = self.create_publisher(TRUTH_MSG_TYPE, topics.GROUND_TRUTH, RELIABLE_QOS)
        self._t0 = None
        self.frames_published = 0
        self._last_at = None  # monotonic time of the last frame of max_frames
        self._timer = self.create_timer(1.0 / p["frame_rate_hz"], self._on_timer)
        self.get_logger().info(
            f"simulating {p['n_nozzles']} nozzles from {p['first_nozzle']} at {p['frame_rate_hz']:g} Hz on head "
            f"{self.profile.name!r} ({self.profile.sample_rate_hz / 1e6:g} MHz x {self.profile.n_samples}, sha256 "
            f"{self.profile.sha256[:12]}); faults {dict(zip(p['fault_nozzles'], p['fault_classes']))}, drying "
            f"{list(p['drying_nozzles'])}")

    @staticmethod
    def _load_profile(p) -> HeadProfile:
        """The head: ``head_profile`` (or the default head), sampled at the sampling parameters if given."""
        prof = head_from_parameters(dict(p), resample=True)  # bad or nominal: ValueError, exit 2
        if (last := p["first_nozzle"] + p["n_nozzles"] - 1) >= MAX_NOZZLE_ID:  # the wire's ids, as msg_defs says
            raise ValueError(f"nozzles {p['first_nozzle']}..{last}: the traces carry nozzle ids below {MAX_NOZZLE_ID}")
        try:  # the wire must carry its sample rate (msg_defs says how)
            encode_traces(np.zeros((1, prof.n_samples), np.float32), sample_rate_hz=prof.sample_rate_hz)
        except FrameError as exc:
            raise ValueError(f"head profile {prof.name!r} cannot be published: {exc}") from None
        return prof

    scenario = property(lambda self: self._scenario, doc="The node's :class:`HeadScenario`.")

    def finished(self) -> bool:
        """Whether ``max_frames`` frames went out at least :data:`LINGER_S` ago (the process may end)."""
        return self._last_at is not None and time.monotonic() - self._last_at >= LINGER_S

    def _on_timer(self) -> None:
        p = self.config
        if p["max_frames"] and self.frames_published >= p["max_frames"]:
            return
        now = self.get_clock().now().nanoseconds * 1e-9
        self._t0 = now if self._t0 is None else self._t0
        traces, labels, fm, mu_true = self._scenario.frame(now - self._t0, head_seed=[p["seed"], 1], rng=self._rng)
        fid = self.frames_published
        self._pub.publish(encode_traces(traces, first_nozzle=p["first_nozzle"], frame_id=fid,
                                        sample_rate_hz=self.profile.sample_rate_hz, stamp=now))
        self._truth_pub.publish(encode_truth(truth_from_arrays(
            frame_id=fid, stamp=now, first_nozzle=p["first_nozzle"], classes=labels, fm=fm,
            mu_nozzle=mu_true)))
        self.frames_published += 1
        if p["max_frames"] and self.frames_published >= p["max_frames"]:
            self._timer.cancel()
            self._last_at = time.monotonic()
            then = f"ending in {LINGER_S:g} s" if self._ends_process else "publishing no more"
            self.get_logger().info(f"published {self.frames_published} frames (max_frames): {then}")


def main(args=None) -> int:
    """``--record BAG_DIR`` (before ``--ros-args``): a rosbag2 bag of traces and ground_truth (inkdiag_ros.bags)."""
    try:
        argv, bag = pop_record_arg(sys.argv if args is None else args)
        sim = functools.partial(PrintheadSim, ends_process=True)
        make = sim if bag is None else recording_node(sim, bag, (topics.TRACES, topics.GROUND_TRUTH))
    except ValueError as exc:
        print(f"printhead_sim: {exc}", file=sys.stderr)
        return 2
    return spin_node(make, argv, prog="printhead_sim", until=PrintheadSim.finished)


if __name__ == "__main__":
    exit_now(main())  # the nodes down: not the interpreter's teardown too
