"""Small helpers shared by the experiment modules: CSV writing and a headless matplotlib."""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

__all__ = ["plt", "save_fig", "write_csv"]


def write_csv(path: Path, rows: list[dict[str, Any]]) -> Path:
    """Write dict rows (keys of the first row are the header; floats with repr precision)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as f:
        if not rows:
            return path
        w = csv.DictWriter(f, fieldnames=list(rows[0].keys()))
        w.writeheader()
        for r in rows:
            w.writerow(r)
    return path


def save_fig(fig: Any, path: Path) -> Path:
    """Save a figure as PNG (120 dpi) and close it."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120, bbox_inches="tight")
    plt.close(fig)
    return path
