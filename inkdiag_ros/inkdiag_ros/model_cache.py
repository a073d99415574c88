"""``python -m inkdiag_ros.model_cache``: verify the default FDI model, or train it.

The logic is the core's (:mod:`inkdiag_core.model_cache`); this is its command-line
entry point in the ROS package, kept for the scripts and docs that run it.

    python -m inkdiag_ros.model_cache [models/fdi_default.joblib]
"""

from __future__ import annotations

import sys

from inkdiag_core.model_cache import (  # noqa: F401
    DEFAULT_FEATURES,
    DEFAULT_MODEL,
    DEFAULT_SETTINGS,
    default_config,
    ensure_default_model,
    train_default_model,
)
from inkdiag_core.model_cache import main as _core_main


def main(argv=None) -> int:
    """Verify or train each model file in ``argv`` (default: the default model); exit status 0."""
    return _core_main(argv, prog="python -m inkdiag_ros.model_cache")


if __name__ == "__main__":
    sys.exit(main())
