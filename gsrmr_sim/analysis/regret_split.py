"""gsrmr-regret-split: where each run's regret comes from, after the run (hindsight): image placement × budget left
unspent, over gsrmr-demo reports. How to read it: docs/scheduling.md, "Reading recorded runs: the analysis tools"."""

from __future__ import annotations

import argparse
import itertools
import json
import os
from pathlib import Path
import statistics

import numpy as np

from gsrmr_server.recording import read_slots_csv
from gsrmr_sim.hindsight import HINDSIGHT_COLUMNS, RegretSplit, regret_split

PROG = "gsrmr-regret-split"


def split_of(report: Path, loss_threshold: float) -> RegretSplit:
    """The regret split of one report's scored slots that carry every hindsight value."""
    needed = ("energy_j", *HINDSIGHT_COLUMNS)
    rows = [r for r in read_slots_csv(report / "slots.csv")
            if r.get("scored") and all(r.get(c) is not None for c in needed)]
    if not rows:
        raise SystemExit(f"regret_split: {report} has no scored slot with the hindsight columns")
    cols = [np.array([r[c] for r in rows], float) for c in ("x", "energy_j", *HINDSIGHT_COLUMNS)]
    return regret_split(*cols, loss_threshold)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog=PROG, description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("reports", nargs="+", type=Path, metavar="REPORT_DIR",
                    help="gsrmr-demo report folders (reports/demo-*)")
    ap.add_argument("--loss-threshold", type=float, default=None,
                    help="L_th (default: each report's summary.json loss_threshold, else 0.03)")
    ap.add_argument("--per-run", action="store_true")
    ap.add_argument("--batch-bar", type=float, default=None,
                    help="also: the share of one-run-per-channel-seed batches whose median regret is <= this")
    args = ap.parse_args(argv)
    print(f"# gsrmr-regret-split: {len(args.reports)} reports ({os.cpu_count()} CPUs, load average "
          f"{os.getloadavg()[0]:.1f}); HINDSIGHT: computed after the runs")
    print("| run | channel seed | regret | placement | unspent | mean loss | images | optimum's images at that loss |")
    print("|---|---|---|---|---|---|---|---|")
    splits = []
    by_seed: dict[object, list[float]] = {}
    for report in args.reports:
        summary_path = report / "summary.json"
        summary = json.loads(summary_path.read_text()) if summary_path.exists() else {}
        lth = args.loss_threshold if args.loss_threshold is not None else float(summary.get("loss_threshold", 0.03))
        s = split_of(report, lth)
        splits.append(s)
        by_seed.setdefault(summary.get("channel_seed"), []).append(s.regret)
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
    if args.batch_bar is not None:
        print(batch_pass_line(by_seed, args.batch_bar))
    return 0


def batch_pass_line(by_seed: dict[object, list[float]], bar: float) -> str:
    """How many batches of one run per channel seed (every combination of the runs) have a median regret <= bar."""
    medians = [statistics.median(c) for c in itertools.product(*by_seed.values())]
    seeds = ", ".join(f"{k}: {len(v)}" for k, v in sorted(by_seed.items(), key=lambda kv: str(kv[0])))
    return (f"\nbatches of one run per channel seed (runs per seed {seeds}): {len(medians)}; median regret <= {bar}: "
            f"{sum(m <= bar for m in medians)} ({100 * sum(m <= bar for m in medians) / len(medians):.0f} %); "
            f"the batch medians' median {statistics.median(medians):.3f}, range "
            f"{min(medians):.3f}–{max(medians):.3f}")


if __name__ == "__main__":
    raise SystemExit(main())
