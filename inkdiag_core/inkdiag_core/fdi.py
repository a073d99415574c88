"""Fault detection and isolation pipelines (thesis Part I, sections 3.2-3.6).

A whole FDI model is one scikit-learn ``Pipeline`` from raw traces
(n, n_samples) to class labels: features -> scaling where the classifier
needs it -> classifier. ``joblib`` saves and loads it as one object
(:mod:`inkdiag_core.persistence` adds the verified manifest).

Feature sets (``features=``):

``"kpi_y"``
    The 7 KPIs of the raw trace (the thesis's KPI_Y).
``"kpi_r"``
    The 7 KPIs of the original residual (KPI_R).
``"kpi_r_modified"``
    The 7 KPIs of the modified residual (KPI_R_Modified).
``"kpi_y+r_modified"``
    Both, side by side: the thesis's own suggestion (section 3.6).
``"rich"``
    KPI_Y + KPI_R_Modified + the KPIs of the second spectral mode + relative
    band energies of the raw trace: richer features where they earn their place.
``"kpi_y+baseline"``
    KPI_Y + the KPIs relative to the nozzle's own healthy baseline
    (:mod:`inkdiag_core.baselines`); its input rows are ``[trace, baseline KPIs]``
    (:func:`inkdiag_core.baselines.with_baseline`), not bare traces.

Tasks: ``"fi"`` classifies into the 12 classes of :class:`FaultClass` (both
healthy classes included, Table 2/9); ``"fd"`` is healthy (0) vs faulty (1),
both healthy classes counting as healthy (:func:`fd_labels`).
"""

from __future__ import annotations

import weakref

import numpy as np
import scipy.fft
from sklearn.base import BaseEstimator, TransformerMixin
from sklearn.ensemble import RandomForestClassifier
from sklearn.neighbors import KNeighborsClassifier
from sklearn.pipeline import FeatureUnion, Pipeline
from sklearn.preprocessing import StandardScaler
from sklearn.utils.validation import check_is_fitted, validate_data

from .faults import HEALTHY_VALUES, healthy_mask  # noqa: F401  (HEALTHY_VALUES: kept as fdi.HEALTHY_VALUES)
from .kpis import KPI_NAMES, MIN_KPI_SAMPLES, KpiExtractor, extract_kpis, reconstruct
from .residual import ResidualFilter, head_bands_hz

__all__ = [
    "FEATURE_SETS",
    "classify",
    "classify_finite",
    "decide_classes",
    "finite_rows_proba",
    "fault_probability",
    "fnr_threshold",
    "forest_predict_proba",
    "pipeline_predict_proba",
    "threshold_and_scores",
    "train_default_model",
    "BandEnergies",
    "RawTraceFeatures",
    "SecondModeKpis",
    "fd_labels",
    "head_band_edges_hz",
    "make_fdi_pipeline",
]

FEATURE_SETS = ("kpi_y", "kpi_r", "kpi_r_modified", "kpi_y+r_modified", "rich", "kpi_y+baseline")

#: Band edges of :class:`BandEnergies`, Hz: around the classes' modes (Table 3).
BAND_EDGES_HZ = (50e3, 150e3, 180e3, 195e3, 207e3, 219e3, 231e3, 245e3, 280e3, 320e3,
                 345e3, 400e3, 800e3, 1200e3, 1700e3, 2000e3, 2300e3, 5000e3)


def head_band_edges_hz(profile=None) -> tuple:
    """:data:`BAND_EDGES_HZ` for a head, Hz: the default head's edges times its frequency scale.

    The edges bracket the default head's fault modes (Table 3); another head's
    modes move with its healthy mode (:meth:`inkdiag_core.HeadProfile.frequency_scale`,
    exactly 1 for the default head). Edges beyond the Nyquist frequency leave
    empty bands (a constant feature), not an error.

    Parameters
    ----------
    profile : HeadProfile or None
        A complete head profile; None: the default head.

    Returns
    -------
    tuple of float
        Increasing band edges, Hz.
    """
    if profile is None:
        return BAND_EDGES_HZ
    scale = profile.frequency_scale()
    return tuple(float(e * scale) for e in BAND_EDGES_HZ)


def fd_labels(labels) -> np.ndarray:
    """Fault-detection targets: 0 for the healthy classes, 1 for every fault (int, (n,))."""
    return (~healthy_mask(labels)).astype(int)


