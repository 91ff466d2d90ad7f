"""A fleet on one machine: ``gsrmr-demo --robots N`` for several N, as a table, and how many robots a core serves.

Usage: ``.venv/bin/python bench/acceptance/fleet.py [--robots 1 2 3] [--runs 1] [--hosts 1|2] [--uplink-mbit R]
[--slots S] [-- DEMO_ARGS...]`` (e.g. ``-- --cache .cache/gsrmr``). Each run is one ``gsrmr-demo --robots N`` subprocess
(every robot with its own server, scheduler and simulated world, namespaces /robot1 … /robotN); per N the
table gives, as the median over runs (worst run in brackets): slots on time of the worst robot, MR-image
latency p50/p95/p99 over every robot's scored slots (``slots.csv`` ``latency_ms``: MR image published − slot
start), the energy ratio upload-all / ours (median over robots), the mean loss of the worst robot, and CPU per
robot in cores (CPU seconds per second of the round, read by the demo from ``/proc/<pid>/stat`` of every
process of each robot): server + scheduler (the workstation's share), robot node + LIMO driver (the robot's
computer) and the simulated world (mock LIMO, camera, radio, route follower — hardware and physics on a real
deployment — and the simulation's ground-truth scorer, ``gsrmr-sim-scorer``, which scores the MR images outside
the server), plus the machine's 1-min load average before the runs and the CPU the rest of the machine used
during them (``/proc/stat`` busy time minus the fleet's processes: this runner, the demo, other jobs). The last
lines derive from the measured server + scheduler CPU how many robots one workstation core serves.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
from pathlib import Path
import signal
import statistics
import subprocess
import sys
import time

import numpy as np

REPO = Path(__file__).resolve().parents[2]
ON_TIME_OK = 0.99  # a fleet size "keeps up" when its worst robot has at least this share of slots on time


def run_demo(robots: int, demo_args: list[str], out: Path) -> dict:
    """One ``gsrmr-demo --robots N`` run: its fleet summary (the last stdout line), the wall time, the load
    average before it and the latency percentiles over every robot's scored slots."""
    exe = Path(sys.executable).parent / "gsrmr-demo"
    load_before = os.getloadavg()[0]
    t0 = time.perf_counter()
    argv = [str(exe), "--robots", str(robots), "--out", str(out), *demo_args]
    with subprocess.Popen(argv, stdout=subprocess.PIPE, text=True) as proc:
        try:
            stdout, _ = proc.communicate()
        except BaseException:  # Ctrl-C / SIGTERM: let the demo stop its nodes (it handles both)
            proc.terminate()
            proc.wait(timeout=120)
            raise
    if proc.returncode:
        raise subprocess.CalledProcessError(proc.returncode, argv)
    fleet = json.loads(stdout.strip().splitlines()[-1])
    fleet["wall_s"] = time.perf_counter() - t0
    fleet["load_before"] = load_before
    latency = []
    for robot in fleet["per_robot"]:
        with open(Path(robot["report_dir"]) / "slots.csv", newline="") as f:
            latency += [float(r["latency_ms"]) for r in csv.DictReader(f) if r.get("scored") == "1" and r["latency_ms"]]
    for q in (50, 95, 99):
        fleet[f"latency_ms_p{q}"] = float(np.percentile(latency, q)) if latency else math.nan
    per = fleet["per_robot"]
    fleet["on_time_min"] = min(r["slots_on_time"] for r in per)
    fleet["slots_per_robot"] = min(r["slots"] for r in per)
    fleet["energy_ratio_median"] = statistics.median(r["energy_ratio_vs_upload_all"] for r in per)
    fleet["cores_total"] = sum(fleet[f"{g}_cores_per_robot"] for g in ("server", "robot", "world")) * robots
    return fleet


def _med_worst(runs: list[dict], key: str, worst=max, fmt: str = "{:.3f}") -> str:
    values = [r[key] for r in runs]
    med = fmt.format(statistics.median(values))
    return med if len(values) == 1 else f"{med} ({fmt.format(worst(values))})"


def table(results: dict[int, list[dict]], failed: dict[int, list[dict]]) -> list[str]:
    lines = ["| robots | runs | load avg before / other CPU during (cores) | on time, worst robot | "
             "latency p50 / p95 / p99 ms | energy ratio (median robot) | mean loss, worst robot | "
             "server+scheduler cores / robot | robot-side cores / robot | world cores / robot | all cores | wall s |",
             "|" + "---|" * 12]
    for n, runs in results.items():
        slots = min(r["slots_per_robot"] for r in runs)
        lat = " / ".join(f"{statistics.median(r[f'latency_ms_p{q}'] for r in runs):.1f}" for q in (50, 95, 99))
        lines.append(
            f"| {n} | {len(runs)} | {max(r['load_before'] for r in runs):.2f} / "
            f"{max(r['other_cores'] for r in runs):.2f} | "
            f"{_med_worst(runs, 'on_time_min', min, '{:.0f}')} / {slots} | {lat} | "
            f"{_med_worst(runs, 'energy_ratio_median', min, '{:.1f}')}× | "
            f"{_med_worst(runs, 'mean_loss_max', max, '{:.4f}')} | "
            f"{_med_worst(runs, 'server_cores_per_robot')} | {_med_worst(runs, 'robot_cores_per_robot')} | "
            f"{_med_worst(runs, 'world_cores_per_robot')} | {_med_worst(runs, 'cores_total', max, '{:.2f}')} | "
            f"{statistics.median(r['wall_s'] for r in runs):.0f} |")
    for n, runs in failed.items():
        lines.append(f"| {n} | {len(runs)} failed | {max(r['load_before'] for r in runs):.2f} | gsrmr-demo exit code "
                     f"{', '.join(str(r['exit_code']) for r in runs)} (its error above) |" + " |" * 8)
    return lines


