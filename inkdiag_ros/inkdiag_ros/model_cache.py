"""The default FDI model on disk: verify it, or train and save it with a progress bar.

Training is the core's :func:`inkdiag_core.fdi.train_default_model`; this
module only decides when (missing or unverifiable file) and shows progress.
"""

from __future__ import annotations

import inspect
from pathlib import Path

from inkdiag_core import ModelFileError, load_model
from inkdiag_core.fdi import train_default_model as _core_train

DEFAULT_MODEL = Path("models") / "fdi_default.joblib"
#: Training settings that define the default model; a cached file trained otherwise is stale.
DEFAULT_SETTINGS = ("kind", "features", "n_per_class", "seed", "n_estimators", "min_samples_leaf", "fnr_target")


def default_config() -> dict:
    """The training settings :func:`inkdiag_core.fdi.train_default_model` uses by default."""
    params = inspect.signature(_core_train).parameters
    return {k: params[k].default for k in DEFAULT_SETTINGS}


def train_default_model(path, *, progress=True, **kwargs):
    """Train and save the default model at ``path`` (tqdm progress bar); return the manifest path."""
    if not progress:
        return _core_train(path, **kwargs)
    from tqdm import tqdm

    with tqdm(total=4, desc="training the default FDI model", unit="step") as bar:
        def report(step, total, message):
            bar.set_postfix_str(message)
            bar.update(step - bar.n)

        return _core_train(path, progress=report, **kwargs)


def ensure_default_model(path=DEFAULT_MODEL, *, progress=True, log=print):
    """Return ``path`` after making sure it holds a model that verifies; train one if not.

    A file named like the default (``fdi_default.joblib``) that verifies but was
    trained with other settings than the current defaults (:func:`default_config`,
    e.g. after an upgrade changed the default feature set) is retrained too; any
    other model file is the user's own and is only verified.
    """
    path = Path(path)
    if path.exists():
        try:
            _, manifest = load_model(path)
            cfg = manifest.get("config", {})
            stale = {k: (cfg.get(k), v) for k, v in default_config().items()
                     if path.name == DEFAULT_MODEL.name and cfg.get(k) != v}
            if not stale:
                return path
            log(f"inkdiag: cached model trained with other settings than the default "
                f"({', '.join(f'{k}={a!r}, now {b!r}' for k, (a, b) in stale.items())}); retraining")
        except ModelFileError as exc:
            log(f"inkdiag: cached model unusable ({exc}); retraining")
    else:
        log(f"inkdiag: no FDI model at {path}; training the default one (once, a few seconds)")
    train_default_model(path, progress=progress)
    return path
