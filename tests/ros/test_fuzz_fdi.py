"""A standing fuzz test of the fdi node: hostile and odd frames through real rclpy and Fast DDS.

10,000 frames of 46 named kinds (a fixed seed) go to one fdi node. Every frame must be
accounted for in the counters the node publishes on ``/diagnostics``
(received = labelled + malformed + failed + dropped, each as many as sent of its kind),
and every well-formed frame labelled with each of its good rows valid and classified, its
bad rows invalid with their reason. A failure names the kind.
"""

from __future__ import annotations

import array
import collections
import time

import numpy as np
from rclpy.parameter import Parameter
from std_msgs.msg import Float32MultiArray, MultiArrayDimension

from inkdiag_core import FaultClass, simulate
from msg_defs import (
    DIAGNOSTICS_MSG_TYPE,
    DIAGNOSTICS_QOS,
    LABELS_MSG_TYPE,
    RELIABLE_QOS,
    TRACE_MSG_TYPE,
    TRACES_QOS,
    decode_labels,
    diagnostics_values,
    encode_traces,
    topics,
)

N_FRAMES = 10_000
N_NOZZLES = 64  # the node's head
MAX_ABS_V = 10.0
F32_MAX = float(np.finfo(np.float32).max)


def _pool():
    r = simulate({c: 6 for c in FaultClass}, seed=3)
    return r.traces.astype(np.float32)


def _set(msg, **idx_values):
    """``msg`` with header/data values replaced: ``_set(msg, d2=2**24)`` sets data[2]."""
    data = np.frombuffer(msg.data, dtype=np.float32).copy()
    for k, v in idx_values.items():
        data[int(k[1:])] = v
    a = array.array("f")
    a.frombytes(data.tobytes())
    msg.data = a
    return msg


def _layout(msg, dims=None, offset=None, data=None):
    if dims is not None:
        msg.layout.dim = [MultiArrayDimension(label=l, size=s, stride=st) for l, s, st in dims]
    if offset is not None:
        msg.layout.data_offset = offset
    if data is not None:
        a = array.array("f")
        a.frombytes(np.asarray(data, np.float32).tobytes())
        msg.data = a
    return msg


