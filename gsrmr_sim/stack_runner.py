"""``gsrmr-demo``'s round over DDS, one robot or a fleet, on one host or two: the one stack runner.

:func:`run_round` starts a process list, sets the robots in motion once every server composes and every scheduler
has planned (round 2 then begins with every node up and warm, as on the real system), follows the round, stops
everything in ``finally`` (namespaces, truth-frame folders and ptys removed) and returns one :class:`RobotRun` per
robot: docs/architecture.md, "One pipeline each".
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
import contextlib
from dataclasses import dataclass, field
import os
from pathlib import Path
import random
import shutil
import subprocess
import time

from gsrmr_server.recording import CSV_NAME, read_slots_csv
from gsrmr_sim.cpu_usage import CPU_GROUPS, CpuMeter, RoundUsage, cpu_group
from gsrmr_sim.link_events import LinkEvent
from gsrmr_sim.netns import TwoHosts
from gsrmr_sim.param_events import ParamEvent
from gsrmr_sim.round_start import first_round_row, radio_round_row
from gsrmr_sim.scores import SCORER_READY_NAME, await_scores, join_scores
from gsrmr_sim.sim_stack import ProcessSpec, environment, mock_limo_link
from gsrmr_sim.supervisor import ProcessStack

ROUTE_FOLLOWER = "gsrmr-route-follower"  # started last: it sets its robot in motion
SERVER, SCORER, RADIO = "gsrmr-server", "gsrmr-sim-scorer", "gsrmr-sim-channel"
SCHEDULER = "gsrmr-scheduler"
WARM_ROWS = 10  # composed slots every server has logged before the robots set off
WARM_TIMEOUT_S = 60.0  # how long to wait for that (one robot) …
WARM_TIMEOUT_PER_ROBOT_S = 30.0  # … and per further robot
POLL_S = 0.5  # how often the round's progress is read (and CPU snapshots taken)
PROGRESS_LOG_S = 5.0


def limo_link_path() -> str:
    """Where this process's stacks put the mock LIMO's pty (robot k of a fleet: ``<path>_robot<k>``)."""
    return f"/tmp/gsrmr_limo_{os.getpid()}"


def random_domain_id() -> int:
    """A ROS domain in 1…100 for one run (two runs on a machine rarely share one)."""
    return random.Random(os.getpid() ^ time.time_ns()).randrange(1, 101)


def process_name(spec: ProcessSpec) -> str:
    """``spec``'s name in the stack and its log's under ``logs/``: the node name, under its robot in a fleet
    (``robot2/gsrmr_server``)."""
    robot = spec.namespace.strip("/")
    return f"{robot}/{spec.name}" if robot else spec.name


@dataclass
class RobotRun:
    """One robot's round: its scored rows, where its round starts in its ``slots.csv`` and its CPU."""

    name: str  # robot<k>; "" for the single robot in the root namespace
    namespace: str
    record_dir: Path  # its server's recording (slots.csv) and its scorer's scores.csv
    channel_seed: int | None = None  # its simulated radio's (None: config/link.yaml's)
    processes: dict[str, str] = field(default_factory=dict)  # executable → process name in the stack
    rows: list[dict] = field(default_factory=list)
    first_moving: int = 0  # row of slots.csv where its round starts
    round_start: str = ""  # where first_moving came from: "slots.csv" or "radio log"
    cpu: dict = field(default_factory=dict)
    scheduler_state: Path | None = None  # its scheduler's state_dir (schedule.json after every plan), if any

    @property
    def planned(self) -> bool:
        """Its scheduler has planned (its ``schedule.json`` exists), or it has no scheduler state to tell."""
        return self.scheduler_state is None or (self.scheduler_state / "schedule.json").exists()

    @property
    def scorer_ready(self) -> bool:
        """Its scorer receives the server's MR images (``scorer.ready`` exists), or it has no scorer."""
        return SCORER not in self.processes or (self.record_dir / SCORER_READY_NAME).exists()

    @property
    def report_dir(self) -> Path:
        """Its report folder: the folder holding its recording."""
        return self.record_dir.parent

    @property
    def label(self) -> str:
        """``robot2``, or ``the robot`` for the single one (log lines)."""
        return self.name or "the robot"

    def rows_so_far(self) -> list[dict]:
        """Its server's ``slots.csv`` rows as they are now (none before the file exists)."""
        path = self.record_dir / CSV_NAME
        return read_slots_csv(path) if path.exists() else []


