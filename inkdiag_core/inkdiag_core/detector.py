"""The whole FDI model as one scikit-learn estimator: :class:`FaultDetector`.

Until now an FDI model travelled as loose pieces: a fitted pipeline
(:func:`inkdiag_core.make_fdi_pipeline`), its fault-detection threshold in the
manifest, a second pipeline for the per-nozzle baselines with its own
threshold, and a model id derived by the node. A :class:`FaultDetector` holds
them all, as scikit-learn's ``FixedThresholdClassifier`` holds its decision
rule:

- ``pipeline_`` and ``fd_threshold_``: raw traces (n, n_samples) -> classes;
- optionally ``baseline_pipeline_`` and ``baseline_fd_threshold_``: the same
  traces with each nozzle's healthy baseline KPIs (n, 7)
  (:mod:`inkdiag_core.baselines`);
- optionally ``openset_`` and ``baseline_openset_``: each branch's open-set layer
  (:mod:`inkdiag_core.openset`), which calls a row ``unknown`` when it is unlike
  every known class, at a calibrated false-unknown rate ``unknown_rate``;
- :meth:`FaultDetector.label`: one call that routes each row to its branch;
- :attr:`FaultDetector.model_id`, from the sha256 of the file it was saved to
  or loaded from (:func:`inkdiag_core.save_detector`,
  :func:`inkdiag_core.load_detector`).

Training is :func:`inkdiag_core.fdi.train_default_model`'s procedure: a
stratified split, the pipeline fitted on one part, the false-negative-averse
threshold (:func:`inkdiag_core.fdi.fnr_threshold`) and the scores from the other.
"""

from __future__ import annotations

import functools
import numbers
from typing import NamedTuple

import numpy as np
from sklearn.base import BaseEstimator, ClassifierMixin
from sklearn.ensemble import RandomForestClassifier
from sklearn.model_selection import train_test_split
from sklearn.utils.multiclass import check_classification_targets
from sklearn.utils.validation import check_is_fitted, validate_data

from .baselines import N_KPIS, with_baseline
from .baselines.features import RELATIVE_EPS, BaselineKpis
from .faults import healthy_mask
from .fdi import (
    FEATURE_SETS,
    decide_classes,
    finite_rows_proba,
    flat_forest,
    make_fdi_pipeline,
    pipeline_predict_proba,
    threshold_and_scores,
)
from .kpis import MIN_KPI_SAMPLES, KpiExtractor, extract_kpis, kpis_of_checked
from .openset import (
    OPENSET_FEATURES_VERSION,
    UNKNOWN,
    ConformalOpenSet,
    baseline_openset_features,
    check_unknown_rate,
    openset_features,
)

__all__ = ["DetectorLabels", "FaultDetector"]

#: Sample rate of a detector with neither ``sample_rate_hz`` nor a profile: the default head's, Hz.
DEFAULT_SAMPLE_RATE_HZ = 10e6
#: Feature set of the baseline branch (its rows are ``with_baseline(traces, baseline_kpis)``).
BASELINE_FEATURES = "kpi_y+baseline"
_DTYPES = [np.float64, np.float32]


@functools.lru_cache(maxsize=32)
def _healthy_classes(classes: tuple) -> np.ndarray:
    """``healthy_mask(classes)`` once per set of classes (read-only): ``label`` must not change the
    detector's ``__dict__`` (scikit-learn's contract), so the mask is cached here, not on it."""
    mask = healthy_mask(np.asarray(classes, dtype=object))
    mask.flags.writeable = False
    return mask