def _second_mode(X, k1, fs):
    """Second-mode KPIs (n, 5) of traces ``X`` whose dominant-mode KPIs are ``k1``."""
    rest = X - reconstruct(k1, X.shape[1], fs)
    k2 = extract_kpis(rest, fs)
    eps = 1e-30
    return np.column_stack([
        k2[:, 1], k2[:, 2], k2[:, 3] / (k1[:, 3] + eps), k2[:, 4], k2[:, 5] / (k1[:, 5] + eps),
    ])


def _band_energies(X, fs, band_edges_hz):
    """Log10 fraction of each trace's AC energy per band, (n, n_bands)."""
    P = np.abs(scipy.fft.rfft(X - X.mean(axis=1, keepdims=True), axis=1)) ** 2
    f = np.fft.rfftfreq(X.shape[1], 1.0 / fs)
    idx = np.searchsorted(f, np.asarray(band_edges_hz, float))
    csum = np.concatenate([np.zeros((P.shape[0], 1)), np.cumsum(P, axis=1)], axis=1)
    band = csum[:, idx[1:]] - csum[:, idx[:-1]]
    return np.log10(band / (csum[:, -1:] + 1e-300) + 1e-12)


class RawTraceFeatures(TransformerMixin, BaseEstimator):
    """KPI_Y, second-mode KPIs and band energies of the raw trace, sharing one KPI fit.

    Output (n, 7 + 5 + n_bands): :data:`KPI_NAMES`, then the columns of
    :class:`SecondModeKpis`, then those of :class:`BandEnergies`.
    """

    def __init__(self, sample_rate_hz=10e6, band_edges_hz=BAND_EDGES_HZ):
        self.sample_rate_hz = sample_rate_hz
        self.band_edges_hz = band_edges_hz

    def fit(self, X, y=None):
        validate_data(self, X, dtype=[np.float64, np.float32], ensure_min_features=MIN_KPI_SAMPLES)
        BandEnergies(self.sample_rate_hz, self.band_edges_hz).fit(X)  # validates the edges
        return self

    def transform(self, X):
        check_is_fitted(self, "n_features_in_")
        X = validate_data(self, X, dtype=[np.float64, np.float32], reset=False)
        fs = float(self.sample_rate_hz)
        k1 = extract_kpis(X, fs)
        return np.hstack([k1, _second_mode(X, k1, fs), _band_energies(X, fs, self.band_edges_hz)])

    def get_feature_names_out(self, input_features=None):
        return np.concatenate([np.array(KPI_NAMES, dtype=object),
                               SecondModeKpis().get_feature_names_out(),
                               BandEnergies(band_edges_hz=self.band_edges_hz).get_feature_names_out()])


class SecondModeKpis(TransformerMixin, BaseEstimator):
    """KPIs of the second spectral mode: the trace minus its dominant damped sinusoid.

    The thesis extracts only the dominant frequency, even when several modes
    exist (its section 3.6). Here the dominant mode (from :func:`extract_kpis`)
    is subtracted and the KPIs of what is left are returned, with the
    amplitude and energy made relative to the first mode's (scale-free).

    Output: (n, 5): second-mode frequency (Hz), damping ratio, amplitude ratio,
    phase (rad), energy ratio.
    """

    def __init__(self, sample_rate_hz=10e6):
        self.sample_rate_hz = sample_rate_hz

    def fit(self, X, y=None):
        validate_data(self, X, dtype=[np.float64, np.float32], ensure_min_features=MIN_KPI_SAMPLES)
        return self

    def transform(self, X):
        check_is_fitted(self, "n_features_in_")
        X = validate_data(self, X, dtype=[np.float64, np.float32], reset=False)
        fs = float(self.sample_rate_hz)
        return _second_mode(X, extract_kpis(X, fs), fs)

    def get_feature_names_out(self, input_features=None):
        return np.array(["mode2_frequency_hz", "mode2_damping_ratio", "mode2_amplitude_ratio",
                         "mode2_phase_rad", "mode2_energy_ratio"], dtype=object)