def robot_runs(specs: Sequence[ProcessSpec]) -> dict[str, RobotRun]:
    """One :class:`RobotRun` per namespace of ``specs``, from its server's ``record_dir`` and its radio's seed;
    ValueError for a robot without a recording server."""
    runs: dict[str, RobotRun] = {}
    for spec in specs:
        name = spec.namespace.strip("/")
        run = runs.setdefault(name, RobotRun(name, spec.namespace, Path()))
        run.processes[spec.executable] = process_name(spec)
        if spec.executable == SERVER:
            if not spec.params.get("record_dir"):
                raise ValueError(f"{process_name(spec)} records nowhere (record_dir): the round cannot be followed")
            run.record_dir = Path(spec.params["record_dir"])
        elif spec.executable == RADIO and "channel_seed" in spec.params:
            run.channel_seed = int(spec.params["channel_seed"])
        elif spec.executable == SCHEDULER and spec.params.get("state_dir"):
            run.scheduler_state = Path(spec.params["state_dir"])
    missing = [run.label for run in runs.values() if SERVER not in run.processes]
    if missing:
        raise ValueError(f"no {SERVER} for {', '.join(missing)}")
    return runs


def run_round(specs: Sequence[ProcessSpec], *, run_dir: Path, slots: int, timeout_s: float, hosts: int = 1,
              uplink_mbit: float = 5.0, link_events: Sequence[LinkEvent] = (), link_log: dict | None = None,
              kill_safe: bool = False, warm_timeout_s: float | None = None, domain_id: int | None = None,
              label: str = "round 2", param_events: Sequence[ParamEvent] = (), param_log: list | None = None,
              log: Callable[[str], None] = print) -> list[RobotRun]:
    """Run ``specs`` as processes over DDS until every robot has composed ``slots`` slots of its round, within
    ``timeout_s`` of setting off (else TimeoutError); return each robot's run (see the module docstring).

    Logs go to ``<run_dir>/logs/`` (a fleet's robot k: ``logs/robot<k>/``), parameter files to
    ``<run_dir>/params/``. ``hosts`` = 2 puts the processes on two hosts joined by a link limited to
    ``uplink_mbit`` (DDS over UDPv4 across it); ``link_events`` then change the link once every robot has composed
    their ``at_slot`` round slots, and ``link_log`` (a dict) receives the link's byte counters (``start``,
    ``end``) and the events applied. ``kill_safe`` selects the kill-safe DDS transport, ``domain_id`` the ROS
    domain (default: a random one), ``warm_timeout_s`` how long the servers may take to compose before the
    robots set off anyway (default 60 s + 30 s per further robot), ``label`` what the progress lines call the
    round (``gsrmr-demo --rounds``: "round k"). ``param_events`` (one host only) run ``ros2 param set`` at their
    round slots (:mod:`gsrmr_sim.param_events`); ``param_log`` (a list) receives each one's slot, exit code and
    output once the round is over.
    """
    domain = random_domain_id() if domain_id is None else domain_id
    runs = robot_runs(specs)
    fleet = any(run.name for run in runs.values())
    stack = ProcessStack(environment(domain, kill_safe=kill_safe), run_dir / "logs", params_dir=run_dir / "params")
    for spec in specs:
        (stack.log_dir / process_name(spec)).parent.mkdir(parents=True, exist_ok=True)
    for run in runs.values():
        run.report_dir.mkdir(parents=True, exist_ok=True)
    links = [path for path in map(mock_limo_link, specs) if path]
    truth_dirs = sorted({str(spec.params["truth_dir"]) for spec in specs if spec.params.get("truth_dir")})
    net: TwoHosts | None = None
    try:
        placement: dict[str, dict] = {}
        if hosts == 2:
            net = TwoHosts(uplink_mbit=uplink_mbit, domain_id=domain).open()
            for spec in specs:
                ns = net.robot_ns if spec.host == "robot" else net.server_ns
                placement[process_name(spec)] = {"prefix": ["ip", "netns", "exec", ns],
                                                 "env": net.environment(stack.env)}
            shared = f" shared by {len(runs)} robots" if fleet else ""
            log(f"two hosts: robot {net.robot_ns} ({net.robot_ip}), server {net.server_ns} ({net.server_ip}), "
                f"uplink limited to {uplink_mbit:g} Mbit/s{shared}, DDS over UDPv4")
        of_robots = f" of {len(runs)} robots ({', '.join(r.namespace for r in runs.values())})" if fleet else ""
        log(f"starting {len(specs)} processes{of_robots} in ROS domain {domain}")
        warm_s = WARM_TIMEOUT_S + WARM_TIMEOUT_PER_ROBOT_S * (len(runs) - 1) if warm_timeout_s is None \
            else warm_timeout_s
        _start_and_set_off(stack, specs, runs, placement, warm_s, log)
        if net is not None and link_log is not None:
            link_log["start"] = net.link_bytes()
        meter = CpuMeter({proc.pid for proc in stack.procs.values()})
        meter.take()
        if param_events and hosts != 1:
            raise ValueError("parameter events run on one host only")
        started = _follow_round(stack, runs, slots=slots, timeout_s=timeout_s, net=net, link_events=link_events,
                                link_log=link_log, meter=meter, fleet=fleet, label=label, log=log,
                                param_events=param_events)
        _finish_param_events(started, param_log, log)
        meter.take()
        round_start_s = max(run.rows_so_far()[run.first_moving]["stamp_s"] for run in runs.values())
        _count_cpu(specs, stack, runs, meter.round_usage(round_start_s))
        # the round is over: the others stop, each robot's scorer catches up with it (scores.csv)
        await_scores(stack, {run.processes[SCORER]: (run.record_dir, [
            r["slot"] for r in run.rows_so_far()[run.first_moving:][:slots]]) for run in runs.values()
            if SCORER in run.processes}, log=log)
    finally:
        if net is not None and link_log is not None and "start" in link_log:
            with contextlib.suppress(Exception):
                link_log["end"] = net.link_bytes()
        try:
            for name, took in stack.stop().items():
                if took >= stack.stop_timeout_s:
                    log(f"{name} ignored SIGINT for {stack.stop_timeout_s:.0f} s; killed")
        finally:
            if net is not None:
                net.close()
            for folder in truth_dirs:
                shutil.rmtree(folder, ignore_errors=True)
            for path in links:
                if os.path.islink(path):
                    os.unlink(path)
    for run in runs.values():
        every = join_scores(read_slots_csv(run.record_dir / CSV_NAME), run.record_dir)
        run.rows = every[run.first_moving:run.first_moving + slots]
    return list(runs.values())


