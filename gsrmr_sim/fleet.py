"""``gsrmr-demo --robots N``: N simulated robots at once, each with its own server, scheduler and world.

Every robot runs the single robot's closed loop (:func:`gsrmr_sim.sim_stack.fleet_stack`, the list of
``fleet.launch.py``) in its own namespace ``/robot<k>`` of one ROS domain: mock LIMO on its own pty, LIMO
driver, mock camera, simulated radio (channel seed + k − 1), route follower, robot node, server and
scheduler. With ``--hosts 2`` every robot's processes run in the robot namespace and every server and
scheduler in the server namespace of one :class:`gsrmr_sim.netns.TwoHosts`, all robots sharing the uplink.

:func:`run_fleet` starts every node but the route followers, waits until every server composes, sets all
robots in motion, and stops once every robot has composed the round's slots. Once every robot's round has
started, and again just before the stop, it reads each process's CPU time (``/proc/<pid>/stat``, user +
system, of every process in the node's session): the CPU each robot's server + scheduler, robot side (robot
node, LIMO driver) and simulated world (mock LIMO, camera, radio, route follower) spent during the round.
:func:`fleet_demo` writes one report folder per robot (``<out>/robot<k>/``: ``slots.csv`` with ``scored``,
``summary.json``, plots, ``run.mcap``, ``recording/``, ``scheduler_state/``; logs in ``<out>/logs/robot<k>/``)
and prints one JSON line:
``robots``, ``per_robot`` (each robot's summary, as the single-robot demo's, with ``robot``, ``namespace``
and ``cpu``) and the fleet totals over every robot's scored slots (``slots``, ``slots_on_time``,
``mean_loss``, ``energy_ratio_vs_upload_all`` …, worst robot's ``slots_on_time_min`` and ``mean_loss_max``,
CPU in cores per robot).
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
import contextlib
from dataclasses import dataclass, field
import json
import math
import os
from pathlib import Path
import random
import re
import shutil
import time
from typing import TYPE_CHECKING

from gsrmr_sim.demo import (
    LinkEvent,
    _log,
    copy_recording,
    first_round_row,
    link_summary,
    run_summary,
    summarise,
    write_report,
)

if TYPE_CHECKING:
    from gsrmr_sim.models import BuiltModel
    from gsrmr_sim.sim_stack import ProcessSpec

# What each process stands for when its CPU is counted: the simulated world (hardware and physics on a real
# deployment), the robot's own computer (robot node, LIMO driver) or the workstation (server, scheduler).
WORLD_EXECUTABLES = frozenset({"gsrmr-mock-limo", "gsrmr-mock-camera", "gsrmr-route-follower", "gsrmr-sim-channel"})
CPU_GROUPS = ("server", "robot", "world")


def cpu_group(spec: ProcessSpec) -> str:
    """``server`` (server, scheduler), ``world`` (the simulated world) or ``robot`` (robot node, LIMO driver)."""
    if spec.host == "server":
        return "server"
    return "world" if spec.executable in WORLD_EXECUTABLES else "robot"


def cpu_seconds_by_session() -> dict[int, float]:
    """CPU seconds (user + system, own and of reaped children) of every live process, summed per session id.

    The supervisor starts each node in its own session (``start_new_session``; ``nice`` and ``ip netns exec``
    exec the node), so a node's session id is its Popen pid and the sum covers its threads and any children.
    """
    tick = os.sysconf("SC_CLK_TCK")
    out: dict[int, float] = {}
    for entry in os.scandir("/proc"):
        if not entry.name.isdigit():
            continue
        try:
            with open(f"/proc/{entry.name}/stat", "rb") as f:
                stat = f.read()
        except OSError:
            continue
        fields = stat[stat.rindex(b")") + 2:].split()  # after "pid (comm) ": state is fields[0] (field 3)
        session = int(fields[3])  # field 6
        utime, stime, cutime, cstime = (int(v) for v in fields[11:15])  # fields 14-17
        out[session] = out.get(session, 0.0) + (utime + stime + cutime + cstime) / tick
    return out


RADIO_ROUND_START = re.compile(r"round clock of the channel starts at slot (\d+)")
RADIO_GRACE_SLOTS = 20  # the server's rows must reach this far past the radio's start before its log is used


def radio_round_row(rows: list[dict], radio_log: str) -> int | None:
    """Row of the round's first slot from the simulated radio's own log (``gsrmr-sim-channel``: "round clock of
    the channel starts at slot S", the slot whose ``round_slot`` is 0) — for a server so overloaded that neither
    the robot's ledger (round slots) nor a moved pose key reached it (:func:`gsrmr_sim.demo.first_round_row`
    finds nothing); None until its rows reach :data:`RADIO_GRACE_SLOTS` slots past S."""
    found = RADIO_ROUND_START.search(radio_log)
    if found is None or not rows or rows[-1]["slot"] < int(found.group(1)) + RADIO_GRACE_SLOTS:
        return None
    start = int(found.group(1))
    return next(i for i, r in enumerate(rows) if r["slot"] >= start)


def machine_busy_seconds() -> float:
    """CPU seconds the whole machine has been busy (every core; ``/proc/stat``: all but idle and iowait)."""
    with open("/proc/stat") as f:
        values = [int(v) for v in f.readline().split()[1:]]
    return (sum(values[:8]) - values[3] - values[4]) / os.sysconf("SC_CLK_TCK")


MACHINE = -1  # the key of the machine's busy seconds in a CPU snapshot


@dataclass
class RobotRun:
    """One robot of a fleet run: its scored rows, where its round starts in its ``slots.csv`` and its CPU."""

    name: str  # robot<k>
    namespace: str
    channel_seed: int
    report_dir: Path
    rows: list[dict] = field(default_factory=list)
    first_moving: int = 0
    round_start: str = ""  # where first_moving came from: "slots.csv" (as the single demo) or "radio log"
    cpu: dict = field(default_factory=dict)


def run_fleet(*, robots: int, scene: str, model_path: Path, loss_map: Path | str, run_dir: Path,
              loss_threshold: float, slots: int, method: str, timeout_s: float, channel_seed: int | None = None,
              oracle_channel: bool = False, hosts: int = 1, uplink_mbit: float = 5.0,
              link_events: Sequence[LinkEvent] = (), link_log: dict | None = None,
              overrides: dict[str, dict] | None = None, kill_safe: bool = False,
              warm_timeout_s: float | None = None, domain_id: int | None = None) -> list[RobotRun]:
    """Start ``robots`` closed loops as processes over DDS; stop once every robot has composed ``slots``
    slots of its round; return each robot's run (see the module docstring).

    ``hosts``, ``uplink_mbit``, ``link_events`` and ``link_log`` as :func:`gsrmr_sim.demo.run_stack` (a link
    event applies once every robot has composed ``at_slot`` round slots). ``overrides`` (per node name) apply to
    every robot; ``kill_safe`` selects the kill-safe DDS transport; ``domain_id`` the ROS domain (default: a
    random one).
    """
    from gsrmr_server.recording import read_slots_csv
    from gsrmr_sim.sim_stack import environment, fleet_stack, mock_limo_link
    from gsrmr_sim.supervisor import ProcessStack
    domain = random.Random(os.getpid() ^ time.time_ns()).randrange(1, 101) if domain_id is None else domain_id
    link = f"/tmp/gsrmr_limo_{os.getpid()}"
    per_robot = str(run_dir / "{robot}")
    truth_dir = per_robot + "/truth_frames" if hosts == 2 else ""
    specs = fleet_stack(robots=robots, scene=scene, model_path=str(model_path),
                        record_dir=per_robot + "/recording", loss_threshold=loss_threshold, link_path=link, laps=1,
                        method=method, loss_map_file=str(loss_map), state_dir=per_robot + "/scheduler_state",
                        channel_seed=channel_seed, oracle_channel=oracle_channel, truth_dir=truth_dir,
                        overrides=overrides)
    runs: dict[str, RobotRun] = {}
    for spec in specs:
        name = spec.namespace.strip("/")
        if name not in runs:
            runs[name] = RobotRun(name, spec.namespace, -1, run_dir / name)
        if spec.executable == "gsrmr-sim-channel":
            runs[name].channel_seed = int(spec.params["channel_seed"])
    # one stack for every robot: one stop() ends them all (Ctrl-C, SIGTERM, errors); process "robot2/gsrmr_server"
    # logs to <run_dir>/logs/robot2/gsrmr_server.log
    stack = ProcessStack(environment(domain, kill_safe=kill_safe), run_dir / "logs", params_dir=run_dir / "params")
    for name, run in runs.items():
        (stack.log_dir / name).mkdir(parents=True, exist_ok=True)
        run.report_dir.mkdir(parents=True, exist_ok=True)

    def key(spec: ProcessSpec) -> str:
        return f"{spec.namespace.strip('/')}/{spec.name}"

    net = None
    placement: dict[str, dict] = {}
    links = [p for p in map(mock_limo_link, specs) if p]
    csv = {name: r.report_dir / "recording" / "slots.csv" for name, r in runs.items()}
    events = sorted(link_events, key=lambda e: e.at_slot)
    try:
        if hosts == 2:
            from gsrmr_sim.netns import TwoHosts

            net = TwoHosts(uplink_mbit=uplink_mbit, domain_id=domain).open()
            for spec in specs:
                ns = net.robot_ns if spec.host == "robot" else net.server_ns
                placement[key(spec)] = {"prefix": ["ip", "netns", "exec", ns], "env": net.environment(stack.env)}
            _log(f"two hosts: robot {net.robot_ns} ({net.robot_ip}), server {net.server_ns} ({net.server_ip}), "
                 f"uplink limited to {uplink_mbit:g} Mbit/s shared by {robots} robots, DDS over UDPv4")
        _log(f"starting {len(specs)} processes of {robots} robots ({', '.join(r.namespace for r in runs.values())}) "
             f"in ROS domain {domain}")

        def rows_of(name: str) -> list[dict]:
            return read_slots_csv(csv[name]) if csv[name].exists() else []

        # as the single robot's demo: the route followers start once every server composes
        last = ("gsrmr-route-follower",)
        for spec in specs:
            if spec.executable not in last:
                stack.start(key(spec), spec, wait_for_path=mock_limo_link(spec), **placement.get(key(spec), {}))
        warm = time.monotonic() + (warm_timeout_s if warm_timeout_s is not None else 60.0 + 30.0 * (robots - 1))
        while time.monotonic() < warm and min(len(rows_of(n)) for n in runs) < 10:
            stack.check()
            time.sleep(0.2)
        for spec in specs:
            if spec.executable in last:
                stack.start(key(spec), spec, **placement.get(key(spec), {}))
        if net is not None and link_log is not None:
            link_log["start"] = net.link_bytes()
        # CPU is counted over the round: from the last snapshot before the latest robot's first round slot
        # started (its slots.csv stamp: ROS time, the wall clock) to the stop
        pids = {stack.procs[key(spec)].pid for spec in specs}

        def snapshot() -> tuple[float, dict[int, float]]:
            return time.time(), {**{pid: v for pid, v in cpu_seconds_by_session().items() if pid in pids},
                                 MACHINE: machine_busy_seconds()}

        snapshots = [snapshot()]
        deadline = time.monotonic() + timeout_s
        first: dict[str, int | None] = dict.fromkeys(runs)
        fallbacks: set[str] = set()
        done: dict[str, int] = dict.fromkeys(runs, 0)
        last_report = 0.0
        while time.monotonic() < deadline:
            time.sleep(0.5)
            stack.check()
            for name in runs:
                if done[name] >= slots:
                    continue
                rows = rows_of(name)
                if first[name] is None:
                    first[name] = first_round_row(rows)
                if first[name] is None:  # the server has neither the radio's round slots nor a moved pose key
                    first[name] = radio_round_row(rows, stack.log(f"{name}/gsrmr_sim_channel"))
                    if first[name] is not None:
                        fallbacks.add(name)
                        _log(f"{name}: its server saw no round slot and no moved pose key: the round starts at the "
                             f"simulated radio's first round slot")
                if first[name] is not None:
                    done[name] = len(rows) - first[name]
            snapshots.append(snapshot())
            fleet_done = min(done.values())
            while net is not None and events and fleet_done >= events[0].at_slot:
                event = events.pop(0)
                event.apply(net)
                if link_log is not None:
                    link_log.setdefault("events", []).append(
                        {**event.as_dict(), "applied_after_slot": fleet_done, "wall_s": time.time()})
                _log(f"link: {event.describe()} (round slot ~{fleet_done} of every robot)")
            if fleet_done >= slots:
                break
            if time.monotonic() - last_report > 5:
                _log("round 2: " + ", ".join(f"{n} {min(d, slots)}/{slots}" for n, d in done.items()) + " slots")
                last_report = time.monotonic()
        else:
            raise TimeoutError(f"round 2 did not produce {slots} slots for every robot in {timeout_s:.0f} s: {done}")
        end_s, cpu_end = snapshot()
        round_start_s = max(rows_of(name)[first[name]]["stamp_s"] for name in runs)  # type: ignore[index]
        start_s, cpu_start = max((s for s in snapshots if s[0] <= round_start_s), default=snapshots[0],
                                 key=lambda s: s[0])
        wall = end_s - start_s
        for spec in specs:
            pid = stack.procs[key(spec)].pid
            run = runs[spec.namespace.strip("/")]
            used = cpu_end.get(pid, 0.0) - cpu_start.get(pid, 0.0)
            run.cpu.setdefault("by_node_cpu_s", {})[spec.name] = round(used, 3)
            group = cpu_group(spec)
            run.cpu[f"{group}_cpu_s"] = run.cpu.get(f"{group}_cpu_s", 0.0) + used
        machine = (cpu_end[MACHINE] - cpu_start[MACHINE]) / wall
        ours = sum(cpu_end.get(pid, 0.0) - cpu_start.get(pid, 0.0) for pid in pids) / wall
        for run in runs.values():
            run.cpu["window_s"] = wall
            # every core of the machine: the fleet's processes, this runner, and whatever else runs here
            run.cpu["machine_busy_cores"] = machine
            run.cpu["other_cores"] = machine - ours
            for group in CPU_GROUPS:
                run.cpu[f"{group}_cores"] = run.cpu.get(f"{group}_cpu_s", 0.0) / wall
        for name, run in runs.items():
            run.first_moving = int(first[name])  # type: ignore[arg-type]
            run.round_start = "radio log" if name in fallbacks else "slots.csv"
    finally:
        if net is not None and link_log is not None and "start" in link_log:
            with contextlib.suppress(Exception):
                link_log["end"] = net.link_bytes()
        try:
            for name, took in stack.stop().items():
                if took >= stack.stop_timeout_s:
                    _log(f"{name} ignored SIGINT for {stack.stop_timeout_s:.0f} s; killed")
        finally:
            if net is not None:
                net.close()
            for run in runs.values():
                if truth_dir:
                    shutil.rmtree(run.report_dir / "truth_frames", ignore_errors=True)
            for path in links:
                if os.path.islink(path):
                    os.unlink(path)
    for name, run in runs.items():
        run.rows = read_slots_csv(csv[name])[run.first_moving:run.first_moving + slots]
    return list(runs.values())


def fleet_totals(runs: Sequence[RobotRun], slot_s: float) -> dict:
    """The fleet's figures: :func:`gsrmr_sim.demo.summarise` over every robot's scored slots together, the worst
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
    _log(f"round 2: {robots} robots × {slots} slots in real time ({slots * slot_s:.1f} s) over DDS, "
         f"L_th = {args.loss_threshold}")
    link_log: dict = {}
    runs = run_fleet(robots=robots, scene=args.scene, model_path=built.path, loss_map=loss_map, run_dir=out,
                     loss_threshold=args.loss_threshold, slots=slots, method=args.method,
                     timeout_s=slots * slot_s + 120.0, channel_seed=args.channel_seed, oracle_channel=args.oracle,
                     hosts=args.hosts, uplink_mbit=args.uplink_mbit, link_events=link_events, link_log=link_log,
                     overrides=getattr(args, "overrides", None) or None)
    per_robot = []
    for run in runs:
        copy_recording(run.report_dir, run.report_dir / "recording", run.first_moving, len(run.rows))
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
    (out / "fleet_summary.json").write_text(json.dumps(fleet, indent=1))
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
    print(json.dumps(fleet), flush=True)
    return 0