class DetectorLabels(NamedTuple):
    """Per-row result of :meth:`FaultDetector.label` (n = rows).

    classes : ndarray of object, (n,) -- class of each row (a value of ``classes_``, or
        ``"unknown"`` (:data:`inkdiag_core.openset.UNKNOWN`) where the open-set layer finds
        the row unlike every known class), None where the row is not ``valid``
    confidence : ndarray of float64, (n,) -- probability of that class; for an
        ``"unknown"`` row its ``unknown_score``; NaN where not valid
    p_faulty : ndarray of float64, (n,) -- 1 minus the probability of the healthy classes;
        1.0 for an ``"unknown"`` row (an unknown is a fault for fault detection, never
        healthy); NaN where not valid
    baseline : ndarray of bool, (n,) -- the row went to the baseline branch
    valid : ndarray of bool, (n,) -- False where the row's features came out NaN or Inf
        in float32 (e.g. a finite sample so large that its energy overflows): that row
        is not classified, the others are
    unknown_score : ndarray of float64, (n,) -- ``1 - max_c q_c``, the row's largest
        per-class conformal p-value, scaled to the class's training-conditional level
        (:meth:`inkdiag_core.openset.ConformalOpenSet.unknown_score`), subtracted from 1 (in [0, 1); the row
        is ``"unknown"`` when it is ``>= 1 - unknown_rate``; a row whose ringing is below the layer's noise floor,
        :data:`inkdiag_core.openset.SNR_FLOOR`: against the chosen class alone, by that weakness); NaN where not
        valid or where
        the row's branch has no open-set layer (``unknown_rate`` None, or a model file
        from before the layer) or the row's open-set features are not finite (then it
        keeps its classifier's class)
    """

    classes: np.ndarray
    confidence: np.ndarray
    p_faulty: np.ndarray
    baseline: np.ndarray
    valid: np.ndarray
    unknown_score: np.ndarray = None


