"""record_baseline: record a printhead's per-nozzle healthy baselines from its trace frames.

Run it while the head is known to jet (after a purge, at commissioning): it subscribes to ``traces`` in the
head's namespace, keeps each nozzle's first ``n_frames`` valid rows (:class:`inkdiag_core.BaselineRecorder`:
nozzle ranges in any order; invalid rows, rows beyond 5x the head's ADC range and, with ``n_nozzles``, frames
outside the head's ids skipped) and, once ``n_nozzles`` are complete, writes their baselines (median KPIs,
healthy f_m for fe, reference traces for fdi's gate: :class:`inkdiag_core.NozzleBaselines`) to
``output_path`` and exits 0. At ``timeout_s``, or stopped by SIGINT / SIGTERM, it writes the nozzles
complete so far and exits 1 if there are none. ``head_profile`` is the head (empty: the default one); a bad
or nominal profile, or a sampling not the profile's, stops it at start (one line, exit 2). docs/nodes.md.

    record_baseline --ros-args -r __ns:=/head_07 -p output_path:=baselines/head_07.npz -p n_nozzles:=2656
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

from rclpy.node import Node

from inkdiag_core import BaselineRecorder, refuse_to_replace
from msg_defs import TRACE_MSG_TYPE, TRACES_QOS, FrameError, decode_traces, topics

from . import _params
from ._head import HEAD_PROFILE_PARAM, head_from_parameters
from ._spin import exit_now, spin_node

PARAMS = (
    ("output_path", "", "where to write the baselines (.npz)", str, None),
    ("n_frames", 8, "healthy frames per nozzle in its baseline (median)", int, (1, 1000)),
    ("fm_frames", 3, "also record each nozzle's healthy f_m (for fe): the median over its first "
     "fm_frames valid rows, at most n_frames; 0: none (about 1 ms of CPU per row)", int, (0, 1000)),
    ("n_nozzles", 0, "nozzles of the head to wait for, ids first_nozzle..first_nozzle + n_nozzles - 1; a frame "
     "with other ids is rejected (0: any ids, until timeout_s)", int, (0, 2**24)),
    ("first_nozzle", 0, "id of the head's first nozzle (with n_nozzles)", int, (0, 2**24 - 1)),
    ("timeout_s", 60.0, "give up waiting after this long, s; writes the complete nozzles (so does a SIGINT or "
     "SIGTERM)", float, (0.1, 86400.0)),
    HEAD_PROFILE_PARAM,
    ("n_samples", 0, "samples per trace; other frames are rejected; 0: the head profile's (else it must be "
     "the profile's)", int, (0, 65536)),
    ("sample_rate_hz", 0.0, "sample rate of the traces, Hz; other frames are rejected; 0: the head profile's "
     "(else it must be the profile's)", float, (0.0, 1e9)),
)


class BaselineRecorderNode(Node):
    """Collects baselines from ``traces``; :attr:`done` once the file is written (or abandoned)."""

    def __init__(self, **kwargs):
        super().__init__("record_baseline", **kwargs)
        self.config = c = _params.declare_all(self, PARAMS)
        self.add_on_set_parameters_callback(lambda params: _params.fixed_at_start(params))
        if not c["output_path"]:
            raise ValueError("output_path is required (-p output_path:=baselines/head.npz)")
        try:  # a directory, device or pipe there: said now, not after the recording
            refuse_to_replace(c["output_path"])
        except OSError as exc:
            raise ValueError(f"output_path: {exc}") from None
        if c["n_nozzles"] and c["first_nozzle"] + c["n_nozzles"] > 2**24:  # the wire's ids are below 2**24
            raise ValueError(f"first_nozzle {c['first_nozzle']} + n_nozzles {c['n_nozzles']} is beyond 2**24")
        self.profile = head_from_parameters(c)  # bad, nominal or contradicting: ValueError, exit 2 at start
        self.recorder = BaselineRecorder(n_frames=c["n_frames"], sample_rate_hz=c["sample_rate_hz"],
                                         n_samples=c["n_samples"], profile=self.profile,
                                         fm_frames=min(c["fm_frames"], c["n_frames"]), reference=True)
        self.frames, self.malformed, self.last_error, self.done, self.written = 0, 0, "", False, None  # written: path
        self._t0 = time.monotonic()
        self._sub = self.create_subscription(TRACE_MSG_TYPE, topics.TRACES, self._on_traces, TRACES_QOS)
        self._timer = self.create_timer(1.0, self._on_tick)
        self.get_logger().info(
            f"recording {c['n_frames']} healthy frames per nozzle"
            + (f" (f_m from the first {self.recorder.fm_frames})" if self.recorder.fm_frames else "")
            + (f" of {c['n_nozzles']} nozzles from {c['first_nozzle']}" if c["n_nozzles"] else "")
            + f" of head {self.profile.name!r} ({self.profile.sample_rate_hz / 1e6:g} MHz x {self.profile.n_samples}, "
            f"sha256 {self.profile.sha256[:12]}) into {c['output_path']} (timeout {c['timeout_s']:g} s)")

    def _on_traces(self, msg) -> None:
        if self.done:
            return
        c = self.config
        try:
            frame = decode_traces(msg, n_samples=self.recorder.n_samples,
                                  sample_rate_hz=self.recorder.sample_rate_hz)
            lo, n, last = c["first_nozzle"], c["n_nozzles"], frame.first_nozzle + frame.traces.shape[0] - 1
            if n and (frame.first_nozzle < lo or last >= lo + n):  # another head's: not counted towards this one's
                raise FrameError(f"nozzles {frame.first_nozzle}..{last} outside this head's {lo}..{lo + n - 1}")
            self.recorder.add(frame.first_nozzle, frame.traces)
        except (FrameError, ValueError) as exc:  # the recorder never dies of input
            self.malformed += 1
            self.last_error = str(exc)
            self.get_logger().warning(f"dropped a malformed trace frame: {exc}", throttle_duration_sec=1.0)
            return
        self.frames += 1
        if c["n_nozzles"] and self.recorder.n_complete >= c["n_nozzles"]:
            self._finish()

    def _on_tick(self) -> None:
        if self.done:
            return
        if time.monotonic() - self._t0 >= self.config["timeout_s"]:
            self._finish(f"timed out after {self.config['timeout_s']:g} s")
            return
        self.get_logger().info(f"{self.frames} frames, {self.recorder.n_complete} nozzles complete",
                               throttle_duration_sec=5.0)

    def exit_status(self) -> int:
        """0 once the file is written, else 1. A stop (SIGINT, SIGTERM) before it was writes the nozzles that
        are complete, as ``timeout_s`` does."""
        if not self.done:
            try:
                self._finish(f"stopped after {time.monotonic() - self._t0:.1f} s")
            except Exception as exc:  # noqa: BLE001 - said here: spin_node may ask before it could raise it
                self._say("error", f"could not write the baselines: {type(exc).__name__}: {exc}")
        return 0 if self.written else 1

    def _say(self, level: str, text: str) -> None:  # after a signal the context is down: no rosout, plain stderr
        if not self.context.ok():
            print(f"record_baseline: {text}", file=sys.stderr, flush=True)
        elif level == "info":  # one call site per severity: rclpy refuses a call site whose severity changes
            self.get_logger().info(text)
        elif level == "warning":
            self.get_logger().warning(text)
        else:
            self.get_logger().error(text)

    def _finish(self, early: str | None = None) -> None:
        """Write the complete nozzles' baselines; ``early``: why before ``n_nozzles`` were (timed out, stopped)."""
        self.done = True
        baselines = self.recorder.baselines()
        if early:
            want = self.config["n_nozzles"]
            self._say("warning", f"{early} with {self.frames} frames: {len(baselines)} nozzles complete"
                      + (f" of {want}" if want else ""))
        if len(baselines) == 0:
            self._say("error", "no nozzle has enough valid frames: nothing written")
            return
        path = Path(self.config["output_path"])
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            self.written = baselines.save(path)
        except OSError as exc:
            self._say("error", f"could not write {path}: {exc}")
            return
        ids = baselines.nozzle_ids
        self._say("info", f"wrote the baselines of {len(baselines)} nozzles ({ids[0]}..{ids[-1]}) to {path}")
        if why := self.recorder.unlike_note():  # faulty at commissioning: labelled without a baseline
            self._say("warning", why)
        if why := baselines.gain_mismatch(self.profile):  # the head rings unlike its profile: the model will see it
            self._say("warning", why)


def main(args=None) -> int:
    """Exit status 0 once the file is written, 1 if nothing could be, 2 for bad parameters."""
    return spin_node(BaselineRecorderNode, args, until=lambda node: node.done,
                     exit_code=BaselineRecorderNode.exit_status, prog="record_baseline")


if __name__ == "__main__":
    exit_now(main())  # the nodes down: not the interpreter's teardown too
