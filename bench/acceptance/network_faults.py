"""Network faults on the two-host link: ``gsrmr-demo --hosts 2`` under a rate limit, a link outage and a rate cut.

Usage: ``.venv/bin/python bench/acceptance/network_faults.py [--runs 1] [--cases NAME ...] [-- DEMO_ARGS...]`` (root).
Each case is one full round 2 (288 slots, ~45 s with the model cached) with the robot's processes and the
server's in two network namespaces (``gsrmr_sim.netns.TwoHosts``), DDS over UDPv4 across a veth pair limited
by ``tbf``. Cases (``--link-events`` slots count composed round slots):

* ``5mbit`` — the default uplink, 5 Mbit/s;
* ``2mbit`` — 2 Mbit/s (a 7–9 kB JPEG takes 29–36 ms);
* ``down2s`` — 5 Mbit/s, the link down from round slot 100 to 120 (2 s) and back;
* ``cut`` — 5 Mbit/s, cut to 0.5 Mbit/s at round slot 100 (below one image per slot once the keys, ledger
  rows, cmd_vel and DDS's own traffic are counted) for the rest of the round;
* ``cut-nohold`` — the same cut with the robot's hold-back off (``hold_images_while_queued`` false): images
  go into the queue whenever the schedule asks.

Prints per case (median and worst over ``--runs``): slots on time, images sent (the robot's ledger) and
composed, images held back, missing keys and images, late arrivals (the server's counter, whole run), packets
the rate limiter dropped (its queue overflowed), mean MR loss, energy below upload-all, the uplink's mean
Mbit/s, and for the outage the seconds from link-up to the first composed image. The machine's load average is printed
first; figures from a loaded machine say so.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
import statistics
import subprocess
import sys
import tempfile
import time

CASES = {
    "5mbit": ["--uplink-mbit", "5"],
    "2mbit": ["--uplink-mbit", "2"],
    "down2s": ["--uplink-mbit", "5", "--link-events", "down@100,up@120"],
    "cut": ["--uplink-mbit", "5", "--link-events", "rate=0.5@100"],
    "cut-nohold": ["--uplink-mbit", "5", "--link-events", "rate=0.5@100",
                   "--param", "gsrmr_robot:hold_images_while_queued=false"],
}
COLUMNS = ("slots_on_time", "images_sent", "images_composed", "held_back", "missing_key", "missing_image", "late",
           "link_uplink_dropped_packets", "mean_loss", "energy_ratio_vs_upload_all", "link_uplink_mbit_mean",
           "images_back_after_s")


def _run(case: str, extra: list[str]) -> dict:
    out = Path(tempfile.mkdtemp(prefix=f"gsrmr-net-{case}-"))
    exe = Path(sys.executable).parent / "gsrmr-demo"
    proc = subprocess.run([str(exe), "--hosts", "2", *CASES[case], "--out", str(out), *extra],
                          stdout=subprocess.PIPE, text=True)
    if proc.returncode:
        raise SystemExit(f"{case}: gsrmr-demo exited {proc.returncode}")
    summary = json.loads(proc.stdout.strip().splitlines()[-1])
    return {**summary, **_slot_figures(out, summary)}


def _slot_figures(out: Path, summary: dict) -> dict:
    from gsrmr_server.recording import read_slots_csv

    rows = [r for r in read_slots_csv(out / "slots.csv") if r.get("scored")]
    faults = [f for r in rows for f in (r["faults"] or "").split(";") if f]
    fig = {"images_composed": sum(r["source"] == "image" for r in rows),
           # what the robot's ledger says it sent as images (rows whose ledger row reached the server)
           "images_sent": sum(1 for r in rows if r["x"] == 1 and (r["bytes_sent"] or 0) > 24),
           "missing_key": faults.count("missing_key"), "missing_image": faults.count("missing_image"),
           # uploads that came after their slot was composed (the server's counter, whole run)
           "late": _server_faults(out).get("late", 0), "held_back": sum(r["held_back"] or 0 for r in rows),
           "images_back_after_s": float("nan")}
    ups = [e for e in summary.get("link_events", []) if e["action"] == "up"]
    if ups:
        t_up = ups[0]["wall_s"]
        first = next((r for r in rows if r["stamp_s"] >= t_up and r["source"] == "image"), None)
        fig["images_back_after_s"] = first["stamp_s"] - t_up if first else float("inf")
    return fig


def _server_faults(out: Path) -> dict:
    path = out / "recording" / "server_summary.json"
    return json.loads(path.read_text()).get("faults", {}) if path.exists() else {}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=1)
    ap.add_argument("--cases", nargs="*", default=list(CASES), choices=list(CASES))
    ap.add_argument("demo_args", nargs="*", help="passed to gsrmr-demo (after --)")
    args = ap.parse_args()
    print(f"# bench/acceptance/network_faults.py: {args.runs} run(s) per case, gsrmr-demo --hosts 2 "
          f"{' '.join(args.demo_args)} ({os.cpu_count()} CPUs, load average before {os.getloadavg()[0]:.1f}, "
          f"{time.strftime('%Y-%m-%d %H:%M')})")
    print("| case | stat | " + " | ".join(COLUMNS) + " |")
    print("|" + "---|" * (len(COLUMNS) + 2))
    lower_is_better = {"missing_key", "missing_image", "late", "held_back", "mean_loss", "images_back_after_s",
                       "link_uplink_dropped_packets"}
    for case in args.cases:
        runs = [_run(case, args.demo_args) for _ in range(args.runs)]
        for label, pick in (("median", statistics.median), ("worst", None)):
            if label == "worst" and len(runs) == 1:
                continue
            cells = []
            for c in COLUMNS:
                values = [r[c] for r in runs]
                v = pick(values) if pick else (max(values) if c in lower_is_better else min(values))
                cells.append(f"{v:.4g}" if isinstance(v, float) else str(v))
            print(f"| {case} | {label} | " + " | ".join(cells) + " |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
