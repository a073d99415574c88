"""Model files: joblib plus a manifest that is verified before anything is unpickled.

``joblib.load`` unpickles, and unpickling can run arbitrary code; loading
across scikit-learn versions is unsupported. So every model file
``<name>.joblib`` has a manifest ``<name>.joblib.manifest.json`` beside it:

.. code-block:: json

    {"format": "inkdiag-model", "format_version": 1,
     "sha256": "...", "size_bytes": 123,
     "versions": {"python": "3.11.7", "numpy": "...", "scipy": "...",
                  "scikit-learn": "...", "joblib": "...", "inkdiag_core": "..."},
     "created_utc": "2026-11-22T08:00:00Z",
     "config": {...}, "scores": {...}}

:func:`load_model` refuses, with :class:`ModelFileError` (a ``ValueError``)
saying what is wrong, a missing file or manifest, a manifest that does not
parse, a file whose sha256 or size differs from the manifest (tampered or
truncated), or a file written with other numpy / scipy / scikit-learn /
joblib versions than the running ones. Only then does it unpickle.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import os
import platform
from pathlib import Path

import joblib
import numpy
import scipy
import sklearn

from ._fileio import refuse_to_replace, temp_beside
from ._version import __version__

__all__ = ["ModelFileError", "save_model", "load_model", "save_detector", "load_detector", "read_manifest",
           "verify_model_file",
           "library_versions", "manifest_path", "model_head_sha256", "check_manifest_entries"]

FORMAT = "inkdiag-model"
FORMAT_VERSION = 1
#: Libraries whose versions must match for a model to load.
PINNED_LIBRARIES = ("numpy", "scipy", "scikit-learn", "joblib")
#: ``config['estimator']`` of a :func:`save_detector` file.
DETECTOR_ESTIMATOR = "FaultDetector"


class ModelFileError(ValueError):
    """A model file that must not be loaded: missing, tampered, or from other library versions."""


def library_versions() -> dict:
    """Versions of the running interpreter and libraries, as written to manifests."""
    return {
        "python": platform.python_version(),
        "numpy": numpy.__version__,
        "scipy": scipy.__version__,
        "scikit-learn": sklearn.__version__,
        "joblib": joblib.__version__,
        "inkdiag_core": __version__,
    }


def manifest_path(path) -> Path:
    """The manifest file beside model file ``path``: ``<name>.joblib.manifest.json``."""
    path = Path(path)
    return path.with_name(path.name + ".manifest.json")


def _one_line(exc: BaseException) -> str:
    return " ".join(f"{type(exc).__name__}: {exc}".split())[:200]


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def save_model(model, path, *, config: dict | None = None, scores: dict | None = None) -> Path:
    """Write ``model`` with joblib and its manifest beside it; return the manifest path.

    Parameters
    ----------
    model : object
        Typically a fitted scikit-learn Pipeline.
    path : str or Path
        Destination ``.joblib`` file; its directory is created if needed.
    config, scores : dict, optional
        Training configuration and scores (JSON-serialisable), kept in the manifest.

    Both files are written to temporary names and renamed, so a crash never
    leaves a model without a matching manifest.
    """
    return _save(model, path, config=config, scores=scores)[0]


def _save(model, path, *, config, scores):
    """:func:`save_model`; returns the manifest path and the manifest written."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    manifest = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "file": path.name,
        "versions": library_versions(),
        "created_utc": _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "config": config or {},
        "scores": scores or {},
    }
    json.dumps(manifest)  # fail before writing anything if config/scores are not JSON
    refuse_to_replace(manifest_path(path))
    fd, tmp = temp_beside(path)
    os.close(fd)
    mtmp = None
    try:
        joblib.dump(model, tmp)
        manifest["sha256"] = _sha256(Path(tmp))
        manifest["size_bytes"] = os.path.getsize(tmp)
        mpath = manifest_path(path)
        mtmp = str(mpath) + ".tmp"
        with open(mtmp, "w") as f:
            json.dump(manifest, f, indent=2, sort_keys=True)
        os.replace(tmp, path)
        os.replace(mtmp, mpath)
    finally:  # stopped half-way (an error, a Ctrl-C): neither temporary file stays
        for left in (tmp, mtmp):
            if left is not None and os.path.exists(left):
                os.remove(left)
    return mpath, manifest