def _start_and_set_off(stack: ProcessStack, specs: Sequence[ProcessSpec], runs: Mapping[str, RobotRun],
                       placement: Mapping[str, dict], warm_s: float, log: Callable[[str], None]) -> None:
    """Start every process but the route followers (each mock LIMO's pty before its driver opens it), wait until
    every server has composed :data:`WARM_ROWS` slots, every scheduler has planned and every scorer receives the MR
    images (at most ``warm_s``; what was not ready then is logged), then start the route followers. Without the plan,
    the round's first slots go by the robot's default (an image at the power its channel asks for, however deep the
    fade): a scheduler whose kernels compile afresh plans about 0.7 s into the round, and two such images at 18 mW
    double a round's energy (regret 3.2 against 1.6). A scorer at its low priority starts seconds after the rest when
    another session keeps a core busy: without the wait, the round's first slots go unscored."""
    for spec in specs:
        if spec.executable != ROUTE_FOLLOWER:
            name = process_name(spec)
            stack.start(name, spec, wait_for_path=mock_limo_link(spec), **placement.get(name, {}))
    warm = time.monotonic() + warm_s
    checks = {"composed": lambda run: len(run.rows_so_far()) >= WARM_ROWS, "planned": lambda run: run.planned,
              "scorer ready": lambda run: run.scorer_ready}
    while not all(check(run) for check in checks.values() for run in runs.values()):
        stack.check()
        if time.monotonic() > warm:
            log(f"set off after {warm_s:.0f} s with " + "; ".join(
                f"{run.label} not {what}" for run in runs.values() for what, check in checks.items()
                if not check(run)))
            break
        time.sleep(0.2)
    for spec in specs:
        if spec.executable == ROUTE_FOLLOWER:
            name = process_name(spec)
            stack.start(name, spec, **placement.get(name, {}))