def conclusions(results: dict[int, list[dict]], cpus: int, failed: dict[int, list[dict]]) -> list[str]:
    """Robots per workstation core from the measured server + scheduler CPU per robot (worst run of each N)."""
    lines = [f"- N = {n}: {len(runs)} run(s) failed: the machine did not keep up" for n, runs in failed.items()]
    keeps_up = []
    for n, runs in results.items():
        worst = max(max(r["server_cores_per_robot"] for r in runs), 1e-9)
        ok = min(r["on_time_min"] / r["slots_per_robot"] for r in runs) >= ON_TIME_OK
        busy = max(r["cores_total"] for r in runs) / cpus
        lines.append(f"- N = {n}: server+scheduler {worst:.3f} core per robot (worst run) → one core serves "
                     f"{1.0 / worst:.1f} robots; whole simulated stack {max(r['cores_total'] for r in runs):.2f} of "
                     f"{cpus} cores ({100 * busy:.0f} %); worst robot on time "
                     f"{min(r['on_time_min'] for r in runs)}/{min(r['slots_per_robot'] for r in runs)}"
                     + ("" if ok else f" — below {100 * ON_TIME_OK:.0f} %: the machine did not keep up")
                     + (" (CPU near saturation: the per-robot figure is a lower bound)" if busy > 0.9 else ""))
        if ok and n not in failed:
            keeps_up.append((n, worst))
    if keeps_up:
        n, cost = max(keeps_up, key=lambda t: t[1])  # the dearest per-robot cost among the sizes that kept up
        lines.append(f"- one workstation core serves {math.floor(1.0 / cost)} robots (server + scheduler at "
                     f"{cost:.3f} core each, the dearest of the fleet sizes that kept up, N = {n}); this {cpus}-core "
                     f"machine's server side alone would serve {math.floor(cpus / cost)}")
        largest = max(n for n, _ in keeps_up)
        per_robot_all = max(r["cores_total"] for r in results[largest]) / largest
        lines.append(f"- with the simulated world and the robots' own nodes on the same machine "
                     f"({per_robot_all:.3f} core per robot in all at N = {largest}), CPU alone would fit "
                     f"{math.floor(cpus / per_robot_all)} robots on its {cpus} cores; the largest fleet that kept up "
                     f"here: N = {largest}")
    else:
        lines.append("- no fleet size kept up (worst robot below "
                     f"{100 * ON_TIME_OK:.0f} % of slots on time): no robots-per-core figure")
    return lines


def _exit_on_sigterm(signum: int, _frame: object) -> None:
    raise SystemExit(128 + signum)


def main() -> int:
    signal.signal(signal.SIGTERM, _exit_on_sigterm)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", type=int, nargs="+", default=[1, 2, 3], help="fleet sizes N")
    ap.add_argument("--runs", type=int, default=1, help="runs per fleet size")
    ap.add_argument("--hosts", type=int, choices=(1, 2), default=1, help="gsrmr-demo --hosts")
    ap.add_argument("--uplink-mbit", type=float, default=None, help="gsrmr-demo --uplink-mbit (with --hosts 2)")
    ap.add_argument("--slots", type=int, default=0, help="gsrmr-demo --slots (0 = the scene's round)")
    ap.add_argument("--out", default="", help="report folder (default reports/fleet-<time>)")
    ap.add_argument("demo_args", nargs="*", help="passed to gsrmr-demo (after --)")
    args = ap.parse_args()
    demo_args = ["--hosts", str(args.hosts), *args.demo_args]
    if args.uplink_mbit is not None:
        demo_args += ["--uplink-mbit", f"{args.uplink_mbit:g}"]
    if args.slots:
        demo_args += ["--slots", str(args.slots)]
    out = Path(args.out or REPO / "reports" / f"fleet-{time.strftime('%Y%m%d-%H%M%S')}")
    cpus = os.cpu_count() or 1
    print(f"# bench/acceptance/fleet.py: gsrmr-demo --robots {' '.join(map(str, args.robots))} × {args.runs} run(s), "
          f"{' '.join(demo_args)} ({cpus} CPUs, load average before {os.getloadavg()[0]:.2f})", flush=True)
    results: dict[int, list[dict]] = {}
    failed: dict[int, list[dict]] = {}
    for n in args.robots:
        for k in range(args.runs):
            load_before = os.getloadavg()[0]
            try:
                fleet = run_demo(n, demo_args, out / f"robots{n}-run{k + 1}")
            except subprocess.CalledProcessError as e:  # e.g. a robot's round never reached its server in time
                failed.setdefault(n, []).append({"exit_code": e.returncode, "load_before": load_before})
                print(f"# N={n} run {k + 1}: gsrmr-demo failed with exit code {e.returncode}", flush=True)
                continue
            results.setdefault(n, []).append(fleet)
            print(f"# N={n} run {k + 1}: worst robot on time {fleet['on_time_min']}/{fleet['slots_per_robot']}, "
                  f"mean loss (worst robot) {fleet['mean_loss_max']:.4f}, server+scheduler "
                  f"{fleet['server_cores_per_robot']:.3f} core/robot, {fleet['wall_s']:.0f} s", flush=True)
    out.mkdir(parents=True, exist_ok=True)
    (out / "fleet_bench.json").write_text(json.dumps({"runs": {str(n): runs for n, runs in results.items()},
                                                      "failed": {str(n): f for n, f in failed.items()}}, indent=1))
    print("\n".join(["", *table(results, failed), "", *conclusions(results, cpus, failed)]), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