class Fuzzer:
    """Builds frames of named kinds; records what the node must make of each."""

    def __init__(self, seed=0):
        self.rng = np.random.default_rng(seed)
        self.pool = _pool()
        self.next_id = 0
        self.last = None  # (msg, expect) of the last well-formed frame (for duplicates)

    def rows(self, n):
        return self.pool[self.rng.integers(0, len(self.pool), n)].copy()

    def good(self, n=None, first=None, frame_id=None, stamp=None, x=None):
        n = int(self.rng.integers(1, 5)) if n is None and x is None else (x.shape[0] if x is not None else n)
        x = self.rows(n) if x is None else x
        first = int(self.rng.integers(0, N_NOZZLES - n + 1)) if first is None else first
        fid = self.next_id if frame_id is None else frame_id
        self.next_id += 1
        stamp = 1.7e9 + fid * 1e-3 if stamp is None else stamp
        return encode_traces(x, first_nozzle=first, frame_id=fid, stamp=stamp), x, first, fid

    def labelled(self, x, first, fid, msg, bad=None):
        expect = {"frame_id": fid, "first": first, "n": x.shape[0], "bad": dict(bad or {})}
        self.last = (msg, expect)
        return msg, expect

    def with_bad_rows(self, make_bad, reason, n_bad=1):
        msg, x, first, fid = self.good(n=int(self.rng.integers(n_bad, 5)))
        rows = self.rng.choice(x.shape[0], n_bad, replace=False)
        for i in rows:
            x[i] = make_bad(x[i])
        msg = encode_traces(x, first_nozzle=first, frame_id=fid, stamp=1.7e9)
        return self.labelled(x, first, fid, msg, {first + int(i): reason for i in rows})

    def malformed(self, msg):
        return msg, None

    # ---- the kinds -------------------------------------------------------------------------
    def kinds(self):
        r = self.rng
        spike = lambda v: (lambda row: _put(row, int(r.integers(0, row.size)), v))  # noqa: E731
        k = {
            "good": lambda: self.labelled(*self._parts(self.good())),
            "good_one_row": lambda: self.labelled(*self._parts(self.good(n=1))),
            "good_last_nozzles": lambda: self.labelled(*self._parts(self.good(n=4, first=N_NOZZLES - 4))),
            "good_big_in_range": lambda: self._scaled(3.0),
            "good_max_frame_id": lambda: self.labelled(*self._parts(self.good(frame_id=2**48 - 1))),
            "good_max_stamp": self._max_stamp,
            "duplicate_frame_id": self._duplicate,
            "nan_sample": lambda: self.with_bad_rows(spike(np.nan), "non_finite"),
            "inf_sample": lambda: self.with_bad_rows(spike(np.inf), "non_finite"),
            "neg_inf_sample": lambda: self.with_bad_rows(spike(-np.inf), "non_finite"),
            "all_nan_row": lambda: self.with_bad_rows(lambda row: np.full_like(row, np.nan), "non_finite"),
            "spike_1e30": lambda: self.with_bad_rows(spike(1e30), "out_of_range"),
            "spike_f32_max": lambda: self.with_bad_rows(spike(F32_MAX), "out_of_range"),
            "spike_neg_1e20": lambda: self.with_bad_rows(spike(-1e20), "out_of_range"),
            "spike_just_beyond": lambda: self.with_bad_rows(spike(MAX_ABS_V * 1.01), "out_of_range"),
            "alternating_extremes": lambda: self.with_bad_rows(_alternating, "out_of_range"),
            "flat_row": lambda: self.with_bad_rows(lambda row: np.full_like(row, 0.3), "flat"),
            "zero_row": lambda: self.with_bad_rows(np.zeros_like, "flat"),
            "tiny_row": lambda: self.with_bad_rows(lambda row: row * 1e-9, "flat"),
            "clipped_row": lambda: self.with_bad_rows(_clipped, "clipped"),
            "two_bad_rows": lambda: self.with_bad_rows(spike(np.nan), "non_finite", n_bad=2),
            "every_row_bad": self._all_bad,
            # malformed: the frame is refused whole and counted
            "empty_layout": lambda: self.malformed(Float32MultiArray()),
            "one_dim": lambda: self.malformed(_layout(self.good()[0], dims=[("nozzle", 2, 1024)])),
            "three_dims": lambda: self.malformed(_layout(
                self.good(n=1)[0], dims=[("nozzle", 1, 512), ("sample", 512, 512), ("x", 1, 1)])),
            "swapped_labels": lambda: self.malformed(_layout(
                self.good(n=2)[0], dims=[("sample", 2, 1024), ("nozzle", 512, 512)])),
            "wrong_stride": lambda: self.malformed(_layout(
                self.good(n=2)[0], dims=[("nozzle", 2, 1000), ("sample", 512, 512)])),
            "wrong_offset": lambda: self.malformed(_layout(self.good()[0], offset=0)),
            "short_data": lambda: self.malformed(_truncate(self.good()[0], -1)),
            "long_data": lambda: self.malformed(_truncate(self.good()[0], +3)),
            "zero_nozzles": lambda: self.malformed(_layout(
                self.good(n=1)[0], dims=[("nozzle", 0, 0), ("sample", 512, 512)], data=np.zeros(8))),
            "zero_samples": lambda: self.malformed(_layout(
                self.good(n=1)[0], dims=[("nozzle", 1, 0), ("sample", 0, 0)], data=np.zeros(8))),
            "wrong_schema": lambda: self.malformed(_set(self.good()[0], d0=2)),
            "zero_sample_rate": lambda: self.malformed(_set(self.good()[0], d4=0)),
            "inf_sample_rate": lambda: self.malformed(_set(self.good()[0], d4=np.inf)),
            "wrong_sample_rate": lambda: self.malformed(_set(self.good()[0], d4=5e6)),
            "wrong_length": lambda: self.malformed(encode_traces(self.rows(2)[:, :256], frame_id=1)),
            "nozzles_beyond_head": lambda: self.malformed(self.good(n=4, first=N_NOZZLES - 2)[0]),
            "huge_nozzle_id": lambda: self.malformed(_set(self.good()[0], d1=1e30)),
            "negative_nozzle": lambda: self.malformed(_set(self.good()[0], d1=-3)),
            "nan_header": lambda: self.malformed(_set(self.good()[0], d2=np.nan)),
            "fractional_frame_id": lambda: self.malformed(_set(self.good()[0], d2=1.5)),
            "frame_lo_2_24": lambda: self.malformed(_set(self.good()[0], d2=2**24)),
            "frame_hi_f32_max": lambda: self.malformed(_set(self.good()[0], d3=F32_MAX)),
            "stamp_s_lo_2_24": lambda: self.malformed(_set(self.good()[0], d5=2**24)),
            "stamp_s_hi_huge": lambda: self.malformed(_set(self.good()[0], d6=1e30)),
            "stamp_us_1e6": lambda: self.malformed(_set(self.good()[0], d7=1e6)),
        }
        return k

    def _parts(self, g):
        msg, x, first, fid = g
        return x, first, fid, msg

    def _scaled(self, factor):
        x = self.rows(int(self.rng.integers(1, 5)))
        x *= factor / max(float(np.abs(x).max()), 1e-3) * 2.0  # peak at 2*factor V, under the limit
        return self.labelled(*self._parts(self.good(x=x)))

    def _max_stamp(self):
        msg, x, first, fid = self.good()
        return self.labelled(x, first, fid, _set(msg, d5=2**24 - 1, d6=2**24 - 1, d7=999_999))

    def _duplicate(self):
        if self.last is None:
            return self.labelled(*self._parts(self.good()))
        return self.last

    def _all_bad(self):
        msg, x, first, fid = self.good()
        x[:] = np.nan
        msg = encode_traces(x, first_nozzle=first, frame_id=fid)
        return self.labelled(x, first, fid, msg, {first + i: "non_finite" for i in range(x.shape[0])})


