"""The default FDI model on disk: verify it, or train and save it (with a progress bar if tqdm is installed).

Training is :func:`inkdiag_core.fdi.train_default_model`; this module decides
when (a missing or unverifiable file, or a default trained with other settings
than :func:`default_config`) and shows progress.
The default, ``models/fdi_default.joblib``, is one :class:`inkdiag_core.FaultDetector`
with both branches (KPI_Y for every nozzle, and KPI_Y + the nozzle's recorded
healthy baseline) and its thresholds inside (:func:`inkdiag_core.load_detector`
reads it; the fdi node takes it as ``model_path``, and its ``baseline_path``
alone turns the baseline branch on).

    python -m inkdiag_core.model_cache [models/fdi_default.joblib]

(``python -m inkdiag_ros.model_cache`` is the same command.)
"""

from __future__ import annotations

import argparse
import inspect
import sys
from pathlib import Path

from .fdi import train_default_model as _core_train
from .detector import FaultDetector
from .persistence import ModelFileError, check_manifest_entries, load_model
from .openset import OPENSET_FEATURES_VERSION, OPENSET_SCORES_VERSION

__all__ = ["DEFAULT_FEATURES", "DEFAULT_MODEL", "DEFAULT_SETTINGS", "default_config", "ensure_default_model",
           "main", "train_default_model"]

DEFAULT_MODEL = Path("models") / "fdi_default.joblib"
#: Feature set of each default file name.
DEFAULT_FEATURES = {DEFAULT_MODEL.name: "kpi_y"}
#: Training settings that define the default model; a cached file trained otherwise is stale.
DEFAULT_SETTINGS = ("kind", "features", "n_per_class", "seed", "n_estimators", "min_samples_leaf", "max_features",
                    "fnr_target", "baseline", "unknown_rate")
#: What a file whose manifest predates a setting was trained with.
_SETTINGS_BEFORE = {"max_features": "sqrt"}


def default_config(name: str = DEFAULT_MODEL.name) -> dict:
    """The training settings of the default model file ``name`` (:data:`DEFAULT_FEATURES`).

    ``fdi_default.joblib`` is a detector with its baseline branch (``baseline=True``).
    """
    params = inspect.signature(_core_train).parameters
    cfg = {k: params[k].default for k in DEFAULT_SETTINGS}
    cfg["features"] = DEFAULT_FEATURES.get(name, cfg["features"])
    if cfg["features"] == "kpi_y+baseline":
        del cfg["baseline"]
        del cfg["unknown_rate"]  # a plain pipeline file: no open-set layer
    else:
        cfg["baseline"] = name == DEFAULT_MODEL.name
    return cfg


def train_default_model(path, *, progress=True, **kwargs):
    """Train and save the default model at ``path``; return the manifest path.

    ``progress``: show a tqdm progress bar (if tqdm is not installed, train without
    one). ``kwargs`` go to :func:`inkdiag_core.fdi.train_default_model`.
    """
    if not progress:
        return _core_train(path, **kwargs)
    try:
        from tqdm import tqdm
    except ImportError:  # optional: train without a bar
        return _core_train(path, **kwargs)

    what = kwargs.get("features", "kpi_y") + (" + baseline branch" if kwargs.get("baseline") else "")
    with tqdm(total=4, desc=f"training the default FDI model ({what})",
              unit="step") as bar:
        def report(step, total, message):
            bar.set_postfix_str(message)
            bar.update(step - bar.n)

        return _core_train(path, progress=report, **kwargs)


def ensure_default_model(path=DEFAULT_MODEL, *, progress=True, log=print):
    """Return ``path`` after making sure it holds a model that verifies; train one if not.

    A file named like the default (:data:`DEFAULT_FEATURES`: ``fdi_default.joblib``) is trained with that default's settings, and
    one that verifies but was trained with other settings than the current
    defaults (:func:`default_config`, e.g. after an upgrade changed them) is
    retrained too, as is one that does not verify; any other model file is the user's own
    and is only verified: one that does not verify raises :class:`ModelFileError`, never
    trained over (a missing one gets the KPI_Y default).
    """
    path = Path(path)
    want = default_config(path.name)
    if path.exists():
        try:
            obj, manifest = load_model(path, as_pipeline=False)
            if isinstance(obj, FaultDetector):  # its manifest's entries as load_detector checks them (the fdi node)
                check_manifest_entries(path, manifest, obj)
            cfg = manifest.get("config", {})
            had = {k: cfg.get(k, _SETTINGS_BEFORE.get(k)) for k in want}
            stale = {k: (had[k], v) for k, v in want.items() if path.name in DEFAULT_FEATURES and had[k] != v}
            layers = [getattr(obj, a, None) for a in ("openset_", "baseline_openset_")]
            versions = {getattr(x, "features_version_", 1) for x in layers if x is not None}
            if versions - {OPENSET_FEATURES_VERSION}:
                if path.name not in DEFAULT_FEATURES:  # it cannot label today's features: say so, never train over it
                    raise ModelFileError(obj.openset_outdated() or f"{path}: open-set features version "
                                         f"{min(versions)}, now {OPENSET_FEATURES_VERSION}: retrain it (inkdiag train)")
                stale["open-set features version"] = (min(versions), OPENSET_FEATURES_VERSION)
            scoring = {getattr(x, "scores_version_", 1) for x in layers if x is not None}
            if scoring - {OPENSET_SCORES_VERSION} and path.name in DEFAULT_FEATURES:  # labels as it was calibrated
                stale["open-set scores version"] = (min(scoring), OPENSET_SCORES_VERSION)  # (a user's: as it is)
            if not stale:
                return path
            log(f"inkdiag: cached model trained with other settings than the default "
                f"({', '.join(f'{k}={a!r}, now {b!r}' for k, (a, b) in stale.items())}); retraining")
        except ModelFileError as exc:
            if path.name not in DEFAULT_FEATURES:  # a model of the user's own: never trained over
                raise ModelFileError(f"{exc} (a model of your own is not retrained here: train it again, "
                                     "e.g. with inkdiag train)") from None
            log(f"inkdiag: cached model unusable ({exc}); retraining")
    else:
        log(f"inkdiag: no FDI model at {path}; training the default one (once, a few seconds)")
    path.parent.mkdir(parents=True, exist_ok=True)
    train_default_model(path, progress=progress, features=want["features"], baseline=want.get("baseline", False))
    return path


def main(argv=None, *, prog: str = "python -m inkdiag_core.model_cache") -> int:
    """Verify or train each model file in ``argv`` (default: :data:`DEFAULT_MODEL`); exit status 0."""
    ap = argparse.ArgumentParser(prog=prog, description=__doc__.splitlines()[0])
    ap.add_argument("paths", nargs="*", default=[str(DEFAULT_MODEL)],
                    help="model files to verify or train (default: the default model)")
    for p in ap.parse_args(argv).paths:
        try:
            print(f"{ensure_default_model(p)}: verified")
        except ModelFileError as exc:
            print(f"{prog}: error: {exc}", file=sys.stderr)
            return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
