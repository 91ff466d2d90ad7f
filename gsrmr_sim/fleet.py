"""``gsrmr-demo --robots N``: N simulated robots at once, each with its own server, scheduler and world.

Namespaces, writer lists, the round and the output (a report folder per robot, one JSON line): docs/world.md,
"A fleet". The runner is the demo's, :func:`gsrmr_sim.stack_runner.run_round`.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
import math
from pathlib import Path
import time
from typing import TYPE_CHECKING

from gsrmr_sim.cpu_usage import CPU_GROUPS
from gsrmr_sim.limo.odometry_errors import OdometryErrors, run_settings
from gsrmr_sim.link_events import LinkEvent
from gsrmr_sim.report import (
    copy_recording,
    exit_status,
    link_summary,
    log,
    run_summary,
    summarise,
    summary_json,
    write_report,
)
from gsrmr_sim.sim_stack import fleet_stack
from gsrmr_sim.stack_runner import RobotRun, limo_link_path, run_round
from gsrmr_sim.world.scene import load_scene

if TYPE_CHECKING:
    from gsrmr_sim.models import BuiltModel


def run_fleet(*, robots: int, scene: str, model_path: Path, loss_map: Path | str, run_dir: Path,
              loss_threshold: float, slots: int, method: str, timeout_s: float, channel_seed: int | None = None,
              oracle_channel: bool = False, hosts: int = 1, uplink_mbit: float = 5.0,
              link_events: Sequence[LinkEvent] = (), link_log: dict | None = None,
              overrides: dict[str, dict] | None = None, kill_safe: bool = False,
              warm_timeout_s: float | None = None, domain_id: int | None = None,
              odometry: OdometryErrors = OdometryErrors(), odometry_seed: int | None = None,
              localization: bool = True) -> list[RobotRun]:
    """Run ``robots`` closed loops (:func:`gsrmr_sim.sim_stack.fleet_stack`; robot k's recording, scheduler state
    and truth frames under ``<run_dir>/robot<k>/``) with :func:`gsrmr_sim.stack_runner.run_round`: stop once every
    robot has composed ``slots`` slots of its round; return each robot's run.

    ``hosts``, ``uplink_mbit``, ``link_events``, ``link_log``, ``kill_safe``, ``warm_timeout_s`` and ``domain_id``
    as :func:`~gsrmr_sim.stack_runner.run_round` (a link event applies once every robot has composed ``at_slot``
    round slots); ``overrides`` (parameters per node name) apply to every robot.
    """
    per_robot = str(run_dir / "{robot}")
    specs = fleet_stack(robots=robots, scene=scene, model_path=str(model_path),
                        record_dir=per_robot + "/recording", loss_threshold=loss_threshold, link_path=limo_link_path(),
                        laps=1, method=method, loss_map_file=str(loss_map), state_dir=per_robot + "/scheduler_state",
                        channel_seed=channel_seed, oracle_channel=oracle_channel,
                        truth_dir=per_robot + "/truth_frames" if hosts == 2 else "", overrides=overrides,
                        odometry=odometry, odometry_seed=odometry_seed, localization=localization)
    return run_round(specs, run_dir=run_dir, slots=slots, timeout_s=timeout_s, hosts=hosts, uplink_mbit=uplink_mbit,
                     link_events=link_events, link_log=link_log, kill_safe=kill_safe, warm_timeout_s=warm_timeout_s,
                     domain_id=domain_id, log=log)


def fleet_totals(runs: Sequence[RobotRun], slot_s: float) -> dict:
    """The fleet's figures: :func:`gsrmr_sim.report.summarise` over every robot's scored slots together, the worst
    robot's on-time slots and mean loss, and CPU (cores, i.e. CPU seconds per second of the round) per robot."""
    pooled = summarise([row for run in runs for row in run.rows], slot_s)
    pooled.pop("faults", None)
    alone = [summarise(run.rows, slot_s) for run in runs]
    cpu = {}
    for group in CPU_GROUPS:
        cores = [run.cpu.get(f"{group}_cores", 0.0) for run in runs]
        cpu[f"{group}_cores_per_robot"] = sum(cores) / len(cores)
        cpu[f"{group}_cores_per_robot_max"] = max(cores)
    return {**pooled, "slots_on_time_min": min(s["slots_on_time"] for s in alone),
            "mean_loss_max": max(s["mean_loss"] for s in alone), **cpu,
            "cpu_window_s": max(run.cpu.get("window_s", 0.0) for run in runs),
            "machine_busy_cores": runs[0].cpu.get("machine_busy_cores", math.nan),
            "other_cores": runs[0].cpu.get("other_cores", math.nan)}


