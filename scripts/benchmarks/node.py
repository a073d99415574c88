"""CPU per message of the fdi node's own work, without DDS: this tree against an older commit, same run.

    scripts/bench node [--ref HEAD] [--rounds 3] [--nozzles 2656] [--chunk 200] [--case realistic|worst]

What the fdi node does with each 200-nozzle trace message once rclpy has taken it (serialized, as
its raw subscription takes it): ``decode_traces_serialized`` -> ``FrameLabeller.label`` (screening, the healthy gate, the detector on
what the gate did not clear) -> ``LabelsReport.from_arrays`` -> the labels and drying messages'
bytes (``serialize_labels``, ``serialize_drying``; a tree without them: its messages through
``serialize_message``); timed per message with the frames labelled one message per call and in
batches of 8 messages per call (what the labelling pipeline hands the labeller under load:
``scripts/bench graph`` reports 8-9 frames per classifier pass). The head is
:func:`graph.realistic_head` (2,656 nozzles, 2 % faulty, every nozzle's baseline and
reference recorded; ``--case worst``: every nozzle faulty) with the default model.

Each tree runs in a child process of its own (``REF``'s ``inkdiag_core`` and ``msg_defs``
extracted with ``git archive`` and put first on ``PYTHONPATH``), on the same frames and
baselines (written once by this tree), one BLAS thread; the children alternate for
``--rounds`` rounds (which goes first alternating too: a round's first child ran slower) and each
reports its process CPU time per message, best of 5 passes.
Prints ms per message for each tree, the ratio, and whether the two trees' labels and drying
messages are byte-identical. Then some of its stages alone, best of 50 passes over every message, as
us per message: ``decode`` (the serialized message to a ``TraceFrame``), ``screen`` (the labeller's
first stage, ``FrameLabeller.screen``: screening, the healthy gate, the rows left gathered; one and 8
messages per call) and ``answers`` (a labelled frame to its labels and drying messages' bytes).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
BATCHES = (1, 8)


def child(data: Path, model: str, n_nozzles: int, chunk: int, passes: int = 5) -> dict:
    """This interpreter's package versions: CPU s per message for each batch size, and a digest of the output."""
    from inkdiag_core import load_labeller
    from rclpy.serialization import serialize_message

    from msg_defs import (DryingNozzles, LabelsReport, decode_traces_serialized, encode_drying, encode_labels,
                          encode_traces)

    try:  # what the fdi node of each tree publishes: the two answers' CDR bytes
        from msg_defs import serialize_drying, serialize_labels
    except ImportError:  # a tree before them: its messages' bytes, as rclpy serializes them
        def serialize_labels(report):
            return serialize_message(encode_labels(report))

        def serialize_drying(drying):
            return serialize_message(encode_drying(drying))

    frames = np.load(data / "frames.npy")
    labeller, err = load_labeller(model, data / "baselines.npz", max_abs_v=10.0, sample_rate_hz=10e6, n_samples=512)
    if err is not None:
        raise SystemExit(f"baselines not used: {err}")
    msgs = [serialize_message(encode_traces(x[i:i + chunk], first_nozzle=i, frame_id=k, stamp=0.0))
            for k, x in enumerate(frames) for i in range(0, n_nozzles, chunk)]

    def decode(m):
        return decode_traces_serialized(m, max_nozzle_id=n_nozzles - 1, n_samples=512, sample_rate_hz=10e6)

    def answers(f, r):
        codes = {k: getattr(r, k) for k in ("class_codes", "class_names") if hasattr(r, k)}  # a tree before them: none
        report = LabelsReport.from_arrays(
            frame_id=f.frame_id, stamp=f.stamp, first_nozzle=f.first_nozzle, classes=r.classes,
            confidence=r.confidence, valid=r.valid, reasons=r.reasons, model_id="bench",
            gate_cleared=r.gate_cleared, **codes)
        return serialize_labels(report), serialize_drying(DryingNozzles.from_labels(report))

    def run(batch: int) -> list:
        out = []
        for j in range(0, len(msgs), batch):
            decoded = [decode(m) for m in msgs[j:j + batch]]
            results = labeller.label([f.traces for f in decoded], [f.first_nozzle for f in decoded])
            out += [answers(f, r) for f, r in zip(decoded, results)]
        return out

    digest = hashlib.sha256()
    for labels, drying in run(1):
        digest.update(labels)
        digest.update(drying)
    def best_per_msg(work, n_passes):  # CPU s per message, best of n_passes after one to warm
        work()
        best = np.inf
        for _ in range(n_passes):
            t = time.process_time()
            work()
            best = min(best, (time.process_time() - t) / len(msgs))
        return best

    per_msg = {str(batch): best_per_msg(lambda: run(batch), passes) for batch in BATCHES}
    decoded = [decode(m) for m in msgs]
    labelled = list(zip(decoded, labeller.label([f.traces for f in decoded], [f.first_nozzle for f in decoded])))
    per_msg["decode"] = best_per_msg(lambda: [decode(m) for m in msgs], 10 * passes)  # short passes: the best of more
    for batch in BATCHES:  # the first stage alone (screening, the gate, the rows left gathered)
        per_msg[f"screen {batch}"] = best_per_msg(lambda: [
            labeller.screen([f.traces for f in decoded[j:j + batch]], [f.first_nozzle for f in decoded[j:j + batch]])
            for j in range(0, len(decoded), batch)], 10 * passes)
    per_msg["answers"] = best_per_msg(lambda: [answers(f, r) for f, r in labelled], 10 * passes)
    return {"per_msg_s": per_msg, "digest": digest.hexdigest(), "messages": len(msgs)}


