"""Where a run's regret comes from, after the run: image placement against the budget left unspent.

Usage: ``.venv/bin/python bench/regret_split.py REPORT_DIR... [--loss-threshold 0.03] [--per-run]``.

Each REPORT_DIR is a ``gsrmr-demo`` report (its ``slots.csv`` with the hindsight columns). Over the scored slots
with every hindsight value, the run's regret (its energy over the hindsight optimum's at L_th, the demo's
``regret``) is the product of two factors (:func:`gsrmr_sim.hindsight.regret_split`, hindsight: an evaluation,
never available live):

* ``placement``: the run's energy over the hindsight optimum's at the run's *own* mean loss — how well it placed
  its images for the loss it ended with;
* ``unspent``: the optimum at the run's own loss over the optimum at L_th — what ending the round below L_th cost.

The table gives each factor's median and worst over the runs (``--per-run``: every run), with the run's mean
loss, its images and the optimum's images at the run's loss.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
import statistics
import sys

import numpy as np

from gsrmr_server.recording import read_slots_csv
from gsrmr_sim.hindsight import HINDSIGHT_COLUMNS, RegretSplit, regret_split


def split_of(report: Path, loss_threshold: float) -> RegretSplit:
    """The regret split of one report's scored slots that carry every hindsight value."""
    needed = ("energy_j", *HINDSIGHT_COLUMNS)
    rows = [r for r in read_slots_csv(report / "slots.csv")
            if r.get("scored") and all(r.get(c) is not None for c in needed)]
    if not rows:
        raise SystemExit(f"regret_split: {report} has no scored slot with the hindsight columns")
    cols = [np.array([r[c] for r in rows], float) for c in ("x", "energy_j", *HINDSIGHT_COLUMNS)]
    return regret_split(*cols, loss_threshold)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("reports", nargs="+", type=Path)
    ap.add_argument("--loss-threshold", type=float, default=None,
                    help="L_th (default: each report's summary.json loss_threshold, else 0.03)")
    ap.add_argument("--per-run", action="store_true")
    args = ap.parse_args()
    print(f"# bench/regret_split.py: {len(args.reports)} reports ({os.cpu_count()} CPUs, load average "
          f"{os.getloadavg()[0]:.1f}); HINDSIGHT: computed after the runs")
    print("| run | channel seed | regret | placement | unspent | mean loss | images | optimum's images at that loss |")
    print("|---|---|---|---|---|---|---|---|")
    splits = []
    for report in args.reports:
        summary_path = report / "summary.json"
        summary = json.loads(summary_path.read_text()) if summary_path.exists() else {}
        lth = args.loss_threshold if args.loss_threshold is not None else float(summary.get("loss_threshold", 0.03))
        s = split_of(report, lth)
        splits.append(s)
        if args.per_run:
            print(f"| {report.name} | {summary.get('channel_seed', '')} | {s.regret:.3f} | {s.placement:.3f} | "
                  f"{s.unspent:.3f} | {s.mean_loss:.4f} | {s.images} | {s.images_at_own_loss} |")

    def mw(values: list[float], worst=max) -> str:
        return f"{statistics.median(values):.3f} ({worst(values):.3f})"

    print(f"| **median (worst)** of {len(splits)} | | {mw([s.regret for s in splits])} | "
          f"{mw([s.placement for s in splits])} | {mw([s.unspent for s in splits])} | "
          f"{statistics.median(s.mean_loss for s in splits):.4f} ({max(s.mean_loss for s in splits):.4f}) | "
          f"{statistics.median(s.images for s in splits):.0f} | "
          f"{statistics.median(s.images_at_own_loss for s in splits):.0f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
