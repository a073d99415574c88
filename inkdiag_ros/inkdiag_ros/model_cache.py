"""The default FDI model on disk: verify it, or train and save it (with a progress bar).

Training is the core's job (``inkdiag_core.fdi.train_default_model`` when it
exists); until then :func:`_train_fallback` builds the same kind of model from
core pieces: ``simulate`` -> ``make_fdi_pipeline("rf", "kpi_y")`` -> ``save_model``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from inkdiag_core import FaultClass, ModelFileError, load_model, make_fdi_pipeline, save_model, simulate

DEFAULT_MODEL = Path("models") / "fdi_default.joblib"


def _train_fallback(path, *, n_per_class=400, seed=0, n_estimators=100, progress=True):
    try:
        from tqdm import tqdm
    except ImportError:  # pragma: no cover - tqdm is in requirements/dev.txt
        tqdm = None
    steps = ["simulate training set", "fit RF on KPI_Y", "score held-out set", "save with manifest"]
    bar = tqdm(total=len(steps), desc="training default FDI model", unit="step",
               disable=not progress) if tqdm else None

    def step(i):
        if bar is not None:
            bar.set_postfix_str(steps[i])

    step(0)
    counts = {c: n_per_class for c in FaultClass}
    train = simulate(counts, seed=seed)
    test = simulate({c: max(n_per_class // 4, 10) for c in FaultClass}, seed=seed + 1)
    bar and bar.update()
    step(1)
    pipe = make_fdi_pipeline("rf", "kpi_y", n_estimators=n_estimators, random_state=seed)
    pipe.fit(train.traces, train.label_values())
    bar and bar.update()
    step(2)
    acc = float(np.mean(pipe.predict(test.traces) == test.label_values()))
    bar and bar.update()
    step(3)
    config = {"name": "fdi-rf-kpi_y", "kind": "rf", "features": "kpi_y", "n_per_class": n_per_class,
              "n_estimators": n_estimators, "seed": seed, "n_samples": 512, "sample_rate_hz": 10e6}
    mpath = save_model(pipe, path, config=config, scores={"accuracy_12_class_held_out": acc})
    bar and bar.update()
    bar and bar.close()
    return mpath


def train_default_model(path, *, n_per_class=400, seed=0, progress=True):
    """Train and save the default model at ``path``; return the manifest path."""
    try:
        from inkdiag_core.fdi import train_default_model as core_train
    except ImportError:
        return _train_fallback(path, n_per_class=n_per_class, seed=seed, progress=progress)
    return core_train(path, n_per_class=n_per_class, seed=seed, progress=progress)


def ensure_default_model(path=DEFAULT_MODEL, *, progress=True, log=print):
    """Return ``path`` after making sure it holds a model that verifies; train one if not."""
    path = Path(path)
    if path.exists():
        try:
            load_model(path)
            return path
        except ModelFileError as exc:
            log(f"inkdiag: cached model unusable ({exc}); retraining")
    else:
        log(f"inkdiag: no FDI model at {path}; training the default one (once)")
    train_default_model(path, progress=progress)
    return path