def extract(ref: str, tmp: Path, packages=("inkdiag_core", "msg_defs")) -> Path:
    """The ``packages`` of commit ``ref`` under ``tmp`` (``tmp / name / name``): put ``tmp / name`` on PYTHONPATH."""
    tmp.mkdir(parents=True, exist_ok=True)
    tar = tmp / "ref.tar"
    with open(tar, "wb") as fh:
        subprocess.run(["git", "-C", str(ROOT), "archive", ref, *(f"{p}/{p}" for p in packages)],
                       stdout=fh, check=True)
    with tarfile.open(tar) as tf:
        tf.extractall(tmp, filter="data")
    return tmp


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ref", default="HEAD", help="the older commit to compare with (default: HEAD, so a change in "
                    "the work tree is measured against the last commit; the commit must read this tree's baselines "
                    "file, format 5 since 9bd8aec)")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--nozzles", type=int, default=2656)
    ap.add_argument("--chunk", type=int, default=200)
    ap.add_argument("--frames", type=int, default=4)
    ap.add_argument("--case", choices=["realistic", "worst"], default="realistic")
    ap.add_argument("--model", default=str(ROOT / "models" / "fdi_default.joblib"))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--role", choices=["bench", "child"], default="bench", help=argparse.SUPPRESS)
    ap.add_argument("--data", help=argparse.SUPPRESS)
    ns = ap.parse_args()
    if ns.role == "child":
        print(json.dumps(child(Path(ns.data), ns.model, ns.nozzles, ns.chunk)))
        return 0

    sys.path.insert(0, str(Path(__file__).parent))
    from graph import CASES, realistic_head

    from inkdiag_core.model_cache import ensure_default_model

    model = ensure_default_model(ns.model)
    with tempfile.TemporaryDirectory(prefix="bench_node_") as tmp:
        tmp = Path(tmp)
        frames, baselines, n_faulty = realistic_head(ns.nozzles, ns.frames, ns.seed, faulty=CASES[ns.case])
        np.save(tmp / "frames.npy", np.stack(frames))
        baselines.save(tmp / "baselines.npz")
        trees = {"this tree": None, ns.ref: extract(ns.ref, tmp / "ref")}
        env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
        cmd = [sys.executable, __file__, "--role", "child", "--data", str(tmp), "--model", model,
               "--nozzles", str(ns.nozzles), "--chunk", str(ns.chunk)]
        runs = {k: [] for k in trees}
        for r in range(ns.rounds):  # in turn, both trees on the same machine; which goes first alternates (the
            for name, path in list(trees.items())[::1 if r % 2 == 0 else -1]:  # first child of a round ran slower)
                e = dict(env)
                if path is not None:
                    e["PYTHONPATH"] = os.pathsep.join([str(path / "inkdiag_core"), str(path / "msg_defs"),
                                                       env.get("PYTHONPATH", "")])
                out = subprocess.run(cmd, env=e, cwd=ROOT, capture_output=True, text=True)
                if out.returncode:
                    print(out.stderr, file=sys.stderr)
                    return 1
                runs[name].append(json.loads(out.stdout.strip().splitlines()[-1]))
    n_msgs = runs["this tree"][0]["messages"]
    print(f"fdi node work per message without DDS: {ns.frames} frames of {ns.nozzles} nozzles ({ns.case}: "
          f"{n_faulty} faulty, baselines and references of every nozzle), {n_msgs} messages of {ns.chunk} nozzles; "
          f"process CPU ms per message, best of 5 passes per child, {ns.rounds} rounds (min-max over rounds)")
    for batch in BATCHES:
        cells = {}
        for name, rs in runs.items():
            v = np.array([r["per_msg_s"][str(batch)] for r in rs]) * 1e3
            cells[name] = v
        new, old = cells["this tree"], cells[ns.ref]
        ratio = old / new
        print(f"  {batch} message(s) per labeller call: this tree {new.min():.3f}-{new.max():.3f} ms, "
              f"{ns.ref} {old.min():.3f}-{old.max():.3f} ms; {ns.ref} / this tree {ratio.min():.2f}-{ratio.max():.2f}x")
    stages = {"decode": "decode", **{f"screen {b}": f"screen, {b} message(s) per call" for b in BATCHES},
              "answers": "answers"}
    for stage, label in stages.items():
        new, old = (np.array([r["per_msg_s"][stage] for r in runs[k]]) * 1e6 for k in ("this tree", ns.ref))
        ratio = old / new
        print(f"  {label}: this tree {new.min():.1f}-{new.max():.1f} us, {ns.ref} {old.min():.1f}-{old.max():.1f} us per "
              f"message; {ns.ref} / this tree {ratio.min():.2f}-{ratio.max():.2f}x (median {np.median(ratio):.2f}x)")
    same = len({r["digest"] for rs in runs.values() for r in rs}) == 1
    print(f"  labels and drying messages: {'byte-identical' if same else 'DIFFER'} between the trees")
    return 0


if __name__ == "__main__":
    sys.exit(main())