def _put(row, i, v):
    row = row.copy()
    row[i] = v
    return row


def _alternating(row):
    out = np.empty_like(row)
    out[::2], out[1::2] = F32_MAX, -F32_MAX
    return out


def _clipped(row):
    row = row.copy()
    row[20:30] = row.max()  # sitting on the rail for 10 samples
    return row


def _truncate(msg, delta):
    data = np.frombuffer(msg.data, dtype=np.float32)
    data = data[:delta] if delta < 0 else np.concatenate([data, np.zeros(delta, np.float32)])
    return _layout(msg, data=data)


def test_fdi_node_accounts_for_every_hostile_frame(ros, fdi_model):
    from inkdiag_ros.fdi_node import FdiNode

    t_start = time.monotonic()
    params = {"model_path": str(fdi_model), "n_nozzles": N_NOZZLES, "diagnostics_period_s": 0.2,
              "max_queued_frames": 100_000, "max_abs_sample_v": MAX_ABS_V}
    fdi = ros.add(FdiNode(context=ros.context, namespace="/fz",
                          parameter_overrides=[Parameter(k, value=v) for k, v in params.items()]))
    probe = ros.node("probe", namespace="/fz")
    pub = probe.create_publisher(TRACE_MSG_TYPE, topics.TRACES, TRACES_QOS)
    labels = collections.defaultdict(list)
    n_labels = [0]

    def on_labels(m):
        rep = decode_labels(m)
        labels[rep.frame_id].append(rep)
        n_labels[0] += 1

    probe.create_subscription(LABELS_MSG_TYPE, topics.LABELS, on_labels, RELIABLE_QOS)
    diag = []

    def on_diag(m):
        d = diagnostics_values(m).get("inkdiag fdi: /fz")
        if d is not None:
            diag.append(d)

    probe.create_subscription(DIAGNOSTICS_MSG_TYPE, topics.DIAGNOSTICS, on_diag, DIAGNOSTICS_QOS)
    ros.spin_until(lambda: pub.get_subscription_count() > 0, 10, "fdi's subscription")

    fuzz = Fuzzer(seed=0)
    kinds = fuzz.kinds()
    names = sorted(kinds)
    assert len(names) >= 30
    sent = collections.Counter()
    expected = collections.defaultdict(list)  # frame_id -> [(kind, expect)]
    n_labelled = 0
    burst = 8
    for start in range(0, N_FRAMES, burst):
        for kind in fuzz.rng.choice(names, min(burst, N_FRAMES - start)):
            msg, expect = kinds[kind]()
            sent[kind] += 1
            if expect is not None:
                expected[expect["frame_id"]].append((kind, expect))
                n_labelled += 1
            pub.publish(msg)
        total = start + burst if start + burst < N_FRAMES else N_FRAMES
        ros.spin_until(lambda: fdi.stats.frames_received >= total, 5, f"frame {total} received (best effort)")
        # keep the labels within the reliable depth of 50
        st = fdi.stats
        ros.spin_until(lambda: n_labels[0] >= st.frames_labelled - 20 and
                       st.frames_labelled + st.frames_failed + st.frames_dropped >= n_labelled - 24,
                       10, "labelling to keep up")
    ros.spin_until(lambda: st.frames_labelled + st.frames_failed + st.frames_dropped >= n_labelled, 20,
                   "every well-formed frame done")
    ros.spin_until(lambda: n_labels[0] >= st.frames_labelled, 20, "the labels published")
    n_malformed = N_FRAMES - n_labelled
    # a /diagnostics message published after the last frame was labelled (an earlier one may still say
    # frames_received == N_FRAMES with the last few frames in the labelling queue)
    ros.spin_until(lambda: diag and diag[-1]["frames_received"] == str(N_FRAMES)
                   and diag[-1]["frames_labelled"] == str(st.frames_labelled), 5, "final diagnostics")
    d = diag[-1]
    counters = {k: int(d[k]) for k in ("frames_received", "frames_labelled", "frames_malformed",
                                       "frames_failed", "frames_dropped")}
    assert counters == {"frames_received": N_FRAMES, "frames_labelled": n_labelled,
                        "frames_malformed": n_malformed, "frames_failed": 0, "frames_dropped": 0}, \
        (counters, d["last_error"])
    assert (counters["frames_labelled"] + counters["frames_malformed"] + counters["frames_failed"]
            + counters["frames_dropped"]) == counters["frames_received"]
    # every well-formed frame labelled: its good rows valid with a class, its bad rows invalid (reason)
    for fid, wants in expected.items():
        got = labels[fid]
        assert len(got) == len(wants), (wants[0][0], fid, len(got), len(wants))
        for (kind, e), rep in zip(wants, got):
            assert (rep.first_nozzle, rep.n_nozzles) == (e["first"], e["n"]), kind
            assert dict(rep.invalid) == e["bad"], (kind, fid, rep.invalid, e["bad"])
            assert sum(rep.counts.values()) == e["n"], kind
            assert rep.counts.get("invalid", 0) == len(e["bad"]), kind
    bad_rows = sum(len(e["bad"]) for v in expected.values() for _, e in v)
    assert int(d["rows_invalid"]) == int(d["count.invalid"]) == bad_rows
    assert set(sent) == set(names), set(names) - set(sent)
    assert min(sent.values()) >= 100, sent
    elapsed = time.monotonic() - t_start
    print(f"fuzz: {N_FRAMES} frames of {len(names)} kinds in {elapsed:.1f} s; "
          f"{n_labelled} labelled, {n_malformed} malformed, {bad_rows} invalid rows")