class BandEnergies(TransformerMixin, BaseEstimator):
    """Log10 of the fraction of a trace's AC energy in each band of ``band_edges_hz``.

    Relative energies do not depend on the sensor gain; the bands bracket the
    classes' modes (Table 3). Output (n, len(band_edges_hz) - 1).
    """

    def __init__(self, sample_rate_hz=10e6, band_edges_hz=BAND_EDGES_HZ):
        self.sample_rate_hz = sample_rate_hz
        self.band_edges_hz = band_edges_hz

    def fit(self, X, y=None):
        validate_data(self, X, dtype=[np.float64, np.float32], ensure_min_features=MIN_KPI_SAMPLES)
        edges = np.asarray(self.band_edges_hz, float)
        if edges.ndim != 1 or edges.size < 2 or np.any(np.diff(edges) <= 0):
            raise ValueError(f"band_edges_hz must be increasing with >= 2 edges, got {self.band_edges_hz!r}")
        return self

    def transform(self, X):
        check_is_fitted(self, "n_features_in_")
        X = validate_data(self, X, dtype=[np.float64, np.float32], reset=False)
        return _band_energies(X, float(self.sample_rate_hz), self.band_edges_hz)

    def get_feature_names_out(self, input_features=None):
        e = np.asarray(self.band_edges_hz) / 1e3
        return np.array([f"band_{a:.0f}_{b:.0f}khz" for a, b in zip(e[:-1], e[1:])], dtype=object)


def _features(features: str, fs: float, profile=None):
    kpi_y = ("kpi_y", KpiExtractor(sample_rate_hz=fs))
    # The default head (profile None) keeps the filters' own defaults: the same pipeline as always.
    head = {} if profile is None else {"params": profile.channel_params(), "bands_hz": head_bands_hz(profile)}
    raw = {} if profile is None else {"band_edges_hz": head_band_edges_hz(profile)}

    def residual(kind, name):
        return (name, Pipeline([("residual", ResidualFilter(kind=kind, sample_rate_hz=fs, **head)),
                                ("kpis", KpiExtractor(sample_rate_hz=fs))]))

    if features == "kpi_y":
        return kpi_y[1]
    if features == "kpi_r":
        return residual("original", "kpi_r")[1]
    if features == "kpi_r_modified":
        return residual("modified", "kpi_r_modified")[1]
    if features == "kpi_y+r_modified":
        return FeatureUnion([kpi_y, residual("modified", "kpi_r_modified")])
    if features == "rich":
        return FeatureUnion([
            ("raw", RawTraceFeatures(sample_rate_hz=fs, **raw)),
            residual("modified", "kpi_r_modified"),
        ])
    if features == "kpi_y+baseline":
        from .baselines import BaselineKpis

        return BaselineKpis(sample_rate_hz=fs)
    raise ValueError(f"features must be one of {FEATURE_SETS}, got {features!r}")


def make_fdi_pipeline(kind: str = "rf", features: str = "kpi_y", *, sample_rate_hz: float | None = None,
                      random_state: int | None = 0, n_estimators: int = 100,
                      min_samples_leaf: int = 1, n_neighbors: int = 5,
                      n_jobs: int | None = None, profile=None, max_features="sqrt") -> Pipeline:
    """Build an unfitted FDI pipeline: features -> (scaling) -> classifier.

    Parameters
    ----------
    kind : {"rf", "knn"}
        Random Forest (no scaling: trees are scale-free) or k-nearest
        neighbours (standardised features).
    features : str
        One of :data:`FEATURE_SETS`.
    sample_rate_hz : float or None
        Sample rate of the traces the pipeline will see, Hz. None: the profile's
        (10 MHz, the default head's, without a profile); with a profile it must be
        the profile's.
    random_state : int or None
        Seed of the Random Forest.
    n_estimators, min_samples_leaf, n_neighbors : int
        Classifier sizes (the thesis does not state them; scikit-learn's defaults).
    n_jobs : int or None
        Parallel trees for the Random Forest.
    profile : HeadProfile or None
        The head the traces come from: the residual filters use its healthy model
        (:meth:`~inkdiag_core.HeadProfile.channel_params`) and its bands
        (:func:`inkdiag_core.residual.head_bands_hz`), the band energies its edges
        (:func:`head_band_edges_hz`). None: the default head.
    max_features : {"sqrt", "log2"}, int, float or None
        Features each split of the Random Forest may choose from (scikit-learn's
        ``max_features``; default ``"sqrt"``, scikit-learn's). :class:`inkdiag_core.FaultDetector`
        uses None (every feature).

    Returns
    -------
    sklearn.pipeline.Pipeline
        Input: raw traces (n, n_samples); output: labels as given to ``fit``.
    """
    if kind not in ("rf", "knn"):
        raise ValueError(f"kind must be 'rf' or 'knn', got {kind!r}")
    if sample_rate_hz is None:
        sample_rate_hz = 10e6 if profile is None else profile.sample_rate_hz
    elif profile is not None and float(sample_rate_hz) != profile.sample_rate_hz:
        raise ValueError(f"sample_rate_hz={sample_rate_hz!r} Hz but profile {profile.name!r} is sampled at "
                         f"{profile.sample_rate_hz:g} Hz")
    feats = _features(features, float(sample_rate_hz), profile)
    if kind == "rf":
        clf = RandomForestClassifier(n_estimators=n_estimators, min_samples_leaf=min_samples_leaf,
                                     max_features=max_features, random_state=random_state, n_jobs=n_jobs)
        return Pipeline([("features", feats), ("classifier", clf)])
    clf = KNeighborsClassifier(n_neighbors=n_neighbors)
    return Pipeline([("features", feats), ("scale", StandardScaler()), ("classifier", clf)])


