"""Small helpers shared by the report scripts (markdown tables, output paths, seeds)."""

from __future__ import annotations

import os
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
REPORTS = ROOT / "reports"


def out_path(name: str) -> Path:
    """Path of a report artefact under ``reports/`` (created if needed)."""
    REPORTS.mkdir(exist_ok=True)
    return REPORTS / name


def md_table(header, rows) -> str:
    """A GitHub-markdown table from a header row and rows of already formatted cells."""
    lines = ["| " + " | ".join(str(h) for h in header) + " |",
             "|" + "|".join(" --- " for _ in header) + "|"]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def pm(values, scale=1.0, digits=2) -> str:
    """``mean +- std`` of a sequence, formatted."""
    import numpy as np

    v = np.asarray(values, float) * scale
    if v.size == 1:
        return f"{v[0]:.{digits}f}"
    return f"{v.mean():.{digits}f} ± {v.std(ddof=1):.{digits}f}"


def matplotlib_pyplot():
    """pyplot on the non-interactive Agg backend (reports run headless)."""
    os.environ.setdefault("MPLBACKEND", "Agg")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt
