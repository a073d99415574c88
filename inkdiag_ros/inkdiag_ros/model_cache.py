"""The default FDI model on disk: verify it, or train and save it with a progress bar.

Training is the core's :func:`inkdiag_core.fdi.train_default_model`; this
module only decides when (missing or unverifiable file) and shows progress.
"""

from __future__ import annotations

from pathlib import Path

from inkdiag_core import ModelFileError, load_model
from inkdiag_core.fdi import train_default_model as _core_train

DEFAULT_MODEL = Path("models") / "fdi_default.joblib"


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
    """Return ``path`` after making sure it holds a model that verifies; train one if not."""
    path = Path(path)
    if path.exists():
        try:
            load_model(path)
            return path
        except ModelFileError as exc:
            log(f"inkdiag: cached model unusable ({exc}); retraining")
    else:
        log(f"inkdiag: no FDI model at {path}; training the default one (once, a few seconds)")
    train_default_model(path, progress=progress)
    return path
