"""inkdiag_core: the pure-Python numerical core of inkdiag.

Ink-channel model, fault simulator, KPIs, residual filters, classifiers and
fault estimators. numpy, scipy, scikit-learn and joblib only: this package
never imports rclpy or any message package (a test checks it).
"""

__version__ = "0.1.0"

__all__ = ["__version__"]