def _looks_like_a_profile(path: Path) -> bool:
    """Whether ``path`` starts like a head profile's YAML (its schema line), read without unpickling anything."""
    try:
        with open(path, "rb") as f:
            head = f.read(4096)
    except OSError:
        return False
    return b"inkdiag.head_profile" in head


def read_manifest(path) -> dict:
    """Read and check the manifest of ``path`` (the model file itself is not read)."""
    path = Path(path)
    mpath = manifest_path(path)
    if not path.is_file():
        raise ModelFileError(f"model file {path} " + ("is a directory, not a model file" if path.is_dir() else
                                                      "does not exist" if not path.exists() else "is not a regular file"))
    if not mpath.is_file():
        if path.name.endswith(".manifest.json"):  # helper-100's QA: it read as 'a head profile (YAML)'
            raise ModelFileError(f"model file {path} is a model's manifest, not the model: give the "
                                 f"{path.name.removesuffix('.manifest.json')} it describes")
        if _looks_like_a_profile(path):
            raise ModelFileError(f"model file {path} is a head profile (YAML), not a model: a model is the "
                                 "MODEL.joblib `inkdiag train` writes (with its manifest beside it)")
        raise ModelFileError(
            f"model file {path} has no manifest ({mpath} is missing): refusing to unpickle an unverified file"
        )
    try:
        manifest = json.loads(mpath.read_text())
    except (OSError, ValueError) as exc:
        raise ModelFileError(f"manifest {mpath} is not valid JSON: {exc}") from None
    except RecursionError:  # json's decoder recurses per level of nesting
        raise ModelFileError(f"manifest {mpath} is not valid JSON: nested too deeply") from None
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
        raise ModelFileError(f"manifest {mpath} is not an {FORMAT} manifest")
    if manifest.get("format_version") != FORMAT_VERSION:
        raise ModelFileError(
            f"manifest {mpath} has format_version {manifest.get('format_version')!r}, "
            f"expected {FORMAT_VERSION}"
        )
    for key in ("sha256", "size_bytes", "versions"):
        if key not in manifest:
            raise ModelFileError(f"manifest {mpath} lacks '{key}'")
    for key in ("versions", "config", "scores"):  # read as mappings by every loader
        if not isinstance(manifest.get(key, {}), dict):
            raise ModelFileError(f"manifest {mpath}: '{key}' must be an object, got "
                                 f"{type(manifest[key]).__name__}")
    return manifest


def verify_model_file(path, *, check_versions: bool = True) -> dict:
    """Check ``path`` against its manifest without unpickling it: :func:`read_manifest`, then the
    file's size and sha256 and, with ``check_versions``, the libraries it was written with. Its
    manifest (dict); :class:`ModelFileError` as :func:`load_model` raises it for these (a launcher
    checks a model file so before it starts the processes that load it)."""
    path = Path(path)
    manifest = read_manifest(path)
    size = path.stat().st_size
    if size != manifest["size_bytes"]:
        raise ModelFileError(
            f"model file {path} is {size} bytes, its manifest says {manifest['size_bytes']}: "
            "truncated or tampered, refusing to load"
        )
    digest = _sha256(path)
    if digest != manifest["sha256"]:
        raise ModelFileError(
            f"model file {path} has sha256 {digest[:16]}..., its manifest says "
            f"{str(manifest['sha256'])[:16]}...: tampered, refusing to load"
        )
    if check_versions:
        running = library_versions()
        wrong = {
            lib: (manifest["versions"].get(lib), running[lib])
            for lib in PINNED_LIBRARIES
            if manifest["versions"].get(lib) != running[lib]
        }
        if wrong:
            detail = ", ".join(f"{k} {v[0]} (file) vs {v[1]} (running)" for k, v in wrong.items())
            raise ModelFileError(
                f"model file {path} was written with other library versions: {detail}; "
                "retrain it (scripts/run does) instead of loading it"
            )
    return manifest