def forest_predict_proba(forest, X) -> np.ndarray:
    """``RandomForestClassifier.predict_proba`` without its per-tree call overhead.

    scikit-learn calls each tree through joblib with input checks per tree,
    about 50 us per tree and call, and even each tree's bare ``tree_.predict``
    costs ~3 us a call: on the few rows the healthy gate leaves, about half the
    forest's time. Up to ``_KERNEL_MAX_ROWS`` rows the forest is flattened once
    (its node arrays, kept while the forest's trees stay the same) and a compiled
    kernel (:func:`inkdiag_core._kernels.forest_proba`) walks every tree for each
    row in one call; beyond, each tree's ``tree_.predict`` runs. Either way on one
    validated float32 copy, summing the probabilities in the same order, so the
    result is bit-identical to ``forest.predict_proba(X)`` (a test checks it).

    Parameters
    ----------
    forest : fitted sklearn.ensemble.RandomForestClassifier, single output
    X : array_like, shape (n_samples, n_features)
        Finite feature rows.

    Returns
    -------
    ndarray, shape (n_samples, n_classes)
    """
    if forest not in _FLAT_FORESTS:  # flattened before: fitted (the check costs as much as walking ~50 rows)
        check_is_fitted(forest)
    if forest.n_outputs_ != 1:
        return forest.predict_proba(X)
    X = np.ascontiguousarray(X, dtype=np.float32)
    if X.ndim != 2 or X.shape[1] != forest.n_features_in_:
        raise ValueError(f"X must be (n, {forest.n_features_in_}) features, got shape {X.shape}")
    if not np.isfinite(X).all():
        raise ValueError("X must be finite")
    if X.shape[0] > _KERNEL_MAX_ROWS:  # tree by tree: scikit-learn's own traversal, as fast on many rows
        return _per_tree_proba(forest, X)
    from ._kernels import forest_proba

    return forest_proba(X, *flat_forest(forest))


def _per_tree_proba(forest, X):
    """A single-output forest's probabilities of finite float32 rows ``X``, one ``tree_.predict`` call per tree."""
    n_classes = int(forest.n_classes_)
    proba = np.zeros((X.shape[0], n_classes))
    for tree in forest.estimators_:
        proba += tree.tree_.predict(X)[:, :n_classes]
    proba /= len(forest.estimators_)
    return proba


#: Rows up to which :func:`forest_predict_proba` walks the trees in one compiled call; beyond,
#: scikit-learn's per-tree calls cost little per row and its traversal is as fast
#: (``scripts/bench fdi``, the default detector: the kernel 1.8-2.3x on the gate's ~70 leftover rows, 1.0-1.2x
#: at 200, 0.8x at 1,600).
_KERNEL_MAX_ROWS = 256