def _follow_round(stack: ProcessStack, runs: Mapping[str, RobotRun], *, slots: int, timeout_s: float,
                  net: TwoHosts | None, link_events: Sequence[LinkEvent], link_log: dict | None, meter: CpuMeter,
                  fleet: bool, label: str, log: Callable[[str], None],
                  param_events: Sequence[ParamEvent] = ()) -> list[tuple[ParamEvent, subprocess.Popen, int, Path]]:
    """Until every robot has composed ``slots`` round slots: find where each robot's round starts, apply the
    link events that are due, take a CPU snapshot and log the progress; sets each run's ``first_moving`` and
    ``round_start``; starts the parameter events that are due (returned: each with its process, the round slot it
    was started after and its log). Raises :class:`~gsrmr_sim.supervisor.ProcessDiedError` or TimeoutError."""
    events = sorted(link_events, key=lambda e: e.at_slot)
    pending = sorted(param_events, key=lambda e: e.at_slot)
    started: list[tuple[ParamEvent, subprocess.Popen, int, Path]] = []
    first: dict[str, int | None] = dict.fromkeys(runs)
    from_radio: set[str] = set()
    done: dict[str, int] = dict.fromkeys(runs, 0)
    deadline = time.monotonic() + timeout_s
    last_report = 0.0
    while time.monotonic() < deadline:
        time.sleep(POLL_S)
        stack.check()
        for name, run in runs.items():
            if done[name] >= slots:
                continue
            rows = run.rows_so_far()
            if first[name] is None:
                first[name] = first_round_row(rows, moved_key_fallback=RADIO not in run.processes)
            if first[name] is None and RADIO in run.processes:  # no round slot reached the server
                first[name] = radio_round_row(rows, stack.log(run.processes[RADIO]))
                if first[name] is not None:
                    from_radio.add(name)
                    log(f"{run.label}: its server saw no round slot: the round starts at the simulated radio's first "
                        f"round slot")
            if first[name] is not None:
                done[name] = len(rows) - first[name]
        meter.take()
        least = min(done.values())
        while net is not None and events and least >= events[0].at_slot:
            event = events.pop(0)
            event.apply(net)
            if link_log is not None:
                link_log.setdefault("events", []).append(
                    {**event.as_dict(), "applied_after_slot": least, "wall_s": time.time()})
            log(f"link: {event.describe()} (round slot ~{least}{' of every robot' if fleet else ''})")
        while pending and least >= pending[0].at_slot:
            param = pending.pop(0)
            out = stack.log_dir / f"param_set_{len(started)}.log"
            started.append((param, param.start(stack.env, out), least, out))
            log(f"{param.describe()} (round slot ~{least})")
        if least >= slots:
            break
        if time.monotonic() - last_report > PROGRESS_LOG_S:
            if fleet:
                log(f"{label}: " + ", ".join(f"{n} {min(d, slots)}/{slots}" for n, d in done.items()) + " slots")
            else:
                log(f"{label}: {min(least, slots)}/{slots} slots")
            last_report = time.monotonic()
    else:
        every = f" for every robot in {timeout_s:.0f} s: {done}" if fleet else f" in {timeout_s:.0f} s"
        raise TimeoutError(f"{label} did not produce {slots} slots{every}")
    for name, run in runs.items():
        run.first_moving = int(first[name])  # type: ignore[arg-type]
        run.round_start = "radio log" if name in from_radio else "slots.csv"
    return started


def _finish_param_events(started: Sequence[tuple[ParamEvent, subprocess.Popen, int, Path]], param_log: list | None,
                         log: Callable[[str], None], timeout_s: float = 30.0) -> None:
    """Wait for the started ``ros2 param set`` commands (at most ``timeout_s`` each, then killed) and record each
    one in ``param_log``: the event, the round slot it started after, its exit code and its output's last line."""
    for event, proc, after_slot, out in started:
        try:
            rc = proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            rc = proc.wait()
        lines = [line for line in out.read_text(errors="replace").splitlines() if line.strip()]
        answer = lines[-1] if lines else ""
        if rc != 0:
            log(f"{event.describe()} failed ({rc}): {answer}")
        if param_log is not None:
            param_log.append({**event.as_dict(), "started_after_slot": after_slot, "returncode": rc,
                              "answer": answer})


def _count_cpu(specs: Sequence[ProcessSpec], stack: ProcessStack, runs: Mapping[str, RobotRun],
               usage: RoundUsage) -> None:
    """Each run's ``cpu``: CPU seconds per node (``by_node_cpu_s``) and per group (``<group>_cpu_s``), the window,
    the machine's busy cores and those of everything else, and cores per group (:func:`cpu_group`)."""
    for spec in specs:
        run = runs[spec.namespace.strip("/")]
        used = usage.by_group_s.get(stack.procs[process_name(spec)].pid, 0.0)
        run.cpu.setdefault("by_node_cpu_s", {})[spec.name] = round(used, 3)
        group = cpu_group(spec)
        run.cpu[f"{group}_cpu_s"] = run.cpu.get(f"{group}_cpu_s", 0.0) + used
    for run in runs.values():
        run.cpu["window_s"] = usage.window_s
        # every core of the machine: the processes of the stack, this runner, and whatever else runs here
        run.cpu["machine_busy_cores"] = usage.machine_busy_cores
        run.cpu["other_cores"] = usage.other_cores
        for group in CPU_GROUPS:
            run.cpu[f"{group}_cores"] = run.cpu.get(f"{group}_cpu_s", 0.0) / usage.window_s
