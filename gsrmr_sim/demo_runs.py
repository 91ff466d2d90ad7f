"""One ``gsrmr-demo`` run as a subprocess and the figures read from its report folder: the step the acceptance
benches repeat (``bench/acceptance/demo.py``, ``bench/acceptance/align_demo.py``).

:func:`run_once` runs ``gsrmr-demo`` (next to this interpreter) with the given arguments and returns its summary (the
last stdout line) with the wall time and :func:`run_figures` of its report: slot latency percentiles, the server's
stage medians, the scheduler's plan times and what the nodes' input checks counted (:func:`input_checks`). No ROS.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path
import subprocess
import sys
import time

import numpy as np

CHECKS_PREFIX = "input checks: "  # gsrmr_common.ros_admission.SUMMARY_PREFIX (this module imports no ROS)
EXIT_UNMEASURED = 3  # gsrmr_sim.report.EXIT_UNMEASURED: the run ended but measured too little (its JSON says why)


def input_checks(report_dir: Path) -> dict:
    """What every node's input checks counted (its ``input checks:`` log line at exit), by node, and the totals of
    writers refused, implausible inputs and writer alarms (-1 when no node logged the line)."""
    per_node: dict[str, dict] = {}
    for log in sorted((report_dir / "logs").glob("*.log")):
        for line in log.read_text(errors="replace").splitlines():
            if CHECKS_PREFIX in line:
                per_node[log.stem] = json.loads(line.split(CHECKS_PREFIX, 1)[1])
    if not per_node:
        return {"writers_refused": -1, "implausible": -1, "writer_alarms": -1, "input_checks": {}}
    return {"writers_refused": sum(n for c in per_node.values() for w in c.get("writers_refused", {}).values()
                                   for n in w.values()),
            "implausible": sum(n for c in per_node.values() for n in c.get("implausible", {}).values()),
            "writer_alarms": sum(n for c in per_node.values() for n in c.get("writer_alarms", {}).values()),
            "input_checks": {k: v for k, v in per_node.items()
                             if v.get("writers_refused") or v.get("implausible") or v.get("writer_alarms")}}


def run_figures(report_dir: Path) -> dict:
    """Latency percentiles of the scored slots, the server's stage medians and the scheduler's plan times."""
    out: dict = {}
    with open(report_dir / "slots.csv", newline="") as f:
        lat = [float(r["latency_ms"]) for r in csv.DictReader(f) if r.get("scored") == "1" and r.get("latency_ms")]
    for q in (50, 95, 99):
        out[f"latency_ms_p{q}"] = float(np.percentile(lat, q)) if lat else float("nan")
    server = report_dir / "recording" / "server_summary.json"
    out["compose_ms_p50"] = json.loads(server.read_text()).get("compose_ms_p50", {}) if server.exists() else {}
    plans = report_dir / "scheduler_state" / "plan_stats.json"
    stats = json.loads(plans.read_text()) if plans.exists() else {}
    times, slack = stats.get("solve_time_s", []), stats.get("slack_s", [])
    out["plan_ms_p50"] = 1e3 * float(np.median(times)) if times else float("nan")
    out["plan_ms_max"] = 1e3 * float(np.max(times)) if times else float("nan")
    out["replans_late"] = f"{sum(v < 0 for v in slack)}/{len(slack)}" if slack else "n/a"
    out.update(input_checks(report_dir))
    return out


def run_once(demo_args: list[str]) -> dict:
    """One ``gsrmr-demo`` run; its summary (the last stdout line) plus the wall time and its ``exit_code``: 0, or
    :data:`EXIT_UNMEASURED` (the summary's ``unmeasured`` says why). Any other failure raises."""
    exe = Path(sys.executable).parent / "gsrmr-demo"
    t0 = time.perf_counter()
    with subprocess.Popen([str(exe), *demo_args], stdout=subprocess.PIPE, text=True) as proc:
        try:
            out, _ = proc.communicate()
        except BaseException:  # Ctrl-C / SIGTERM: let the demo stop its nodes (it handles both)
            proc.terminate()
            proc.wait(timeout=60)
            raise
    if proc.returncode not in (0, EXIT_UNMEASURED):
        raise subprocess.CalledProcessError(proc.returncode, proc.args)
    summary = json.loads(out.strip().splitlines()[-1])
    summary["wall_s"], summary["exit_code"] = time.perf_counter() - t0, proc.returncode
    summary.update(run_figures(Path(summary["report_dir"])))
    return summary