_FLAT_FORESTS: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def flat_forest(forest) -> tuple:
    """A single-output forest's trees as one set of node arrays (for :func:`_kernels.forest_proba`).

    Kept per forest object while it holds the same trees (a refit makes new ones; ``warm_start``
    appends to the same list). Returns ``(roots, nodes, threshold, value)``.
    """
    got = _FLAT_FORESTS.get(forest)
    if got is not None and len(got[0]) == len(forest.estimators_) and all(
            a is b for a, b in zip(got[0], forest.estimators_)):
        return got[1]
    n_classes = int(forest.n_classes_)
    trees = [e.tree_ for e in forest.estimators_]
    roots = np.cumsum([0] + [t.node_count for t in trees[:-1]], dtype=np.int64)
    nodes = np.zeros((int(sum(t.node_count for t in trees)), 4), np.int32)
    for t, r in zip(trees, roots):
        leaf = t.children_left < 0
        rows = nodes[r:r + t.node_count]
        rows[:, 0] = np.where(leaf, -1, t.children_left + r)
        rows[:, 1] = np.where(leaf, -1, t.children_right + r)
        rows[:, 2] = np.where(leaf, 0, t.feature)
    flat = (roots, nodes, np.concatenate([t.threshold for t in trees]).astype(np.float64),
            np.ascontiguousarray(np.concatenate([t.value[:, 0, :n_classes] for t in trees]), dtype=np.float64))
    _FLAT_FORESTS[forest] = (tuple(forest.estimators_), flat)
    return flat


def pipeline_predict_proba(pipeline, traces):
    """``pipeline.predict_proba``, with :func:`forest_predict_proba` for a forest or a final forest step.

    Parameters
    ----------
    pipeline : fitted classifier or Pipeline with ``predict_proba``
    traces : ndarray, shape (n, n_features)
        Raw traces, V (or feature rows for a bare classifier).

    Returns
    -------
    ndarray of float64, shape (n, n_classes)
        Bit-identical to ``pipeline.predict_proba(traces)``.
    """
    if type(pipeline) is RandomForestClassifier and pipeline.n_outputs_ == 1:  # a bare forest on features
        return forest_predict_proba(pipeline, traces)
    clf = pipeline[-1] if isinstance(pipeline, Pipeline) else None
    if type(clf) is RandomForestClassifier and len(pipeline) > 1 and clf.n_outputs_ == 1:
        return forest_predict_proba(clf, pipeline[:-1].transform(traces))
    return pipeline.predict_proba(traces)


def fault_probability(pipeline, traces) -> tuple:
    """Class probabilities and P(faulty) of a fitted FI pipeline.

    Returns
    -------
    proba : ndarray, shape (n, n_classes)
        ``pipeline.predict_proba(traces)`` (bit-identical; a final Random Forest step
        is evaluated by :func:`forest_predict_proba`), columns in ``pipeline.classes_`` order.
    p_faulty : ndarray, shape (n,)
        1 minus the probability of the two healthy classes.
    """
    proba = pipeline_predict_proba(pipeline, traces)
    healthy = healthy_mask(pipeline.classes_)
    return proba, 1.0 - proba[:, healthy].sum(axis=1)


def classify(pipeline, traces, *, fd_threshold: float = 0.5):
    """Label traces with a fitted FI pipeline and a fault-detection threshold.

    A trace is faulty when ``P(faulty) >= fd_threshold``; a faulty trace gets
    the most probable *fault* class even where a healthy class has the single
    largest probability (the false-negative-averse operating point), and a
    healthy one the more probable healthy class.

    Parameters
    ----------
    pipeline : fitted Pipeline with ``predict_proba`` and ``classes_`` (FaultClass values)
    traces : ndarray, shape (n, n_samples)
    fd_threshold : float in (0, 1]

    Returns
    -------
    labels : ndarray of str, shape (n,)
    confidence : ndarray, shape (n,)
        Probability of the returned class.
    p_faulty : ndarray, shape (n,)
    """
    _check_threshold(fd_threshold)
    classes = np.asarray(pipeline.classes_, dtype=object)
    proba, p_faulty = fault_probability(pipeline, traces)
    idx, confidence = decide_classes(classes, proba, p_faulty, fd_threshold)
    return classes[idx].astype(str), confidence, p_faulty