def fleet_demo(args: argparse.Namespace, *, slots: int, slot_s: float, out: Path, built: BuiltModel,
               loss_map: Path, link_events: Sequence[LinkEvent], t_start: float) -> int:
    """``gsrmr-demo --robots N`` from the model and the loss-map seed on: run the fleet, write each robot's
    report, print the summary; the last stdout line is the fleet's JSON (module docstring)."""
    robots = int(args.robots)
    log(f"round 2: {robots} robots × {slots} slots in real time ({slots * slot_s:.1f} s) over DDS, "
        f"L_th = {args.loss_threshold}")
    link_log: dict = {}
    runs = run_fleet(robots=robots, scene=args.scene, model_path=built.path, loss_map=loss_map, run_dir=out,
                     loss_threshold=args.loss_threshold, slots=slots, method=args.method,
                     timeout_s=slots * slot_s + 120.0, channel_seed=args.channel_seed, oracle_channel=args.oracle,
                     hosts=args.hosts, uplink_mbit=args.uplink_mbit, link_events=link_events, link_log=link_log,
                     overrides=getattr(args, "overrides", None) or None,
                     **run_settings(getattr(args, "odometry", "perfect"), getattr(args, "odometry_error_scale", 1.0),
                                    getattr(args, "odometry_seed", None), args.channel_seed,
                                    not getattr(args, "no_localization", False), load_scene(args.scene).odometry))
    per_robot = []
    for run in runs:
        copy_recording(run.report_dir, run.record_dir, run.first_moving, len(run.rows))
        summary = {"robot": run.name, "namespace": run.namespace, "round_start_from": run.round_start,
                   **run_summary(args, run.rows, slot_s, built, run.channel_seed),
                   "cpu": {k: (round(v, 4) if isinstance(v, float) else v) for k, v in run.cpu.items()},
                   "report_dir": str(run.report_dir)}
        write_report(run.report_dir, run.rows, summary)
        summary.pop("faults", None)
        per_robot.append(summary)
    every_row = [row for run in runs for row in run.rows]
    fleet = {"robots": robots, "scene": args.scene, "loss_threshold": args.loss_threshold, "method": args.method,
             **fleet_totals(runs, slot_s), "hosts": args.hosts,
             **(link_summary(link_log, every_row, args.uplink_mbit) if args.hosts == 2 else {}),
             "report_dir": str(out), "per_robot": per_robot}
    (out / "fleet_summary.json").write_text(summary_json(fleet, indent=1))  # strict JSON: NaN → null
    print(f"\ngsrmr demo — fleet of {robots} robots, scene {args.scene}, L_th {args.loss_threshold}, "
          f"{slots} slots each ({time.perf_counter() - t_start:.0f} s in all)")
    for s in per_robot:
        cpu = s["cpu"]
        print(f"  {s['robot']} (channel seed {s['channel_seed']}): images {s['images_sent']}/{s['slots']}, "
              f"{s['energy_ratio_vs_upload_all']:.1f}× less energy than upload-all, regret {s['regret']:.2f}, "
              f"mean loss {s['mean_loss']:.4f}, on time {s['slots_on_time']}/{s['slots']}; CPU (cores) "
              f"server+scheduler {cpu['server_cores']:.2f}, robot {cpu['robot_cores']:.2f}, "
              f"world {cpu['world_cores']:.2f}")
    print(f"  fleet: on time {fleet['slots_on_time']}/{fleet['slots']} (worst robot {fleet['slots_on_time_min']}), "
          f"mean loss {fleet['mean_loss']:.4f} (worst robot {fleet['mean_loss_max']:.4f}), energy "
          f"{fleet['energy_ratio_vs_upload_all']:.1f}× less than upload-all; per robot "
          f"{fleet['server_cores_per_robot']:.2f} core server+scheduler")
    if args.hosts == 2 and "link_uplink_bytes" in fleet:
        print(f"  two hosts: uplink limited to {args.uplink_mbit:g} Mbit/s; {fleet['link_uplink_bytes']} B crossed "
              f"robot → server ({fleet['link_uplink_mbit_mean']:.2f} Mbit/s mean) for {robots} robots")
    print(f"  reports: {out}/robot1 … robot{robots}")
    print(summary_json(fleet), flush=True)
    return exit_status(per_robot)
