"""CPU a stack's processes spend during a round (``gsrmr-demo``'s runner, :mod:`gsrmr_sim.stack_runner`).

A :class:`CpuMeter` takes snapshots of each process group's CPU seconds (:func:`cpu_seconds_by_group`) and of the
machine's busy time while the round runs; :meth:`CpuMeter.round_usage` turns the round's window into CPU seconds
per process and cores of the whole machine, grouped by what the processes stand for (:func:`cpu_group`).
"""

from __future__ import annotations

from collections.abc import Collection
from dataclasses import dataclass, field
import os
import time

from gsrmr_sim.sim_stack import ProcessSpec

# What each process stands for when its CPU is counted: the simulated world (hardware and physics on a real
# deployment, and the simulation's ground-truth scorer), the robot's own computer (robot node, LIMO driver) or the
# workstation (server, scheduler).
WORLD_EXECUTABLES = frozenset({"gsrmr-mock-limo", "gsrmr-mock-camera", "gsrmr-route-follower", "gsrmr-sim-channel",
                               "gsrmr-sim-scorer"})
CPU_GROUPS = ("server", "robot", "world")


def cpu_group(spec: ProcessSpec) -> str:
    """``world`` (the simulated world, the scorer), ``server`` (server, scheduler) or ``robot`` (robot node, LIMO
    driver)."""
    if spec.executable in WORLD_EXECUTABLES:
        return "world"
    return "server" if spec.host == "server" else "robot"


def cpu_seconds_by_group() -> dict[int, float]:
    """CPU seconds (user + system, own and of reaped children) of every live process, summed per process group.

    The supervisor starts each node in its own process group (:data:`~gsrmr_sim.supervisor.OWN_PROCESS_GROUP`;
    ``nice`` and ``ip netns exec`` exec the node), so a node's group id is its Popen pid and the sum covers its
    threads and any children.
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
        group = int(fields[2])  # field 5 (pgrp)
        utime, stime, cutime, cstime = (int(v) for v in fields[11:15])  # fields 14-17
        out[group] = out.get(group, 0.0) + (utime + stime + cutime + cstime) / tick
    return out


def machine_busy_seconds() -> float:
    """CPU seconds the whole machine has been busy (every core; ``/proc/stat``: all but idle and iowait)."""
    with open("/proc/stat") as f:
        values = [int(v) for v in f.readline().split()[1:]]
    return (sum(values[:8]) - values[3] - values[4]) / os.sysconf("SC_CLK_TCK")


@dataclass(frozen=True)
class CpuSnapshot:
    """CPU seconds of the watched process groups and of the machine at one wall-clock time."""

    wall_s: float  # time.time()
    by_group_s: dict[int, float]
    machine_busy_s: float


@dataclass(frozen=True)
class RoundUsage:
    """CPU over a round's window: seconds per watched process group, and the machine's cores."""

    window_s: float
    by_group_s: dict[int, float]
    machine_busy_cores: float  # every core of the machine: the watched processes, the runner, anything else
    other_cores: float  # the machine's busy cores less the watched processes'


@dataclass
class CpuMeter:
    """Snapshots of the CPU of the process groups ``pids`` and of the machine (see the module docstring)."""

    pids: Collection[int]
    snapshots: list[CpuSnapshot] = field(default_factory=list)

    def take(self) -> CpuSnapshot:
        """Take one snapshot now (kept in :attr:`snapshots`)."""
        watched = set(self.pids)
        snap = CpuSnapshot(time.time(), {pid: v for pid, v in cpu_seconds_by_group().items() if pid in watched},
                           machine_busy_seconds())
        self.snapshots.append(snap)
        return snap

    def round_usage(self, round_start_s: float) -> RoundUsage:
        """CPU from the last snapshot taken by ``round_start_s`` (wall clock; else the first) to the last one."""
        if not self.snapshots:
            raise ValueError("no CPU snapshot taken")
        end = self.snapshots[-1]
        start = max((s for s in self.snapshots if s.wall_s <= round_start_s), default=self.snapshots[0],
                    key=lambda s: s.wall_s)
        window_s = end.wall_s - start.wall_s
        if window_s <= 0:
            raise ValueError("the CPU window is empty: take a snapshot after the round's start")
        used = {pid: end.by_group_s.get(pid, 0.0) - start.by_group_s.get(pid, 0.0) for pid in self.pids}
        machine = (end.machine_busy_s - start.machine_busy_s) / window_s
        return RoundUsage(window_s, used, machine, machine - sum(used.values()) / window_s)