def finite_rows_proba(pipeline, X, *, return_features=False, checked=False, features=None):
    """Class probabilities of the rows of ``X`` whose features are finite in float32.

    The first feature step runs on every row; the steps between it and the final
    estimator (knn's scaler) and the final estimator (what scikit-learn's trees take as
    float32) see only the rows whose features are finite in float32 at their input, so an
    overflowing row costs itself alone (a row finite only after the scaler is not valid
    either). Overflow is expected here and detected, so numpy's floating-point warnings are
    silenced. Per row, the probabilities are bit-identical to ``pipeline.predict_proba``.

    With ``return_features=True`` also the feature rows the final estimator saw
    (for the open-set layer of :class:`inkdiag_core.FaultDetector`). ``checked=True``:
    ``X`` is a finite float32/float64 ndarray of the pipeline's input width, validated by
    the caller; a feature step of inkdiag's own then skips scikit-learn's input checks
    (the same features: they cost about as much as the KPIs of a few traces). ``features``: for a
    Pipeline of more than one step, the feature rows of ``X`` computed by the caller (``X`` itself is
    then not used); ignored for a bare estimator.

    Returns
    -------
    ok : ndarray of bool, shape (n,)
    proba : ndarray of float64, shape (ok.sum(), n_classes)
    features : ndarray, shape (n, n_features), only with ``return_features``
        Every row's features (``X`` itself for a bare estimator).
    """
    with np.errstate(over="ignore", invalid="ignore", divide="ignore", under="ignore"):
        if isinstance(pipeline, Pipeline) and len(pipeline) > 1:
            fast = getattr(pipeline[0], "_transform_checked", None) if checked and len(pipeline) == 2 else None
            if features is not None:
                feats = features
            elif fast is not None:
                feats = fast(X)
            else:
                feats = pipeline[0].transform(X)
                if len(pipeline) > 2:  # e.g. a scaler, which refuses non-finite rows: given the finite ones
                    feats = _finite_rows_through(pipeline[1:-1], feats)
            ok = np.isfinite(np.asarray(feats, dtype=np.float32)).all(axis=1)
            final, rows = pipeline[-1], feats if ok.all() else feats[ok]
        else:
            feats = X
            ok, final, rows = np.ones(X.shape[0], dtype=bool), pipeline, X
        proba = pipeline_predict_proba(final, rows) if ok.any() else np.empty((0, len(final.classes_)))
    return (ok, proba, feats) if return_features else (ok, proba)


def _finite_rows_through(steps, feats):
    """``steps.transform`` of the rows of ``feats`` that are finite in float32, NaN rows for the others (their
    width the finite rows' output width, or ``feats``' where none is finite): a row whose features overflow
    costs itself, not the batch, in a step that refuses non-finite input (scikit-learn's ``StandardScaler``)."""
    feats = np.asarray(feats)
    ok = np.isfinite(feats.astype(np.float32)).all(axis=1)
    if ok.all():
        return steps.transform(feats)
    out = steps.transform(feats[ok]) if ok.any() else np.empty((0, feats.shape[1]))
    full = np.full((feats.shape[0], out.shape[1]), np.nan, dtype=np.result_type(out.dtype, np.float32))
    full[ok] = out
    return full


def classify_finite(pipeline, traces, *, fd_threshold: float = 0.5):
    """:func:`classify` of the rows whose features are finite; the others are not classified.

    What the labelling path calls: a row whose features overflow (a sample of ~1e30 V
    squares beyond any float) is left out, not its frame (:func:`finite_rows_proba`).

    Returns
    -------
    labels : ndarray of str (object), shape (n,)
        ``""`` where not classified.
    confidence : ndarray of float, shape (n,)
        NaN where not classified.
    ok : ndarray of bool, shape (n,)
        The rows classified.
    """
    _check_threshold(fd_threshold)
    n = np.shape(traces)[0]
    labels, conf = np.full(n, "", dtype=object), np.full(n, np.nan)
    ok, proba = finite_rows_proba(pipeline, traces)
    if ok.any():
        classes = np.asarray(pipeline.classes_, dtype=object)
        p_faulty = 1.0 - proba[:, healthy_mask(classes)].sum(axis=1)
        idx, conf[ok] = decide_classes(classes, proba, p_faulty, fd_threshold)
        labels[ok] = classes[idx].astype(str).astype(object)
    return labels, conf, ok


def _check_threshold(fd_threshold) -> float:
    """``fd_threshold`` as a float after checking it is in (0, 1]."""
    if not 0.0 < fd_threshold <= 1.0:
        raise ValueError(f"fd_threshold must be in (0, 1], got {fd_threshold!r}")
    return float(fd_threshold)