class FaultDetector(ClassifierMixin, BaseEstimator):
    """Fault detection and isolation of piezo inkjet traces, with its decision threshold.

    A trace is faulty when its P(faulty) (1 minus the probability of the two healthy
    classes) reaches the learned ``fd_threshold_``; a faulty trace gets its most
    probable fault class, a healthy one its more probable healthy class
    (:func:`inkdiag_core.fdi.classify`). ``fit`` learns the threshold that misses at
    most ``fnr_target`` of the faults of a held-out split.

    Open set: with ``unknown_rate`` (default 0.01) each branch also gets a per-class
    split-conformal layer (:class:`inkdiag_core.openset.ConformalOpenSet`): per class the
    squared Mahalanobis distance (regularised covariance) of the trace's
    open-set features (the KPIs, the energy fraction the KPIs' damped sinusoid leaves
    unexplained and, in the baseline branch, the KPIs relative to the nozzle's own
    healthy baseline) gives a conformal p-value ``p_c``; a row below every class's
    training-conditional level (:func:`inkdiag_core.openset.training_conditional_level`)
    is labelled ``"unknown"`` whatever the classifier says.
    **Guarantee**: for the detector one ``fit`` returns, a trace of a known class ``c``,
    exchangeable with that class's calibration rows (same head, same conditions as the
    training data), is called ``"unknown"`` with probability at most ``unknown_rate``, with
    probability at least 90 % over the draw of the calibration rows
    (:data:`inkdiag_core.openset.DEFAULT_DELTA`); on average about ``1 / (n_c + 1)`` to
    ``unknown_rate / 2``. Each class needs ``(1 - unknown_rate) ** n_c <= 0.1``
    calibration rows (230 for 0.01); with fewer in any class the layer never says unknown.
    The class models are fitted on the validation split and calibrated on the
    classifier's training split (the nonconformity score does not involve the
    classifier, so calibration rows need only be held out from the class models;
    calibrating on the larger split steadies each class's threshold: with 400 traces
    per class the largest per-class false-unknown rate over 4 training seeds was
    1.5-2.4 % this way against 2.1-4.1 % calibrated on the 100 validation traces).
    ``predict`` then returns ``"unknown"`` too, a value not in ``classes_`` (scikit-learn's
    open-set convention for novelty; ``classes_`` stays the known classes).

    Parameters
    ----------
    kind : {"rf", "knn"}
        Random Forest or k-nearest neighbours (:func:`inkdiag_core.make_fdi_pipeline`).
    features : str
        Feature set of the plain branch: one of :data:`inkdiag_core.FEATURE_SETS`
        except ``"kpi_y+baseline"`` (baselines are given to ``fit`` and ``label``
        as ``baseline_kpis`` instead; the baseline branch always uses that set).
    sample_rate_hz : float or None
        Sample rate of the traces, Hz. None (default): the profile's (10 MHz, the
        default head's, without one). A number with a profile must be the
        profile's (kept for callers from before profiles).
    profile : HeadProfile or None
        The head the traces come from (a complete :class:`inkdiag_core.HeadProfile`):
        its sample rate, its healthy model in the residual filters and its frequency
        scale on the feature bands (:func:`inkdiag_core.fdi.make_fdi_pipeline`).
        None: the default head, exactly as before profiles. The model file records
        the profile and its sha256 (:func:`inkdiag_core.save_detector`), so a
        labeller of another head refuses it.
    n_estimators, min_samples_leaf : int
        Random Forest size (``kind="rf"``).
    max_features : {"sqrt", "log2"}, int, float or None
        Features each split of the forest may choose from (scikit-learn's
        ``max_features``). Default None: every feature. On KPI_Y (7 features) that
        tells partially blocked from dried nozzles better than scikit-learn's
        ``"sqrt"`` (2 per split): trained on a head's own traces, partially_blocked
        71.0 against 63.5 % on the 20 MHz head and 49.5 against 42.0 % on the 5 MHz
        head of ``reports/separability.md``; trained on inkdiag's simulation of the
        20 MHz head (``reports/heads.md``), 78.0 against 70.5 % with its true profile
        and a weakest class of 67.5-78.0 against 65.0-73.5 % over three calibrated
        runs (on the 5 MHz head's calibrated profile, whose restrictor is 7-12 % off,
        partially_blocked fell from 19.5-28.5 to 17.0-22.0 %). Measured on KPI_Y only;
        a fit takes 2.5x longer on KPI_Y and 5x on the 36 ``rich`` features. Files from before
        this parameter read as ``"sqrt"``, what they were fitted with.
    n_neighbors : int
        Neighbours (``kind="knn"``).
    fnr_target : float in [0, 1)
        Largest fraction of validation faults the threshold may miss.
    validation_fraction : float in (0, 1)
        Fraction of the training rows held out (stratified) to learn the threshold
        and the scores; the rest fit the pipelines.
    unknown_rate : float in (0, 1), or None or 0
        Bound on the probability that a known trace is called ``"unknown"`` (default
        0.01); None or 0: no open-set layer (``classes`` are always ``classes_`` values).
    random_state : int or None
        Seed of the split and of the forests (one seed for both, as
        :func:`inkdiag_core.fdi.train_default_model` has always used).
    n_jobs : int or None
        Parallel trees when fitting a forest.

    Attributes
    ----------
    pipeline_ : sklearn.pipeline.Pipeline
        Plain branch: raw traces (n, n_samples) -> classes.
    fd_threshold_ : float in (0, 1]
        Its fault-detection threshold on P(faulty).
    scores_ : dict
        Its validation scores (``validation_fi_accuracy``,
        ``validation_fi_accuracy_at_threshold``, ``validation_fd_fnr``,
        ``validation_fd_fpr``: fractions; ``n_validation``).
    baseline_pipeline_ : sklearn.pipeline.Pipeline or None
        Baseline branch (``"kpi_y+baseline"``), taking
        ``with_baseline(traces, baseline_kpis)`` rows (n, n_samples + 7); None when
        ``fit`` was given no ``baseline_kpis``.
    baseline_fd_threshold_ : float or None
        Its threshold.
    baseline_scores_ : dict or None
        Its validation scores (same keys as ``scores_``, same split).
    openset_ : ConformalOpenSet or None
        Open-set layer of the plain branch (None without ``unknown_rate``).
    baseline_openset_ : ConformalOpenSet or None
        Open-set layer of the baseline branch.
    classes_ : ndarray, shape (n_classes,)
        Class labels (``FaultClass`` values for the project's models).
    n_features_in_ : int
        Samples per trace the detector was fitted on.
    file_sha256_ : str
        Set by :func:`inkdiag_core.save_detector` / :func:`inkdiag_core.load_detector`:
        sha256 of the file; never pickled, cleared by ``fit``.
    """

    def __init__(self, *, kind="rf", features="kpi_y", sample_rate_hz=None, profile=None, n_estimators=50,
                 min_samples_leaf=3, max_features=None, n_neighbors=5, fnr_target=0.005, validation_fraction=0.25,
                 unknown_rate=0.01, random_state=0, n_jobs=None):
        self.kind = kind
        self.features = features
        self.sample_rate_hz = sample_rate_hz
        self.profile = profile
        self.n_estimators = n_estimators
        self.min_samples_leaf = min_samples_leaf
        self.max_features = max_features
        self.n_neighbors = n_neighbors
        self.fnr_target = fnr_target
        self.validation_fraction = validation_fraction
        self.unknown_rate = unknown_rate
        self.random_state = random_state
        self.n_jobs = n_jobs

    # -- the head ---------------------------------------------------------------------------

    @property
    def sample_rate_hz_(self) -> float:
        """The sample rate the detector works at, Hz: ``sample_rate_hz``, else the profile's, else 10 MHz."""
        if self.sample_rate_hz is not None:
            return float(self.sample_rate_hz)
        if self.profile is not None:
            return float(self.profile.sample_rate_hz)
        return DEFAULT_SAMPLE_RATE_HZ

    @property
    def head_sha256(self) -> str:
        """sha256 of the head this detector is for (:attr:`inkdiag_core.HeadProfile.sha256`).

        The profile's; without a profile (and in files from before profiles) the
        default head's.
        """
        from .head_profile import HeadProfile

        return (self.profile if self.profile is not None else HeadProfile.default()).sha256

    @property
    def head_name(self) -> str:
        """Name of the head's profile (``"default"`` without one)."""
        return self.profile.name if self.profile is not None else "default"

    def __setstate__(self, state):  # files pickled before profiles / the open-set layer
        state.setdefault("profile", None)
        state.setdefault("unknown_rate", None)
        state.setdefault("max_features", "sqrt")  # scikit-learn's default, what they were fitted with
        if "pipeline_" in state:
            state.setdefault("openset_", None)
            state.setdefault("baseline_openset_", None)
        super().__setstate__(state)

    # -- fitting ---------------------------------------------------------------------------

    def _make_pipeline(self, features):
        return make_fdi_pipeline(self.kind, features, sample_rate_hz=self.sample_rate_hz_,
                                 random_state=self.random_state, n_estimators=self.n_estimators,
                                 min_samples_leaf=self.min_samples_leaf, max_features=self.max_features,
                                 n_neighbors=self.n_neighbors, n_jobs=self.n_jobs, profile=self.profile)

    def _check_params(self):
        if self.features not in FEATURE_SETS or self.features == BASELINE_FEATURES:
            raise ValueError(f"features must be one of {tuple(f for f in FEATURE_SETS if f != BASELINE_FEATURES)} "
                             f"(give baselines to fit/label as baseline_kpis), got {self.features!r}")
        if self.kind not in ("rf", "knn"):
            raise ValueError(f"kind must be 'rf' or 'knn', got {self.kind!r}")
        if self.profile is not None:
            from .head_profile import HeadProfile

            if not isinstance(self.profile, HeadProfile):
                raise ValueError(f"profile must be a HeadProfile or None, got {type(self.profile).__name__}")
            if not self.profile.is_complete:
                raise ValueError(f"profile {self.profile.name!r} is nominal ({', '.join(self.profile.missing)} "
                                 "missing): a detector needs a complete profile (run `inkdiag calibrate` first)")
            if self.sample_rate_hz is not None and float(self.sample_rate_hz) != self.profile.sample_rate_hz:
                raise ValueError(f"sample_rate_hz={self.sample_rate_hz!r} Hz but profile {self.profile.name!r} is "
                                 f"sampled at {self.profile.sample_rate_hz:g} Hz (leave sample_rate_hz None)")
        for name, lo_open, hi_open, lo, hi in (("fnr_target", False, True, 0.0, 1.0),
                                               ("validation_fraction", True, True, 0.0, 1.0)):
            v = getattr(self, name)
            ok = isinstance(v, numbers.Real) and not isinstance(v, bool) and np.isfinite(v) and (
                (lo < v if lo_open else lo <= v) and (v < hi if hi_open else v <= hi))
            if not ok:
                raise ValueError(f"{name} must be a real number in {'(' if lo_open else '['}{lo:g}, {hi:g}"
                                 f"{')' if hi_open else ']'}, got {v!r}")
        check_unknown_rate(self.unknown_rate)

    def _fitted_threshold(self, pipeline, Xval, yval, branch):
        threshold, scores = threshold_and_scores(pipeline, Xval, yval, self.fnr_target)
        if not 0.0 < threshold <= 1.0:
            raise ValueError(
                f"the {branch} branch's fault-detection threshold for fnr_target={self.fnr_target!r} is "
                f"{threshold!r}: more than that fraction of the validation faults have P(faulty) = 0; "
                "lower fnr_target or train on more rows")
        return threshold, scores

    def fit(self, X, y, *, baseline_kpis=None, validation_mask=None):
        """Fit the plain branch (and the baseline branch with ``baseline_kpis``) and their thresholds.

        Parameters
        ----------
        X : array_like, shape (n, n_samples)
            Raw traces, V (float64 or float32).
        y : array_like, shape (n,)
            Class of each trace (``FaultClass`` values for the project's models).
        baseline_kpis : array_like, shape (n, 7), optional
            Healthy baseline KPIs of each trace's nozzle (:func:`inkdiag_core.baseline_kpis`;
            for simulated training data :func:`inkdiag_core.baselines.baseline_training_kpis`),
            all finite. Fits the baseline branch on ``with_baseline(X, baseline_kpis)``
            with the same split.
        validation_mask : array_like of bool, shape (n,), optional
            The rows held out for the threshold and the scores (True), instead of
            the stratified split of ``validation_fraction`` (:func:`inkdiag_core.training.train_detector`
            uses it to keep every copy of a replicated recorded row on one side).

        Returns
        -------
        self
        """
        self.__dict__.pop("file_sha256_", None)
        self._check_params()
        X, y = validate_data(self, X, y, dtype=_DTYPES, ensure_min_features=MIN_KPI_SAMPLES)
        if self.profile is not None and X.shape[1] != self.profile.n_samples:
            raise ValueError(f"X has traces of {X.shape[1]} samples; profile {self.profile.name!r} has "
                             f"{self.profile.n_samples}")
        check_classification_targets(y)
        base = None
        if baseline_kpis is not None:
            base = np.asarray(baseline_kpis)
            if base.shape != (X.shape[0], N_KPIS):
                raise ValueError(f"baseline_kpis must be ({X.shape[0]}, {N_KPIS}), one row per trace; got "
                                 f"shape {base.shape}")
            if not np.isfinite(base).all():
                raise ValueError(f"baseline_kpis must be finite to fit on; {int((~np.isfinite(base).all(1)).sum())} "
                                 "rows are not")
        if validation_mask is None:
            # The same split as train_test_split(X, y, ...) gives: it depends on y and n only.
            train, val = train_test_split(np.arange(X.shape[0]), test_size=self.validation_fraction,
                                          random_state=self.random_state, stratify=y)
        else:
            m = np.asarray(validation_mask)
            if m.shape != (X.shape[0],) or m.dtype != bool or m.all() or not m.any():
                raise ValueError(f"validation_mask must be a boolean array of shape ({X.shape[0]},) with rows on "
                                 "both sides")
            train, val = np.flatnonzero(~m), np.flatnonzero(m)
        self.pipeline_ = self._make_pipeline(self.features).fit(X[train], y[train])
        self.classes_ = self.pipeline_.classes_
        self.fd_threshold_, self.scores_ = self._fitted_threshold(self.pipeline_, X[val], y[val], "plain")
        self.openset_ = self._fit_openset(self.pipeline_, X, X, y, train, val, False)
        self.baseline_pipeline_ = self.baseline_fd_threshold_ = self.baseline_scores_ = None
        self.baseline_openset_ = None
        if base is not None:
            rows = with_baseline(X, base)
            self.baseline_pipeline_ = self._make_pipeline(BASELINE_FEATURES).fit(rows[train], y[train])
            self.baseline_fd_threshold_, self.baseline_scores_ = self._fitted_threshold(
                self.baseline_pipeline_, rows[val], y[val], "baseline")
            self.baseline_openset_ = self._fit_openset(self.baseline_pipeline_, rows, X, y, train, val, True)
        return self

    def _openset_features(self, feats, X, baseline):
        """Open-set feature rows of traces ``X`` from their branch's pipeline features ``feats``."""
        fs = self.sample_rate_hz_
        if baseline:
            return baseline_openset_features(X, feats, fs)
        kpis = feats[:, :7] if self.features in ("kpi_y", "rich") else extract_kpis(X, fs)
        return openset_features(X, kpis, fs)

    def _fit_openset(self, pipeline, rows, X, y, train, val, baseline):
        """A branch's open-set layer: class models on the validation rows, calibrated on the training rows."""
        rate = check_unknown_rate(self.unknown_rate)
        if rate is None:
            return None
        with np.errstate(all="ignore"):
            F = self._openset_features(pipeline[0].transform(rows), X, baseline)
        # each distinct row calibrates once (train_detector replicates recorded rows in the training split)
        Xt = np.ascontiguousarray(rows[train])
        _, first = np.unique(Xt.view(np.dtype((np.void, Xt.dtype.itemsize * Xt.shape[1]))).ravel(),
                             return_index=True)
        cal = train[np.sort(first)]
        return ConformalOpenSet(rate).fit(F[val], y[val], F[cal], y[cal], self.classes_,
                                          noise_v=self._noise_level(X, F, y))

    def _noise_level(self, X, F, y):
        """The head's noise standard deviation, V, from the training traces: the median over the healthy classes'
        rows of what their KPI sinusoid leaves unexplained, ``sqrt(unexplained fraction * AC energy / n_samples)``
        (a healthy trace is one damped sinusoid and noise). None without healthy rows or a finite value."""
        h = np.flatnonzero(np.isin(y, self.classes_[_healthy_classes(tuple(self.classes_.tolist()))]))
        if h.size == 0:
            return None
        ac = np.empty(h.size)
        for a in range(0, h.size, 1024):  # 1,024 rows at a time in float64: a long trace's copies stay small
            x = np.asarray(X[h[a:a + 1024]], dtype=np.float64)
            ac[a:a + 1024] = ((x - x.mean(axis=1, keepdims=True)) ** 2).sum(axis=1)
        with np.errstate(all="ignore"):
            rms = np.sqrt(10.0 ** F[h, 7] * ac / X.shape[1])
        rms = rms[np.isfinite(rms)]
        noise = float(np.median(rms)) if rms.size else np.nan
        return noise if np.isfinite(noise) and noise > 0 else None

    # -- inference ------------------------------------------------------------------------

    def predict_proba(self, X):
        """Class probabilities of the plain branch.

        Parameters
        ----------
        X : array_like, shape (n, n_features_in_)
            Raw traces, V.

        Returns
        -------
        ndarray of float64, shape (n, n_classes)
            Columns in ``classes_`` order (bit-identical to ``pipeline_.predict_proba``).
        """
        check_is_fitted(self)
        X = validate_data(self, X, dtype=_DTYPES, reset=False)
        return pipeline_predict_proba(self.pipeline_, X)

    def predict(self, X):
        """Class of each trace at ``fd_threshold_`` (plain branch), or ``"unknown"``.

        Parameters
        ----------
        X : array_like, shape (n, n_features_in_)
            Raw traces, V.

        Returns
        -------
        ndarray, shape (n,)
            Values of ``classes_`` (its dtype), and ``"unknown"`` where the open-set layer
            says so: a value outside ``classes_`` (scikit-learn's open-set convention; with
            non-string classes the array is then of object dtype).

        Raises
        ------
        ValueError
            Some rows' features are not finite (:meth:`label` leaves them out instead).
        """
        out = self.label(X)
        if not out.valid.all():
            raise ValueError(f"{int((~out.valid).sum())} of {len(out.valid)} rows have non-finite features "
                             "(label() classifies the others)")
        unknown = out.classes == UNKNOWN
        if unknown.any() and self.classes_.dtype.kind not in "OU":
            return out.classes
        dtype = self.classes_.dtype
        if unknown.any() and dtype.kind == "U" and dtype.itemsize // 4 < len(UNKNOWN):
            dtype = np.dtype(f"U{len(UNKNOWN)}")
        return out.classes.astype(dtype)

    def label(self, X, *, baseline_kpis=None) -> DetectorLabels:
        """Classes, confidences and P(faulty) of traces, each row by its branch.

        Rows whose ``baseline_kpis`` row is all finite are labelled by the baseline
        branch at ``baseline_fd_threshold_`` when the detector has one; every other row
        by the plain branch at ``fd_threshold_``. One batch per branch. A row whose
        features are not finite is not classified (``valid`` False) and costs no other row.
        Where the branch has an open-set layer, a row unlike every known class is
        ``"unknown"`` (confidence = its ``unknown_score``, ``p_faulty`` 1): with the
        baseline branch, a nozzle unlike its own healthy self and unlike every known fault.

        Parameters
        ----------
        X : array_like, shape (n, n_features_in_)
            Raw traces, V; finite (screen them first: :func:`inkdiag_core.screen_traces`).
        baseline_kpis : array_like, shape (n, 7), optional
            Each row's nozzle baseline KPIs, NaN where the nozzle has none (as
            :meth:`inkdiag_core.NozzleBaselines.lookup` returns them). Ignored by a
            detector without a baseline branch (then ``baseline`` is all False).

        Returns
        -------
        DetectorLabels
        """
        X = self._checked_traces(X)
        n = X.shape[0]
        use = np.zeros(n, dtype=bool)
        if baseline_kpis is not None and self.baseline_pipeline_ is not None:
            base = np.asarray(baseline_kpis)
            if base.shape != (n, N_KPIS):
                raise ValueError(f"baseline_kpis must be ({n}, {N_KPIS}), one row per trace; got shape {base.shape}")
            use = np.isfinite(base).all(axis=1)
        classes = np.full(n, None, dtype=object)
        confidence = np.full(n, np.nan)
        p_faulty = np.full(n, np.nan)
        valid = np.ones(n, dtype=bool)
        unknown_score = np.full(n, np.nan)
        healthy = _healthy_classes(tuple(self.classes_.tolist()))
        openset = getattr(self, "openset_", None)
        baseline_openset = getattr(self, "baseline_openset_", None)
        for rows, pipeline, threshold, layer in (
                (use, self.baseline_pipeline_, self.baseline_fd_threshold_, baseline_openset),
                (~use, self.pipeline_, self.fd_threshold_, openset)):
            if not rows.any():
                continue
            plain = pipeline is not self.baseline_pipeline_
            Xt = X if rows.all() else X[rows]  # no copy when every row is on one branch
            tail = self._label_tail(Xt, None if plain else base[rows], pipeline, threshold, layer, plain, healthy)
            if tail is not None:
                ok, idx, conf, pf, score = tail
                at = np.flatnonzero(rows)
                if not ok.all():
                    valid[at[~ok]] = False
                    idx, conf, pf, score, at = idx[ok], conf[ok], pf[ok], score[ok], at[ok]
                unk = idx < 0
                cls = self.classes_[np.where(unk, 0, idx)].astype(object)
                cls[unk] = UNKNOWN
                classes[at], confidence[at], p_faulty[at], unknown_score[at] = cls, conf, pf, score
                continue
            # the baseline branch's features from the traces and the baseline KPIs apart, not from a stacked
            # copy of them (knn needs the stacked rows for its open-set features)
            apart = None if plain or len(pipeline) > 2 else getattr(pipeline[0], "_features_of", None)
            Xr = Xt if plain else with_baseline(Xt, base[rows]) if apart is None else None
            with np.errstate(all="ignore"):  # overflowing rows are found below, as finite_rows_proba does
                given = None if apart is None else apart(Xt, base[rows])
            ok, proba, feats = finite_rows_proba(pipeline, Xr, return_features=True, checked=True, features=given)
            at = np.flatnonzero(rows)
            valid[at[~ok]] = False
            if proba.shape[0]:
                pf = 1.0 - proba[:, healthy].sum(axis=1)  # as fault_probability computes it
                idx, conf = decide_classes(self.classes_, proba, pf, threshold, healthy=healthy)
                cls = self.classes_[idx].astype(object)
                if layer is not None:
                    outdated = self.openset_outdated()
                    if outdated:
                        raise ValueError(outdated)
                    sel = ok.all()
                    with np.errstate(all="ignore"):  # a row's overflow is its own (not valid), as above
                        if len(pipeline) > 2:  # knn: the features before its scaler
                            feats = pipeline[0].transform(Xr)
                        F = self._openset_features(feats if sel else feats[ok], Xt if sel else Xt[ok], not plain)
                    score = layer.unknown_score(F, chosen=idx)
                    unk = layer.is_unknown(score)
                    cls[unk] = UNKNOWN
                    conf = np.where(unk, score, conf)
                    pf = np.where(unk, 1.0, pf)
                    unknown_score[at[ok]] = score
                at = at[ok]
                classes[at] = cls
                confidence[at] = conf
                p_faulty[at] = pf
        return DetectorLabels(classes, confidence, p_faulty, use, valid, unknown_score)

    def _label_tail(self, Xt, base, pipeline, threshold, layer, plain, healthy):
        """One branch's rows labelled by one compiled call from their KPIs on
        (:func:`inkdiag_core._kernels.detector_tail`), or None where that call does not apply
        (the loop in :meth:`label` then labels them): a forest on KPI_Y (the plain branch) or on the
        baseline branch's features, and an open-set layer (if any) of today's features and scores
        (``scores_version_`` 2 or later). ``scripts/bench fdi``: from the KPIs on 2.0-2.1x the loop's speed at the
        gate's 72 leftover rows, 3.0x at 8, 1.1x at 1,600 (a worst-case pass). The same labels as the
        loop, bit for bit: classes, confidences, P(faulty), validity and unknown scores (both score a row
        alone, :func:`inkdiag_core._kernels.mahalanobis_scores`). The tail's logs, cosines and sines are
        the C library's; numpy's float64 ones are too on this x86-64 (AVX2) machine, while on AVX-512
        numpy takes its own, which may differ in the last bit (after the float32 cast of the features,
        rarely a visible one).

        Returns
        -------
        ok, idx, conf, pf, uscore : ndarrays, shape (n,), or None
            As :func:`inkdiag_core._kernels.detector_tail` returns them.
        """
        n = Xt.shape[0]
        forest, step = pipeline[-1], pipeline[0]
        if not (n > 0 and len(pipeline) == 2 and type(forest) is RandomForestClassifier
                and forest.n_outputs_ == 1 and forest.n_features_in_ == (7 if plain else 13)
                and type(step) is (KpiExtractor if plain else BaselineKpis)
                and (not plain or self.features == "kpi_y")):
            return None
        params = None
        if layer is not None:
            if self.openset_outdated() or layer.means_.shape[1] != (8 if plain else 13):
                return None
            params = layer._tail_params()
            if params is None:
                return None
        from ._kernels import detector_tail  # numba: imported when a kernel is first needed

        with np.errstate(all="ignore"):  # overflowing rows come out not ok, as in the loop
            kpis = kpis_of_checked(Xt, float(step.sample_rate_hz))
        return detector_tail(kpis, base, Xt, self.sample_rate_hz_, flat_forest(forest), healthy, threshold, params,
                             eps=RELATIVE_EPS)

    def _checked_traces(self, X):
        """``X`` validated as scikit-learn's ``validate_data`` does, at a fraction of its cost for
        the common case (a finite float32/float64 ndarray of the fitted width): labelling a few
        rows, its checks cost as much as their KPIs."""
        if (isinstance(X, np.ndarray) and X.ndim == 2 and X.dtype in (np.float32, np.float64)
                and hasattr(self, "pipeline_") and not hasattr(self, "feature_names_in_")
                and X.shape[1] == self.n_features_in_ and np.isfinite(X).all()):
            return X
        check_is_fitted(self)
        return validate_data(self, X, dtype=_DTYPES, reset=False)

    def openset_outdated(self) -> str:
        """Why this detector's open-set layer cannot label with this inkdiag, or "" if it can.

        A layer fitted on the open-set features of an older inkdiag
        (:data:`inkdiag_core.openset.OPENSET_FEATURES_VERSION`) cannot score today's;
        :meth:`label` raises with this message and :class:`inkdiag_core.FrameLabeller`
        refuses such a model at construction.
        """
        for layer in (getattr(self, "openset_", None), getattr(self, "baseline_openset_", None)):
            version = getattr(layer, "features_version_", 1)
            if layer is not None and version != OPENSET_FEATURES_VERSION:
                return (f"this model's open-set layer was fitted on the features of an older inkdiag "
                        f"(open-set features version {version}, now {OPENSET_FEATURES_VERSION}): "
                        "retrain it (inkdiag train)")
        return ""

    # -- identity -------------------------------------------------------------------------

    @property
    def model_id(self) -> str:
        """``fdi-<kind>-<features>[+baseline]-<first 12 hex of the file's sha256>``.

        The sha256 is the file's (:func:`inkdiag_core.save_detector` /
        :func:`inkdiag_core.load_detector` set it); ``...-unsaved`` before either.
        """
        check_is_fitted(self)
        sha = self.__dict__.get("file_sha256_")
        tail = sha[:12] if sha else "unsaved"
        branch = "+baseline" if self.baseline_pipeline_ is not None else ""
        return f"fdi-{self.kind}-{self.features}{branch}-{tail}"

    def __getstate__(self):
        state = dict(super().__getstate__())  # object.__getstate__ returns the live __dict__
        state.pop("file_sha256_", None)  # a file's hash cannot be inside the file
        return state

    def __sklearn_tags__(self):
        tags = super().__sklearn_tags__()
        tags.input_tags.allow_nan = False
        return tags