def load_model(path, *, check_versions: bool = True, as_pipeline: bool = True):
    """Verify ``path`` against its manifest, then unpickle it.

    Parameters
    ----------
    path : str or Path
        The ``.joblib`` file written by :func:`save_model` or :func:`save_detector`.
    check_versions : bool
        Refuse files written with other numpy/scipy/scikit-learn/joblib
        versions (default). Turn off only for files you trust and have checked.
    as_pipeline : bool
        A :class:`inkdiag_core.FaultDetector` file gives its plain branch's
        ``pipeline_`` (default: what this function's callers, the nodes and
        :func:`inkdiag_core.label_frames`, take until they load detectors; its
        threshold is the manifest's ``config['fd_threshold']``). False returns the
        object as unpickled; :func:`load_detector` returns the whole detector.

    Returns
    -------
    model : object
    manifest : dict

    Raises
    ------
    ModelFileError
        Missing file or manifest, bad manifest, size or sha256 mismatch,
        library version mismatch, a file that matches its manifest but does not unpickle (damaged,
        too large for the memory, or naming classes this version of inkdiag does not have).
    """
    path = Path(path)
    manifest = verify_model_file(path, check_versions=check_versions)
    try:
        model = joblib.load(path)
    except (ImportError, AttributeError) as exc:  # a class or module the pickle names is not in this inkdiag
        raise ModelFileError(f"model file {path} needs {_one_line(exc)}: written by another version of inkdiag, "
                             "or damaged; train it again") from exc
    except MemoryError as exc:  # a damaged length field asks for more than there is; or a model too large
        raise ModelFileError(f"model file {path} does not load (MemoryError): damaged, or too large for this "
                             "machine's memory") from exc
    except Exception as exc:  # noqa: BLE001 - bytes that match their manifest and still do not unpickle: any
        # of pickle's, numpy's or a decompressor's errors (joblib picks one from the first bytes)
        raise ModelFileError(f"model file {path} matches its manifest but does not load ({_one_line(exc)}): "
                             "damaged before its manifest was written, or both edited; train it again") from exc
    if as_pipeline and manifest.get("config", {}).get("estimator") == DETECTOR_ESTIMATOR:
        from .detector import FaultDetector

        if isinstance(model, FaultDetector):
            model = model.pipeline_
    return model, manifest


def save_detector(detector, path, *, config: dict | None = None) -> Path:
    """Write a fitted :class:`inkdiag_core.FaultDetector` and its manifest; return the manifest path.

    One ``.joblib`` file holds the whole detector (both branches and thresholds);
    the manifest beside it (the format of :func:`save_model`) has

    - ``config``: ``detector.get_params()``, then ``estimator`` (``"FaultDetector"``),
      ``baseline`` (bool: has the baseline branch), ``fd_threshold``,
      ``baseline_fd_threshold`` (float or null), ``sample_rate_hz`` (Hz) and
      ``n_samples`` (trace length) it was built for, ``classes`` (list of str),
      the head: ``profile`` (the :class:`inkdiag_core.HeadProfile` document, null for
      the default head), ``profile_sha256`` (its :attr:`~inkdiag_core.HeadProfile.sha256`;
      the default head's when null) and ``profile_name``, and ``config``'s entries
      (e.g. how the training data was made). A file from before profiles has no
      ``profile_sha256``: it is a model of the default head (:func:`model_head_sha256`);
    - ``scores``: ``scores_``, and ``baseline_scores_`` with each key prefixed ``baseline_``.

    ``config['fd_threshold']``, ``kind`` and ``features`` are where loaders of plain
    pipelines look, so :func:`load_model` + :func:`inkdiag_core.fdi.classify` still use
    such a file as its plain branch. Sets ``detector.file_sha256_`` (its
    :attr:`~inkdiag_core.FaultDetector.model_id`).

    Parameters
    ----------
    detector : fitted FaultDetector
    path : str or Path
        Destination ``.joblib`` file; its directory is created if needed.
    config : dict, optional
        More JSON-serialisable entries for the manifest's ``config``; they may not
        replace the detector's own.
    """
    from sklearn.utils.validation import check_is_fitted

    from .detector import FaultDetector

    if not isinstance(detector, FaultDetector):
        raise TypeError(f"save_detector takes a FaultDetector, got {type(detector).__name__}")
    check_is_fitted(detector)
    own, scores = _detector_entries(detector)
    clash = sorted(set(own) & set(config or {}))
    if clash:
        raise ValueError(f"config may not replace the detector's own entries {clash}")
    config = {**own, **(config or {})}
    try:
        json.dumps(config)
    except (TypeError, ValueError) as exc:  # e.g. a RandomState as random_state
        raise ValueError(f"the detector's parameters or config are not JSON-serialisable: {exc}") from None
    mpath, manifest = _save(detector, path, config=config, scores=scores)
    detector.file_sha256_ = manifest["sha256"]
    return mpath