def decide_classes(classes, proba, p_faulty, fd_threshold, *, healthy=None):
    """Each row's class at ``fd_threshold`` (checked before), as a column index and its probability.

    A row is faulty when ``p_faulty >= fd_threshold`` and then gets its most probable
    fault class, else its more probable healthy class (:func:`classify`).

    Parameters
    ----------
    classes : array_like, shape (n_classes,)
        Class values (``FaultClass`` values) in the columns' order.
    proba : ndarray of float, shape (n, n_classes)
    p_faulty : ndarray of float, shape (n,)
    fd_threshold : float in (0, 1]
    healthy : ndarray of bool, shape (n_classes,), optional
        ``healthy_mask(classes)``, if the caller has it already.

    Returns
    -------
    idx : ndarray of int, shape (n,)
    confidence : ndarray of float, shape (n,)
    """
    if healthy is None:
        healthy = healthy_mask(np.asarray(classes, dtype=object))
    faulty = p_faulty >= fd_threshold
    masked = np.where(healthy[None, :] == faulty[:, None], -1.0, proba)  # keep the allowed group
    idx = np.argmax(masked, axis=1)
    return idx, proba[np.arange(len(idx)), idx]


def threshold_and_scores(pipeline, Xval, yval, fnr_target):
    """Fault-detection threshold for ``fnr_target`` on a validation split, and that split's scores.

    Returns
    -------
    threshold : float
        :func:`fnr_threshold` of the validation faults' P(faulty).
    scores : dict
        ``validation_fi_accuracy`` (at threshold 0.5), ``validation_fi_accuracy_at_threshold``,
        ``validation_fd_fnr``, ``validation_fd_fpr`` (fractions; NaN where the split has no
        faults resp. no healthy rows) and ``n_validation``.
    """
    yval = np.asarray(yval)
    classes = np.asarray(pipeline.classes_, dtype=object)
    proba, p_faulty = fault_probability(pipeline, Xval)
    is_fault = fd_labels(yval) == 1
    threshold = fnr_threshold(p_faulty[is_fault], fnr_target)
    idx0, _ = decide_classes(classes, proba, p_faulty, 0.5)
    idx, _ = decide_classes(classes, proba, p_faulty, threshold)
    flagged = ~healthy_mask(classes[idx])

    def mean(a):
        return float(np.mean(a)) if a.size else float("nan")

    scores = {
        "validation_fi_accuracy": mean(classes[idx0] == yval),
        "validation_fi_accuracy_at_threshold": mean(classes[idx] == yval),
        "validation_fd_fnr": mean(~flagged[is_fault]),
        "validation_fd_fpr": mean(flagged[~is_fault]),
        "n_validation": int(len(yval)),
    }
    return threshold, scores


def fnr_threshold(p_faulty_of_faults, fnr_target: float = 0.005) -> float:
    """Largest threshold on P(faulty) that misses at most ``fnr_target`` of the given faults."""
    p = np.sort(np.asarray(p_faulty_of_faults, float))
    if p.size == 0:
        return 0.5
    k = int(np.floor(fnr_target * p.size))
    return float(min(p[k], 0.5))


