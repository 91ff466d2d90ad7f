"""Repeated ``gsrmr-demo`` runs: the node suite's acceptance figures as a table with medians.

Usage: ``.venv/bin/python bench/acceptance/demo.py [--runs 6] [--seeds BASE] [--method M] [--load N]
[-- DEMO_ARGS...]``.
Each run is a full round 2 over DDS (~40 s with the model cached; the first run trains it). Prints, per
run and as the median: slots on time (MR image ≤ τ after the slot start), images sent, uplink energy ratio
upload-all / ours, the upload-all energy itself (equal across runs with one ``--channel-seed``), mean MR
loss, PSNR and SSIM measured on the MR images the server produced, the regret against the hindsight
optimum (computed after each run) with the images that optimum sends, slot latency p50/p95/p99 (MR image
published − slot start, scored slots), the scheduler's plan time (median and worst over its replans) and
the server's median compose time per stage, and what the nodes' input checks refused (``docs/security.md``,
"Application checks"; each deployment node logs an ``input checks: {JSON}`` line when it exits): messages from
unlisted writers, implausible inputs and writer alarms, summed over the nodes — a clean run counts none.

``--seeds BASE`` gives run k the channel seed BASE + k (else ``-- --channel-seed N`` for all);
``--method M`` runs the scheduler with method M; ``--load N`` keeps N busy processes
(``python -c "while True: pass"``, normal priority) running during the runs.
"""

from __future__ import annotations

import argparse
import json
import signal
import statistics
import subprocess
import sys

from gsrmr_sim.demo_runs import run_once
from gsrmr_sim.machine_probe import machine_line

COLUMNS = ("slots", "slots_on_time", "slots_scored", "images_sent", "energy_ratio_vs_upload_all", "energy_upload_all_j",
           "mean_loss", "psnr_db", "psnr_slot_mean_db", "ssim", "regret", "hindsight_images", "latency_ms_p50",
           "latency_ms_p95", "latency_ms_p99", "plan_ms_p50", "plan_ms_max", "replans_late", "writers_refused",
           "implausible", "writer_alarms")
# with gsrmr-demo --hosts 2: what crossed the rate-limited uplink (veth counters) and the limiter's drops
LINK_COLUMNS = ("link_uplink_mbit_mean", "link_uplink_bytes", "link_uplink_dropped_packets")


def _exit_on_sigterm(signum: int, _frame: object) -> None:
    raise SystemExit(128 + signum)


def main() -> int:
    signal.signal(signal.SIGTERM, _exit_on_sigterm)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=6)
    ap.add_argument("--seeds", type=int, default=None, metavar="BASE",
                    help="run k uses --channel-seed BASE + k (default: every run the demo's seed)")
    ap.add_argument("--method", default=None, help="scheduling method (gsrmr-demo --method)")
    ap.add_argument("--load", type=int, default=0, metavar="N", help="N busy processes during the runs")
    ap.add_argument("demo_args", nargs="*", help="passed to gsrmr-demo (after --)")
    args = ap.parse_args()
    if args.method:
        args.demo_args += ["--method", args.method]
    print(f"# bench/acceptance/demo.py: {args.runs} × gsrmr-demo {' '.join(args.demo_args)} (before the runs: "
          f"{machine_line()} (gsrmr_sim.machine_probe); {args.load} busy process(es) during the runs)", flush=True)
    busy = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(args.load)]
    try:
        return _runs(args)
    finally:
        for proc in busy:
            proc.kill()
            proc.wait()


def _runs(args: argparse.Namespace) -> int:
    global COLUMNS
    if "--hosts" in args.demo_args:
        COLUMNS = COLUMNS + LINK_COLUMNS
    print("| run | " + " | ".join(COLUMNS) + " | wall s |")
    print("|" + "---|" * (len(COLUMNS) + 2))
    rows = []
    for k in range(args.runs):
        seed = [] if args.seeds is None else ["--channel-seed", str(args.seeds + k)]
        s = run_once([*args.demo_args, *seed])
        for c in COLUMNS:  # a run without a figure (e.g. no feasible hindsight optimum: no hindsight_images)
            s.setdefault(c, float("nan"))
        rows.append(s)
        print(f"| {k + 1} | " + " | ".join(f"{s[c]:.4g}" if isinstance(s[c], float) else str(s[c])
                                         for c in COLUMNS) + f" | {s['wall_s']:.0f} |", flush=True)
        print(f"|   | compose ms p50 by stage: {json.dumps(s['compose_ms_p50'])} |", flush=True)
        if s.get("input_checks"):
            print(f"|   | input checks counted: {json.dumps(s['input_checks'])} |", flush=True)
    lower_is_better = ("images_sent", "mean_loss", "regret", "latency_ms_p50", "latency_ms_p95", "latency_ms_p99",
                       "plan_ms_p50", "plan_ms_max", "writers_refused", "implausible", "writer_alarms", *LINK_COLUMNS)

    def summary_cell(c: str, pick) -> str:
        if c == "replans_late":  # all runs together: late / all replans
            late = [tuple(map(int, r[c].split("/"))) for r in rows if "/" in str(r[c])]
            return f"{sum(a for a, _ in late)}/{sum(b for _, b in late)}" if late else "n/a"
        if c in ("writers_refused", "implausible", "writer_alarms"):  # all runs together
            return str(sum(r[c] for r in rows)) if all(r[c] >= 0 for r in rows) else "n/a"
        return f"{pick(r[c] for r in rows):.4g}"

    print("| **median** | " + " | ".join(summary_cell(c, statistics.median) for c in COLUMNS)
          + f" | {statistics.median(r['wall_s'] for r in rows):.0f} |")
    print("| **worst** | " + " | ".join(summary_cell(c, max if c in lower_is_better else min) for c in COLUMNS)
          + " | |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