def _detector_entries(detector) -> tuple:
    """The manifest's ``config`` entries and ``scores`` that a fitted detector itself determines."""
    params = {k: v.item() if isinstance(v, numpy.generic) else v for k, v in detector.get_params().items()}
    own = {**params, "estimator": DETECTOR_ESTIMATOR,
           "baseline": detector.baseline_pipeline_ is not None,
           "fd_threshold": float(detector.fd_threshold_),
           "baseline_fd_threshold": (None if detector.baseline_fd_threshold_ is None
                                     else float(detector.baseline_fd_threshold_)),
           "sample_rate_hz": float(detector.sample_rate_hz_), "n_samples": int(detector.n_features_in_),
           "classes": [str(c) for c in detector.classes_],
           # the head: its profile document (None: the default head) and its sha256
           "profile": None if detector.profile is None else detector.profile.to_dict(),
           "profile_sha256": detector.head_sha256, "profile_name": detector.head_name}
    scores = dict(detector.scores_)
    scores.update({f"baseline_{k}": v for k, v in (detector.baseline_scores_ or {}).items()})
    return own, scores


def check_manifest_entries(path, manifest: dict, detector) -> None:
    """Refuse a manifest whose ``config`` or ``scores`` entries disagree with the detector inside.

    Raises :class:`ModelFileError` naming the first entry that differs, or when the manifest
    does not say ``estimator: FaultDetector`` or names another head than the detector's
    (``load_detector`` calls it; so does the model cache for a file it loaded with ``load_model``).

    The file's sha256 covers the model, not the manifest: an edited threshold, class
    list, head or score would otherwise be shown (``inkdiag`` prints the manifest's
    head) while the model inside does something else. Entries a manifest lacks (files
    written before they existed) are not checked."""
    _require_detector_manifest(path, manifest)
    if detector.profile is not None and model_head_sha256(manifest) != detector.head_sha256:
        raise ModelFileError(f"model file {path}: its manifest's profile_sha256 is not the head of the detector "
                             "inside: refusing an inconsistent file")
    own, scores = _detector_entries(detector)
    if detector.profile is None:  # a default-head model: the default head's sha256 when it was written
        own.pop("profile_sha256")  # (model_head_sha256: it stays the current default head's)
    for section, mine in (("config", own), ("scores", scores)):
        theirs = manifest.get(section)
        if not isinstance(theirs, dict):
            raise ModelFileError(f"model file {path}: its manifest's {section} is not an object")
        if section == "scores" and set(theirs) - set(mine):  # every score is the detector's
            raise ModelFileError(f"model file {path}: its manifest's scores {sorted(set(theirs) - set(mine))} are not "
                                 "the model's: manifest edited, refusing an inconsistent file")
        # through JSON (the text the manifest was written as): tuples are lists, NaN equals NaN
        mine = json.loads(json.dumps({k: mine[k] for k in theirs if k in mine}, default=str))
        where = _first_difference({k: theirs[k] for k in mine}, mine, section)
        if where is not None:
            key, got, want = where
            raise ModelFileError(f"model file {path}: its manifest's {key} is {_clip(got)}, the model's {_clip(want)}: "
                                 "manifest edited, refusing an inconsistent file")