def train_default_model(path, *, n_per_class: int = 400, seed: int = 0, kind: str = "rf",
                        features: str = "kpi_y", n_estimators: int = 50, min_samples_leaf: int = 3,
                        max_features=None, fnr_target: float = 0.005, baseline: bool = False,
                        unknown_rate: float | None = 0.01, progress=None):
    """Train the FDI model the nodes load by default, and save it with its manifest.

    The default is a Random Forest on KPI_Y: on its validation split it isolates
    faults as well as the rich feature set (95.92 +- 0.45 % vs 95.42 +- 0.48 % FI
    accuracy, seeds 0-2, 400 traces per class, no open-set layer; ``reports/fdi.md``
    finds the same within one standard deviation over 5 seeds) at about 6x its
    throughput (``scripts/bench fdi``). 50 trees with at least 3 traces per leaf and
    every KPI at each split classify as well as scikit-learn's 100 fully grown trees
    of 2 KPIs per split (95.72 +- 0.28 %; 95.69 +- 0.57 % with 50 such trees, same
    seeds; 2026-11-26) in half the time; the forest is about half of the node's
    labelling time.

    Simulates ``n_per_class`` traces of each of the 12 classes and fits a
    :class:`inkdiag_core.FaultDetector` (``random_state=seed``: 75% fit the
    pipeline, the other 25% give the false-negative-averse fault-detection
    threshold, FNR <= ``fnr_target``, and the scores); with ``baseline=True``
    also its per-nozzle baseline branch, each trace with its nozzle's healthy
    baseline (:func:`inkdiag_core.baselines.baseline_training_kpis`). Saves it with
    :func:`inkdiag_core.save_detector` (the manifest's ``config`` adds
    ``n_per_class`` and ``seed``).

    ``features="kpi_y+baseline"`` is the previous route, kept until the fdi node
    loads detectors: a plain ``"kpi_y+baseline"`` pipeline on
    :func:`inkdiag_core.baselines.baseline_training_rows`, saved with
    :func:`inkdiag_core.save_model` and its threshold in ``config['fd_threshold']``
    (the same forest and threshold as a detector's baseline branch of the same seed).

    Parameters
    ----------
    path : str or Path
        Destination ``.joblib``.
    baseline : bool
        Fit the baseline branch too.
    unknown_rate : float or None
        The open-set layer's bound on the false-unknown rate of known traces
        (:class:`inkdiag_core.FaultDetector`, default 0.01); None or 0: no layer.
    progress : callable(step: int, total: int, message: str), optional
        Called after each stage (for a progress bar).

    Returns
    -------
    pathlib.Path
        The manifest written beside the model.
    """
    from .faults import FaultClass
    from .persistence import save_detector
    from .simulation.linear import simulate

    report = progress or (lambda step, total, message: None)
    total = 4
    sim = simulate({c: int(n_per_class) for c in FaultClass}, seed=seed)
    report(1, total, f"simulated {len(sim)} traces")
    y = sim.label_values()
    data = {"n_per_class": int(n_per_class), "seed": int(seed)}
    if features == "kpi_y+baseline":
        return _train_baseline_pipeline(path, sim, y, data, kind=kind, n_estimators=n_estimators,
                                        min_samples_leaf=min_samples_leaf, max_features=max_features,
                                        fnr_target=fnr_target, report=report)
    from .baselines import baseline_training_kpis
    from .detector import FaultDetector

    det = FaultDetector(kind=kind, features=features, sample_rate_hz=float(sim.sample_rate_hz),
                        n_estimators=int(n_estimators), min_samples_leaf=int(min_samples_leaf),
                        max_features=max_features, fnr_target=float(fnr_target), unknown_rate=unknown_rate,
                        random_state=int(seed))
    det.fit(sim.traces, y, baseline_kpis=baseline_training_kpis(sim, seed) if baseline else None)
    report(2, total, f"fitted {kind} on {features} features" + (" and baselines" if baseline else ""))
    report(3, total, f"validation FI accuracy {100 * det.scores_['validation_fi_accuracy']:.1f}%")
    manifest = save_detector(det, path, config=data)
    report(4, total, f"saved {path}")
    return manifest


def _train_baseline_pipeline(path, sim, y, data, *, kind, n_estimators, min_samples_leaf, max_features, fnr_target,
                             report):
    """The previous ``"kpi_y+baseline"`` route of :func:`train_default_model` (a plain pipeline file)."""
    from sklearn.model_selection import train_test_split

    from .baselines import baseline_training_rows
    from .persistence import save_model

    seed = data["seed"]
    X = baseline_training_rows(sim, seed)
    Xtr, Xval, ytr, yval = train_test_split(X, y, test_size=0.25, random_state=seed, stratify=y)
    pipe = make_fdi_pipeline(kind, "kpi_y+baseline", random_state=seed, n_estimators=n_estimators,
                             min_samples_leaf=min_samples_leaf, max_features=max_features).fit(Xtr, ytr)
    report(2, 4, f"fitted {kind} on kpi_y+baseline features")
    threshold, scores = threshold_and_scores(pipe, Xval, yval, fnr_target)
    report(3, 4, f"validation FI accuracy {100 * scores['validation_fi_accuracy']:.1f}%")
    config = {"kind": kind, "features": "kpi_y+baseline", **data,
              "n_estimators": int(n_estimators), "min_samples_leaf": int(min_samples_leaf),
              "max_features": max_features,
              "sample_rate_hz": float(sim.sample_rate_hz), "n_samples": int(sim.traces.shape[1]),
              "fd_threshold": threshold, "fnr_target": float(fnr_target),
              "classes": [str(c) for c in pipe.classes_]}
    manifest = save_model(pipe, path, config=config, scores=scores)
    report(4, 4, f"saved {path}")
    return manifest
