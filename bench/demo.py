"""Repeated ``gsrmr-demo`` runs: the node suite's acceptance figures as a table with medians.

Usage: ``.venv/bin/python bench/demo.py [--runs 6] [-- DEMO_ARGS...]``. Each run is a full round 2 over
DDS (~40 s with the model cached; the first run trains it). Prints, per run and as the median: slots
on time (MR image ≤ τ after the slot start), images sent, uplink energy ratio upload-all / ours, the
upload-all energy itself (equal across runs with one ``--channel-seed``), mean MR loss, PSNR and SSIM
measured on the MR images the server produced, and the regret against the hindsight optimum (computed
after each run) with the images that optimum sends. Pass ``-- --channel-seed N`` to vary the channel, or
``--seeds`` to give run k the seed ``base + k``.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
import signal
import statistics
import subprocess
import sys
import time

COLUMNS = ("slots", "slots_on_time", "images_sent", "energy_ratio_vs_upload_all", "energy_upload_all_j", "mean_loss",
           "psnr_db", "ssim", "regret", "hindsight_images")


def run_once(demo_args: list[str]) -> dict:
    """One ``gsrmr-demo`` run; its summary (the last stdout line) plus the wall time."""
    exe = Path(sys.executable).parent / "gsrmr-demo"
    t0 = time.perf_counter()
    with subprocess.Popen([str(exe), *demo_args], stdout=subprocess.PIPE, text=True) as proc:
        try:
            out, _ = proc.communicate()
        except BaseException:  # Ctrl-C / SIGTERM: let the demo stop its nodes (it handles both)
            proc.terminate()
            proc.wait(timeout=60)
            raise
    if proc.returncode:
        raise subprocess.CalledProcessError(proc.returncode, proc.args)
    summary = json.loads(out.strip().splitlines()[-1])
    summary["wall_s"] = time.perf_counter() - t0
    return summary


def _exit_on_sigterm(signum: int, _frame: object) -> None:
    raise SystemExit(128 + signum)


def main() -> int:
    signal.signal(signal.SIGTERM, _exit_on_sigterm)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=6)
    ap.add_argument("--seeds", type=int, default=None, metavar="BASE",
                    help="run k uses --channel-seed BASE + k (default: every run the demo's seed)")
    ap.add_argument("demo_args", nargs="*", help="passed to gsrmr-demo (after --)")
    args = ap.parse_args()
    print(f"# bench/demo.py: {args.runs} × gsrmr-demo {' '.join(args.demo_args)} ({os.cpu_count()} CPUs, "
          f"load average before {os.getloadavg()[0]:.1f})")
    print("| run | " + " | ".join(COLUMNS) + " | wall s |")
    print("|" + "---|" * (len(COLUMNS) + 2))
    rows = []
    for k in range(args.runs):
        seed = [] if args.seeds is None else ["--channel-seed", str(args.seeds + k)]
        s = run_once([*args.demo_args, *seed])
        rows.append(s)
        print(f"| {k + 1} | " + " | ".join(f"{s[c]:.4g}" if isinstance(s[c], float) else str(s[c])
                                         for c in COLUMNS) + f" | {s['wall_s']:.0f} |", flush=True)
    print("| **median** | " + " | ".join(f"{statistics.median(r[c] for r in rows):.4g}" for c in COLUMNS)
          + f" | {statistics.median(r['wall_s'] for r in rows):.0f} |")
    lower_is_better = ("images_sent", "mean_loss", "regret")
    print("| **worst** | " + " | ".join(
        f"{(max if c in lower_is_better else min)(r[c] for r in rows):.4g}" for c in COLUMNS) + " | |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