def _clip(text: str, n: int = 60) -> str:
    """``text``, or its first ``n`` characters and `` ...`` with how many more there are: an error stays one line."""
    return text if len(text) <= n else f"{text[:n]} ... ({len(text) - n} characters more)"


def _require_detector_manifest(path, manifest: dict) -> None:
    if manifest.get("config", {}).get("estimator") != DETECTOR_ESTIMATOR:
        raise ModelFileError(f"model file {path} is not a FaultDetector file (its manifest's config has no "
                             f"estimator={DETECTOR_ESTIMATOR!r}; a plain pipeline is read by load_model)")


def _first_difference(a, b, key: str):
    """``(key path, a's JSON, b's JSON)`` where two JSON documents first differ, or None."""
    if isinstance(a, dict) and isinstance(b, dict) and set(a) == set(b):
        for k in sorted(a):
            if (d := _first_difference(a[k], b[k], f"{key}.{k}")) is not None:
                return d
        return None
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        for i, (x, y) in enumerate(zip(a, b)):
            if (d := _first_difference(x, y, f"{key}[{i}]")) is not None:
                return d
        return None
    if isinstance(a, list) and isinstance(b, list):  # a list of another length: said so, not as two clipped lists
        return key, f"a list of {len(a)}", f"a list of {len(b)}"
    ja, jb = json.dumps(a, sort_keys=True), json.dumps(b, sort_keys=True)
    return None if ja == jb else (key, ja, jb)


def load_detector(path, *, check_versions: bool = True):
    """Verify a :func:`save_detector` file against its manifest, unpickle it, and return the detector.

    The checks are :func:`load_model`'s (missing file or manifest, size, sha256,
    library versions), all before unpickling; then the file must hold a
    :class:`inkdiag_core.FaultDetector` whose manifest says so.

    Parameters
    ----------
    path : str or Path
    check_versions : bool
        As for :func:`load_model`.

    Returns
    -------
    FaultDetector
        Fitted, with ``file_sha256_`` (and so ``model_id``) of this file.

    Raises
    ------
    ModelFileError
        As :func:`load_model`, or the file holds something else (e.g. a plain
        pipeline written by :func:`save_model`).
    """
    from .detector import FaultDetector

    path = Path(path)
    _require_detector_manifest(path, read_manifest(path))  # before anything is unpickled
    detector, manifest = load_model(path, check_versions=check_versions, as_pipeline=False)
    if not isinstance(detector, FaultDetector):
        raise ModelFileError(f"model file {path} holds a {type(detector).__name__}, not a FaultDetector")
    check_manifest_entries(path, manifest, detector)
    detector.file_sha256_ = manifest["sha256"]
    return detector


def model_head_sha256(manifest: dict) -> str:
    """sha256 of the head a model file is for, from its manifest (:func:`read_manifest`).

    ``config['profile_sha256']`` of a model trained on a profile; a model of the
    default head without one (``config['profile']`` null, or a file written before
    head profiles) is the *current* default head's (:meth:`inkdiag_core.HeadProfile.default`),
    as its detector says (:attr:`inkdiag_core.FaultDetector.head_sha256`).
    """
    cfg = manifest.get("config", {})
    sha = cfg.get("profile_sha256")
    if sha is None or cfg.get("profile") is None:
        from .head_profile import HeadProfile

        return HeadProfile.default().sha256
    if not isinstance(sha, str):
        raise ModelFileError(f"manifest of {manifest.get('file', 'the model')}: profile_sha256 must be a string, "
                             f"got {type(sha).__name__}")
    return sha
