"""Record tests/core/data/fm_reference_vp.json: every output of the vp-based cases of test_estimation_split, as float hex.

    python tests/core/data/record_fm_reference_vp.py   (after `source scripts/_bootstrap.sh`)
"""
import json
import sys
from pathlib import Path
import numpy as np
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import test_estimation_split as t
from inkdiag_core import InkChannelModel, estimate_fm_batch, estimate_fm
from inkdiag_core.fe_datasets import synthetic_set
model = InkChannelModel()
ds = synthetic_set(model, kind="ct", x0="random", n_levels=5, snr_db=40, n_samples=200, seed=3)
Y, X0 = ds.y, ds.x0
FIELDS = ("fm", "std", "trace", "ci", "d_mu", "viscosity", "x0", "offset")
def hexes(a):
    a = np.asarray(a, dtype=np.float64)
    return {"shape": list(a.shape), "hex": [float(v).hex() for v in a.ravel()]}
out = {}
for name, (method, use_x0, kw, opts) in t.CASES.items():
    r = estimate_fm_batch(Y, model, t.FS, method=method, x0=X0 if use_x0 else None,
                          **(dict(kw, baseline_fm=t.BASELINE[name]) if name in t.BASELINE else kw))
    if r.method not in ("vp", "vp_cal"):
        continue
    out[name] = {"method": r.method, **{f: hexes(getattr(r, f)) for f in FIELDS}}
r = estimate_fm(Y[2], model, t.FS, method="vp_cal")
out["single_vp_cal"] = {"method": r.method, **{f: hexes(getattr(r, f)) for f in ("fm", "std", "trace", "x0")}}
Path(__file__).with_name("fm_reference_vp.json").write_text(json.dumps(out, indent=0))
print(list(out), {k: {f: v[f]["shape"] for f in v if f != "method"} for k, v in list(out.items())[:1]})
